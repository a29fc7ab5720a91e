"""Faults on demand in the simulated cell: the cell file's ``faults:`` timeline fires and a client
sees it on the wire; a bad timeline is refused naming file, line and what is allowed; each
injected fault reaches the fake it names. Real sockets, generous waits."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest

from calib.io.yamlfile import ConfigError
from drivers.kuka_fri.messages import DriveState, decode_monitoring
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH, load_sim_config
from drivers.sim.faults import FaultError, parse_command
from drivers.sim.launch import SimLaunch
from drivers.tracker.client import TrackerSensor

WAIT_S = 15.0
ROBOT = (DEFAULT_CONFIG_PATH.parent.parent / "robots" / "kuka_iiwa14_r820.yaml").resolve()


def cell_file(tmp_path: Path, extra: str, name: str = "cell.yaml") -> Path:
    """The default cell with its robot path made absolute and ``extra`` YAML appended."""
    text = DEFAULT_CONFIG_PATH.read_text(encoding="utf-8")
    text = text.replace("robot: ../robots/kuka_iiwa14_r820.yaml", f"robot: {ROBOT}")
    path = tmp_path / name
    path.write_text(text + extra, encoding="utf-8")
    return path


def wait_for(predicate, timeout: float = WAIT_S, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return bool(predicate())


def test_a_scripted_beam_break_is_seen_by_our_tracker_client_then_recovered(tmp_path):
    path = cell_file(tmp_path, "faults:\n  - {at_s: 1.0, fault: beam_break, device: tracker, duration_s: 1.5}\n")
    cell = SimCell.from_yaml(path)
    with SimLaunch(cell, controller=False) as launch:
        assert launch.timeline is not None and len(launch.timeline.steps) == 1
        tracker = TrackerSensor(launch.addresses["tracker"].url)
        tracker.connect()
        try:
            (before,) = tracker.read(timeout=5.0)
            assert before.visible and tracker.status().locked
            lost: list = []
            assert wait_for(lambda: lost.append(tracker.read(timeout=5.0)[0]) or not lost[-1].visible), (
                "the scripted beam break never reached the tracker client")
            assert not tracker.status().locked
            assert any(e.name == "BEAM_LOST" for e, _ in tracker.events)
            assert wait_for(lambda: ("beam_break", "tracker", "off") in [h[1:] for h in launch.faults.history])
            assert launch.timeline.fired == 1
            # the line of sight is back, but a tracker keeps its beam lost until re-acquired
            assert not tracker.status().locked
            tracker.reacquire(before.position_mm, timeout=10.0)
            (after,) = tracker.read(timeout=5.0)
            assert after.visible and tracker.status().locked
            np.testing.assert_allclose(after.position_mm, before.position_mm, atol=0.5)  # the robot did not move
        finally:
            tracker.close()


@pytest.mark.parametrize("faults, message", [
    ("  - {at_s: 1, fault: beam_break, device: controller}\n",
     r"faults\.1\.device: beam_break does not apply to 'controller' \(given 'controller'; allowed: mocap, tracker\)"),
    ("  - {at_s: 1, fault: beam_break, device: laser}\n",
     r"faults\.1\.device: no device 'laser' in this cell .*allowed: mocap, tracker, controller"),
    ("  - {at_s: 1, fault: meteor_strike}\n", r"faults\.1\.fault: .*'session_drop'.*'packet_loss'"),
    ("  - {at_s: 1, fault: controller_restart, duration_s: 3}\n", r"faults\.1: .*controller_restart is an event"),
    ("  - {at_s: -1, fault: sensor_stall}\n", r"faults\.1\.at_s: .*greater than or equal to 0"),
])
def test_a_bad_fault_timeline_names_file_line_and_what_is_allowed(tmp_path, faults, message):
    path = cell_file(tmp_path, "faults:\n  - {at_s: 0, fault: sensor_stall, device: mocap}\n" + faults)
    with pytest.raises(ConfigError, match=message) as err:
        load_sim_config(path)
    lines = path.read_text().splitlines()
    assert f"{path}:{len(lines)}:" in str(err.value)  # the offending entry is the file's last line


def test_cell_file_fields_for_what_the_fakes_speak_are_checked(tmp_path):
    path = cell_file(tmp_path, "controller: {fri_version: 2.7}\n")
    assert load_sim_config(path).controller.fri_version == "2.7"  # YAML's number read as the version text
    bad = cell_file(tmp_path, "controller: {fri_version: 3.0}\n", "bad.yaml")
    with pytest.raises(ConfigError, match=r"bad\.yaml:\d+:\d+: controller\.fri_version: .*'1\.15', '2\.5' or '2\.7'"):
        load_sim_config(bad)
    text = DEFAULT_CONFIG_PATH.read_text().replace("robot: ../robots/kuka_iiwa14_r820.yaml", f"robot: {ROBOT}")
    markerset = tmp_path / "ms.yaml"
    assert "natnet: {cluster_radius_mm: 30}" in text
    markerset.write_text(text.replace("natnet: {cluster_radius_mm: 30}",
                                      "natnet: {version: 4.0, asset: trained_markerset, cluster_radius_mm: 30}"))
    with pytest.raises(ConfigError, match=r"ms\.yaml:\d+:\d+: sensors\.0\.natnet: .*trained_markerset needs NatNet version 4\.1"):
        load_sim_config(markerset)


def test_stdin_fault_lines_parse_or_say_the_format():
    f = parse_command("packet_loss controller 2.5 0.3")
    assert (f.fault, f.device, f.duration_s, f.probability) == ("packet_loss", "controller", 2.5, 0.3)
    assert parse_command("beam_break all").device is None
    for bad in ("", "meteor", "beam_break tracker soon", "beam_break tracker -1", "packet_loss - 1 2"):
        with pytest.raises(FaultError, match="FAULT \\[DEVICE\\|all\\]"):
            parse_command(bad)


def fri_messages(sock: socket.socket, n: int):
    out = []
    for _ in range(n):
        out.append(decode_monitoring(sock.recv(65536)))
    return out


def test_injected_faults_reach_the_fake_controller_and_sensors():
    """drives_off shows as drive state OFF in the Sunrise's monitoring messages and ACTIVE again
    after its duration; a NatNet stall stops the frames for its duration; a tracker session drop
    closes the TCP connection; a fault aimed where it does not apply is refused."""
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, clock=SimClock(1.0))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fri_client:
        fri_client.bind(("127.0.0.1", 0))
        fri_client.settimeout(WAIT_S)
        with SimLaunch(cell, fri_port=fri_client.getsockname()[1], max_runtime_s=60, operator=False) as launch:
            drives = lambda: set(fri_messages(fri_client, 3)[-1].robot_info.drive_state)  # noqa: E731
            assert drives() == {DriveState.ACTIVE}
            assert launch.inject("drives_off", "controller", duration_s=1.5) == ["controller"]
            assert wait_for(lambda: drives() == {DriveState.OFF}, timeout=5.0)
            assert wait_for(lambda: drives() == {DriveState.ACTIVE}, timeout=10.0), "the drives never came back"

            motive = launch.motives["mocap"]
            launch.inject("sensor_stall", "mocap", duration_s=2.0)
            n0 = motive.frames_sent
            time.sleep(0.5)
            assert motive.frames_sent == n0  # no frame while stalled
            assert wait_for(lambda: motive.frames_sent > n0 + 10)  # and streaming again after

            server = launch.trackers["tracker"][1]
            with socket.create_connection((server.host, server.port), timeout=WAIT_S) as conn:
                conn.sendall(b"x\n")  # one line: the server has accepted us
                assert wait_for(lambda: server.connection_count == 1)
                conn.recv(4096)
                launch.inject("session_drop", "tracker")
                conn.settimeout(WAIT_S)
                assert conn.recv(4096) == b""  # closed by the tracker

            with pytest.raises(FaultError, match=r"drives_off does not apply to 'mocap' \(natnet\)"):
                launch.inject("drives_off", "mocap")
            with pytest.raises(FaultError, match=r"no device 'laser'.*controller, mocap, tracker"):
                launch.inject("beam_break", "laser")


def test_packet_loss_shows_as_gaps_in_the_fri_counter_and_the_natnet_frame_numbers():
    from drivers.natnet import codec as natnet

    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, clock=SimClock(1.0))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fri_client, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as natnet_client:
        for s in (fri_client, natnet_client):
            s.bind(("127.0.0.1", 0))
            s.settimeout(WAIT_S)
        with SimLaunch(cell, fri_port=fri_client.getsockname()[1], max_runtime_s=60, operator=False) as launch:
            natnet_client.sendto(natnet.encode_packet(natnet.Connect(layout="ping")),
                                 ("127.0.0.1", launch.addresses["mocap"].port))

            def counters(sock, n, decode):
                return [decode(sock.recv(65536)) for _ in range(n)]

            def frame_no(data):
                msg = natnet.decode_packet(data, (3, 0, 0, 0))
                return msg.frame_number if isinstance(msg, natnet.FrameOfData) else None

            def fri_no(data):
                return decode_monitoring(data).header.sequence_counter

            def gaps(numbers):
                numbers = [n for n in numbers if n is not None]
                return sum(b - a - 1 for a, b in zip(numbers, numbers[1:]))

            assert gaps(counters(fri_client, 100, fri_no)) == 0
            assert gaps(counters(natnet_client, 60, frame_no)) == 0
            launch.inject("packet_loss", None, duration_s=30.0, probability=0.5)
            fri_lost = gaps(counters(fri_client, 100, fri_no))
            natnet_lost = gaps(counters(natnet_client, 60, frame_no))
    assert fri_lost >= 20 and natnet_lost >= 15, (fri_lost, natnet_lost)  # about one in two lost


def test_rsi_session_drop_cuts_the_link_for_its_duration_and_a_restart_restarts_the_ipoc():
    from drivers.kuka_rsi.codec import SenFormatter, parse_rob

    data = load_sim_config(DEFAULT_CONFIG_PATH).model_dump()
    data["robot"] = str(DEFAULT_CONFIG_PATH.parent.parent / "robots" / "kuka_kr6_r900_2.yaml")
    data["initial_joint_positions_deg"] = [0, -90, 90, 0, 45, 0]
    data["deflection"] = {"link_masses_kg": None, "compliance_rad_per_nm": None}
    data["occlusion"] = {"link_radii_mm": None}
    from drivers.sim.config import SimConfig

    cell = SimCell(SimConfig.model_validate(data), clock=SimClock(time_scale=0.25))
    sen = SenFormatter(6)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as commander:
        commander.bind(("127.0.0.1", 0))
        commander.settimeout(WAIT_S)
        with SimLaunch(cell, rsi_port=commander.getsockname()[1], max_runtime_s=60, operator=False) as launch:
            def answer(n):
                ipocs = []
                for _ in range(n):
                    raw, peer = commander.recvfrom(65536)
                    rob = parse_rob(raw)
                    ipocs.append(rob.ipoc)
                    commander.sendto(sen.format([0.0] * 6, False, rob.ipoc), peer)
                return ipocs

            answer(20)
            with pytest.raises(FaultError, match=r"drives_off does not apply to 'controller' \(rsi\)"):
                launch.inject("drives_off", "controller")
            launch.inject("session_drop", "controller", duration_s=1.0)
            commander.settimeout(0.5)
            with pytest.raises(TimeoutError):
                while True:  # drain what was in flight, then silence
                    answer(1)
            commander.settimeout(WAIT_S)
            assert wait_for(lambda: ("session_drop", "controller", "off") in [h[1:] for h in launch.faults.history])
            before = answer(5)[-1]
            launch.inject("controller_restart", "controller")
            after = answer(50)
    assert min(after) < before  # the restarted program counts its IPOC from the start again


def test_the_commented_examples_in_the_default_cell_are_valid(tmp_path):
    """Uncommented, default.yaml's examples of natnet:, protocols:, controller: and faults: load."""
    import re

    text = DEFAULT_CONFIG_PATH.read_text(encoding="utf-8").replace(
        "robot: ../robots/kuka_iiwa14_r820.yaml", f"robot: {ROBOT}")
    text = text.replace("    natnet: {cluster_radius_mm: 30}", "    # (the rigid-body cluster gives way to the example)")
    text = re.sub(r"(?m)^(\s*)# (natnet|protocols|controller|faults)(:.*)$", r"\1\2\3", text)
    text = re.sub(r"(?m)^#(   - \{.*)$", r"\1", text)
    path = tmp_path / "examples.yaml"
    path.write_text(text, encoding="utf-8")
    config = load_sim_config(path)
    mocap, tracker = config.sensors
    assert (mocap.natnet.version, mocap.natnet.asset, tracker.protocols) == ("4.1", "skeleton", ["line", "emscon"])
    assert config.controller.fri_version == "2.7"
    assert [(f.at_s, f.fault, f.device) for f in config.faults] == [
        (12, "beam_break", "tracker"), (30, "packet_loss", "controller"), (60, "controller_restart", None)]
