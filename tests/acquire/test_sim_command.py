"""``acquire sim`` started as a user starts it (a separate process), every device it prints met
by an independent client: OptiTrack's ``natnetsdk`` (NatNet 4.1), Leica's protocol through
CESAPI (emScon), KUKA's FRI messages through Google's protobuf runtime built from the SDK's
field tables (FRI 2.5), and the line-protocol tracker through our client; faults typed on its
stdin reach those clients (a stalled Motive, a broken beam refused by CESAPI)."""

from __future__ import annotations

import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from drivers.sim.cell import SimCell
from drivers.tracker.client import TrackerSensor

from run_helpers import ROOT, acquire_cmd  # noqa: E402 - tests/acquire is on sys.path under pytest

for sub in ("natnet", "kuka_fri", "emscon"):
    sys.path.insert(0, str(ROOT / "tests" / "drivers" / sub))
from fri_proto import messages  # noqa: E402
from natnet_helpers import natnetsdk_client, stop_natnetsdk, wait_until  # noqa: E402

pytest.importorskip("natnetsdk.NatNetClient", reason="natnetsdk (OptiTrack's client) is the NatNet peer")
pytest.importorskip("CESAPI.connection", reason="CESAPI 1.1.3 is the emScon peer")
from CESAPI import packet as P  # noqa: E402
from CESAPI.connection import Connection  # noqa: E402
from cesapi_helpers import execute as cesapi_execute  # noqa: E402

pytestmark = pytest.mark.timeout(120)
WAIT_S = 30.0


class Sim:
    """``acquire sim`` in a subprocess: its printed addresses, its stdout lines, its stdin."""

    def __init__(self, *args: str) -> None:
        import os

        env = dict(os.environ, PYTHONPATH=str(ROOT))
        self.proc = subprocess.Popen(acquire_cmd("sim", *args), cwd=ROOT, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self.pump = threading.Thread(target=self._pump, daemon=True)
        self.pump.start()
        self.addresses: dict[str, str] = {}
        self.wait_line(lambda line: line.startswith("running for up to"))
        for line in self.seen:
            parts = line.split()
            if len(parts) > 2 and "://" in parts[1]:
                self.addresses[parts[0]] = parts[1]

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def wait_line(self, predicate, timeout: float = WAIT_S) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.seen.append(line)
            if predicate(line):
                return line
        raise AssertionError(f"acquire sim never printed the line; it printed:\n" + "\n".join(self.seen))

    def fault(self, line: str) -> str:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return self.wait_line(lambda out: out.startswith(("fault ", "error: ")))

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.pump.join(timeout=10)
        self.proc.stdin.close()
        self.proc.stdout.close()


def port(url: str) -> tuple[str, int]:
    host, _, p = url.split("://", 1)[1].rpartition(":")
    return host, int(p)




@pytest.mark.slow  # ~30 s; a separately started acquire sim driven by a fake run is test_cell_is_a_cell.py's (default)
def test_acquire_sim_serves_every_device_to_independent_clients(tmp_path):
    cell = yaml.safe_load((ROOT / "fixtures" / "sim" / "default.yaml").read_text())
    cell["robot"] = str((ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").resolve())
    cell["sensors"][0]["natnet"] = {"version": 4.1}  # YAML numbers, as a user writes them
    cell["sensors"][1]["protocols"] = ["line", "emscon"]
    cell["controller"] = {"fri_version": 2.5}
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cell, sort_keys=False))
    truth = SimCell.from_yaml(path)
    q0 = truth.joint_positions()

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fri_client:
        fri_client.bind(("127.0.0.1", 0))
        fri_client.settimeout(WAIT_S)
        sim = Sim("--config", str(path), "--fri-port", str(fri_client.getsockname()[1]), "--duration", "100")
        try:
            assert sim.addresses["mocap"].startswith("natnet://127.0.0.1:")
            assert sim.addresses["tracker"].startswith("socket://127.0.0.1:")
            assert sim.addresses["tracker-emscon"].startswith("emscon://127.0.0.1:")
            assert sim.addresses["controller"].startswith("udp://127.0.0.")  # the fake Sunrise may send from 127.0.0.2
            assert any("NatNet 4.1" in line for line in sim.seen) and any("FRI 2.5" in line for line in sim.seen)
            assert any(line.startswith("faults: one line on stdin") for line in sim.seen)

            # FRI 2.5, decoded by protobuf from KUKA's SDK tables
            monitoring, _ = messages("2.5")
            msg = monitoring.FromString(fri_client.recv(65536))
            assert list(msg.monitorData.measuredJointPosition.value) == pytest.approx(q0, abs=1e-9)

            # NatNet 4.1 through natnetsdk; the Motive is stalled from stdin while it connects
            assert sim.fault("sensor_stall mocap 3") == "fault sensor_stall on mocap for 3 s"
            cmd_port = port(sim.addresses["mocap"])[1]
            note = next(line for line in sim.seen if line.startswith("mocap "))
            data_port = int(note.split("data port ")[1].split(",")[0])
            fake = SimpleNamespace(command_port=cmd_port, data_port=data_port, multicast_group="239.255.42.99")
            client, decoded = natnetsdk_client(fake, multicast=False)
            assert client.run()
            try:
                assert wait_until(lambda: client.connected() and client.get_major() == 4, timeout=10.0)
                assert client.get_nat_net_version_server()[:2] == [4, 1]
                assert wait_until(lambda: len(decoded) >= 3, timeout=15.0), "no frames after the stall"
            finally:
                stop_natnetsdk(client, fake)
            sir = truth.true_marker_positions(q0, frame="mocap")[truth.marker_names.index("sir")]
            (lm,) = decoded[-1][2].labeled_marker_data.labeled_marker_list
            np.testing.assert_allclose(np.asarray(lm.pos) * 1000.0, sir, atol=0.3)
            assert decoded[-1][3] == (4, 1)

            # emScon through CESAPI: a point where the truth is; refused while the beam is broken
            smr = truth.true_marker_positions(q0, frame="tracker")[truth.marker_names.index("smr")]
            conn = Connection()
            host, eport = port(sim.addresses["tracker-emscon"])
            stream = conn.connect(host=host, port=eport)
            try:
                assert cesapi_execute(stream, P.InitializeCT()).packetInfo.status == P.ES_RS_AllOK
                units = P.SetUnitsCT()
                units.unitsSettings.lenUnitType = P.ES_LU_Millimeter
                assert cesapi_execute(stream, units).packetInfo.status == P.ES_RS_AllOK
                got = cesapi_execute(stream, P.StartMeasurementCT(), result=True)
                assert got.packetInfo.status == P.ES_RS_AllOK
                np.testing.assert_allclose([got.dVal1, got.dVal2, got.dVal3], smr, atol=0.3)
                assert sim.fault("beam_break tracker 60") == "fault beam_break on tracker for 60 s"
                broken = cesapi_execute(stream, P.StartMeasurementCT(), result=True)
                assert broken.packetInfo.status != P.ES_RS_AllOK
            finally:
                conn.disconnect()

            # the line protocol: the same tracker, beam still broken → not visible
            tracker = TrackerSensor(sim.addresses["tracker"])
            tracker.connect()
            try:
                (sample,) = tracker.read(timeout=5.0)
                assert not sample.visible and not tracker.status().locked
            finally:
                tracker.close()
            assert sim.fault("drives_off mocap").startswith("error: drives_off does not apply to 'mocap'")
        finally:
            sim.close()


def test_a_key_in_the_terminal_injects_a_fault_and_q_quits():
    """On a terminal (a pty here) ``acquire sim`` prints its one-line key help; ``b`` breaks the
    beam of every sensor, ``x`` does nothing, ``q`` stops the cell."""
    import os
    import pty

    master, slave = pty.openpty()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(acquire_cmd("sim", "--duration", "60", "--fri-port", "1"), cwd=ROOT, env=env,
                            stdin=slave, stdout=slave, stderr=subprocess.DEVNULL)
    os.close(slave)
    out = b""

    def read_until(text: bytes, timeout: float = WAIT_S) -> bytes:
        nonlocal out
        deadline = time.monotonic() + timeout
        while text not in out and time.monotonic() < deadline:
            import select

            if select.select([master], [], [], 0.1)[0]:
                try:
                    out += os.read(master, 4096)
                except OSError:
                    break
        assert text in out, out.decode(errors="replace")
        return out

    try:
        read_until(b"running for up to")
        assert b"keys: d session drop, o drives off, b beam break" in out
        os.write(master, b"b")
        read_until(b"fault beam_break on mocap, tracker for 3 s")
        os.write(master, b"q")
        read_until(b"stopped; final joints")
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)


def test_acquire_sim_plays_a_kr_c4_to_an_rsi_client_written_with_elementtree():
    """The packaged KR C4 cell: RSI state packets read with the standard library's ElementTree
    (as ROS-Industrial's RSI code reads them) and answered with hand-written ``<Sen>`` XML that
    move A1; the robot follows, and a ``controller_restart`` typed on stdin restarts the IPOC."""
    import xml.etree.ElementTree as ET

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client:
        client.bind(("127.0.0.1", 0))
        client.settimeout(WAIT_S)
        sim = Sim("--config", "kr6_rsi", "--rsi-port", str(client.getsockname()[1]), "--duration", "60",
                  "--time-scale", "0.25")
        try:
            assert any("fake KR C4 (RSI)" in line for line in sim.seen)

            def exchange(n: int, a1: float) -> list[ET.Element]:
                got = []
                for _ in range(n):
                    data, peer = client.recvfrom(65536)
                    rob = ET.fromstring(data)
                    got.append(rob)
                    ipoc = rob.find("IPOC").text
                    sen = (f'<Sen Type="ImFree"><AK A1="{a1:.4f}" A2="0.0" A3="0.0" A4="0.0" A5="0.0" A6="0.0" />'
                           f"<IPOC>{ipoc}</IPOC></Sen>")
                    client.sendto(sen.encode(), peer)
                return got

            first = exchange(5, 0.0)
            assert first[0].tag == "Rob"
            start = float(first[0].find("AIPos").get("A1"))
            moved = exchange(150, 2.0)  # an absolute correction of +2° on A1
            assert float(moved[-1].find("AIPos").get("A1")) == pytest.approx(start + 2.0, abs=0.1)
            before = int(moved[-1].find("IPOC").text)
            assert sim.fault("controller_restart controller") == "fault controller_restart on controller"
            after = [int(r.find("IPOC").text) for r in exchange(50, 0.0)]
            assert min(after) < before
        finally:
            sim.close()


@pytest.mark.parametrize("args, message", [
    (["--natnet-version", "5.0"], "given '5.0'; allowed: 3.0, 3.1, 4.0, 4.1"),
    (["--mocap-asset", "glove"], "allowed: rigid_body, skeleton, trained_markerset"),
    (["--tracker-protocols", "line,leica"], "allowed: line, emscon or line,emscon"),
    (["--mocap-asset", "trained_markerset", "--natnet-version", "4.0"], "trained_markerset asset needs NatNet 4.1"),
])
def test_acquire_sim_refuses_what_no_fake_speaks_and_starts_nothing(args, message):
    from typer.testing import CliRunner

    from acquire.cli import app

    result = CliRunner().invoke(app, ["sim", "--duration", "0.2", "--fri-port", "1", *args])
    assert result.exit_code == 2, result.output
    assert message in " ".join(result.output.replace("│", " ").split()), result.output
    assert "running for up to" not in result.output
