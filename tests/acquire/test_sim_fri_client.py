"""An outside FRI client against ``acquire sim``, behaving as KUKA's SDK example
``LBRJointSineOverlay`` does, hand-encoded here (``struct``, ``zlib``; not our codec):

- its receive blocks, without a timeout (the SDK's default);
- given a controller host it ``connect()``s to host:port, so it takes datagrams only from the
  controller's FRI port (the 1.15 ``UdpConnection::open``);
- it answers every message outside IDLE (monitoring: the commanded position in 1.x, a header
  only in 2.x; COMMANDING_WAIT: the ipo position; COMMANDING_ACTIVE: ipo + a sine on A4);
- it leaves its loop as soon as it reads session state IDLE ("the FRI session was closed");
- SDK 2.7 frames every datagram (length, message, CRC-32) and refuses a bad checksum.

Started before the sim, it runs 30 s and ends by itself when the sim's ``--duration`` ends;
started after the sim, it joins the running application and ends on Ctrl-C (SIGINT)."""

from __future__ import annotations

import math
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib

import numpy as np
import pytest

RUN_S = 30.0
AMPLITUDE_RAD = 0.04  # the SDK example's defaults: 0.04 rad, 0.25 Hz, joint mask A4
FREQUENCY_HZ = 0.25
JOINT = 3
CONTROLLER_HOST = "127.0.0.2"  # where the fake Sunrise sends from (its FRI port)
IDLE, MONITORING_WAIT, MONITORING_READY, COMMANDING_WAIT, COMMANDING_ACTIVE = range(5)


# -- a minimal protobuf reader and writer, from the wire-format spec ------------------------------

def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, pos


def fields(buf: bytes) -> dict[int, list]:
    """Field number -> values (int for varints, bytes for the rest), in order."""
    out: dict[int, list] = {}
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        fn, wt = key >> 3, key & 7
        if wt == 0:
            v, pos = _varint(buf, pos)
        elif wt == 1:
            v, pos = buf[pos:pos + 8], pos + 8
        elif wt == 2:
            n, pos = _varint(buf, pos)
            v, pos = buf[pos:pos + n], pos + n
        elif wt == 5:
            v, pos = buf[pos:pos + 4], pos + 4
        else:
            raise ValueError(f"wire type {wt}")
        out.setdefault(fn, []).append(v)
    return out


def joint_values(payload: bytes) -> list[float]:
    return [struct.unpack("<d", raw)[0] for raw in fields(payload).get(1, [])]


def enc_varint(v: int) -> bytes:
    out = bytearray()
    while v >= 0x80:
        out.append((v & 0x7F) | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def enc_len(fn: int, payload: bytes) -> bytes:
    return enc_varint(fn << 3 | 2) + enc_varint(len(payload)) + payload


def command(seq: int, reflected: int, q) -> bytes:
    """FRICommandMessage: header (id 0x34001, seq, reflected), commandData.jointPosition."""
    header = b"\x08" + enc_varint(0x34001) + b"\x10" + enc_varint(seq) + b"\x18" + enc_varint(reflected)
    msg = enc_len(1, header)
    if q is not None:
        jv = b"".join(b"\x09" + struct.pack("<d", float(x)) for x in q)
        msg += enc_len(2, enc_len(1, jv))
    return msg


class SdkStyleClient(threading.Thread):
    """The SDK example's main loop in a thread; ``ended`` says why it left."""

    def __init__(self, port: int, version: str, controller_host: str | None) -> None:
        super().__init__(name=f"sdk-style-client-{version}", daemon=True)
        self.version = version
        self.framed = version == "2.7"
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        if controller_host is not None:
            self.sock.connect((controller_host, port))  # only the controller's FRI port gets through
        self.states: list[int] = []
        self.measured: list[list[float]] = []
        self.stamps: list[float] = []
        self.senders: set = set()
        self.ipo_first = None
        self.t_first = self.t_active = self.t_end = None
        self.ended = "running"

    def _unframe(self, data: bytes) -> bytes:
        if not self.framed:
            return data
        (n,) = struct.unpack_from("<I", data, 0)
        body = data[4:4 + n]
        if len(data) != n + 8 or struct.unpack_from("<I", data, 4 + n)[0] != zlib.crc32(body):
            raise ValueError("bad FRI 2.7 frame")
        return body

    def run(self) -> None:
        seq, phi = 0, 0.0
        try:
            while True:
                data, addr = self.sock.recvfrom(4096)  # blocks, as the SDK's receive does
                self.senders.add(addr)
                if self.t_first is None:
                    self.t_first = time.monotonic()
                m = fields(self._unframe(data))
                header = fields(m[1][0])
                ci = fields(m[4][0])
                state, period_ms = ci[1][0], ci[3][0]
                self.states.append(state)
                md = fields(m[3][0])
                ts = fields(md[15][0])
                self.stamps.append(ts[1][0] + ts[2][0] * 1e-9)
                if state == IDLE:
                    self.ended = "idle"  # "the FRI session was closed": leave the main loop
                    return
                ipo = fields(m[5][0]) if 5 in m else {}
                q = None
                if self.version == "1.15" and state in (MONITORING_WAIT, MONITORING_READY):
                    q = joint_values(md[3][0])  # LBRClient::monitor(): the commanded position
                elif state == COMMANDING_WAIT:
                    q = joint_values(ipo[1][0])  # waitForCommand(): the ipo position
                elif state == COMMANDING_ACTIVE:
                    q = np.asarray(joint_values(ipo[1][0]))
                    if self.t_active is None:
                        self.t_active, self.ipo_first = time.monotonic(), q.copy()
                    q[JOINT] += AMPLITUDE_RAD * math.sin(phi)
                    phi += 2 * math.pi * FREQUENCY_HZ * period_ms / 1000.0
                    self.measured.append(joint_values(md[1][0]))
                out = command(seq, header[2][0], q)
                if self.framed:
                    out = struct.pack("<I", len(out)) + out + struct.pack("<I", zlib.crc32(out))
                self.sock.sendto(out, addr)
                seq += 1
        except OSError as exc:  # the test closed the socket: still blocked when it gave up
            self.ended = f"socket closed while blocked on receive ({exc})"
        except Exception as exc:  # noqa: BLE001 - the SDK quits on a decoding error
            self.ended = f"decoding error: {exc!r}"
        finally:
            self.t_end = time.monotonic()

    def finish(self, timeout: float) -> None:
        self.join(timeout)
        if self.is_alive():
            self.sock.close()
            self.join(5.0)
        self.sock.close()


def _sim(port: int, version: str, duration: float) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "acquire", "sim", "--fri-port", str(port), "--fri-version", version,
         "--duration", str(duration), "--time-scale", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def _free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize("version", ["1.15", "2.5", "2.7"])
def test_an_sdk_style_client_started_first_runs_30_s_and_ends_when_the_sim_does(version):
    port = _free_port()
    client = SdkStyleClient(port, version, CONTROLLER_HOST)
    client.start()  # blocked on receive before the sim exists
    time.sleep(0.2)
    proc = _sim(port, version, RUN_S + 5.0)  # ~5 s: the process start and the session opening
    try:
        client.finish(RUN_S + 90.0)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert client.ended == "idle", f"{client.ended}; states {sorted(set(client.states))}\n{out}"
    assert proc.returncode == 0, out
    assert client.states[0] == MONITORING_WAIT  # the application opened the session: no IDLE first
    assert client.t_active is not None, f"never commanding; states {sorted(set(client.states))}\n{out}"
    assert client.t_end - client.t_first >= RUN_S - 1.0
    assert client.senders == {(CONTROLLER_HOST, port)}  # from the FRI port
    assert len(client.states) > 2000  # ~6000 at 5 ms
    first = client.states.index(COMMANDING_ACTIVE)
    tail = client.states[first:-1]
    dropped = len(tail) - tail.count(COMMANDING_ACTIVE)
    assert dropped < 0.05 * len(tail), f"{dropped} of {len(tail)} messages outside COMMANDING_ACTIVE\n{out}"
    assert abs(client.stamps[-1] - time.time()) < 120.0  # the controller's clock: time of day
    a4 = np.asarray(client.measured)[:, JOINT] - client.ipo_first[JOINT]
    assert np.ptp(a4) > 1.5 * AMPLITUDE_RAD  # the robot followed the overlay, both ways
    # and did not run away: had the ipo taken up each command, A4 would add up the overlay every
    # 5 ms cycle and be radians away within half a period. Not tighter: a servo a step behind after a
    # late answer overshoots (1.20×, 0.0481 rad, seen under four CPU hogs).
    assert np.max(np.abs(a4)) < 1.5 * AMPLITUDE_RAD


@pytest.mark.timeout(120)
def test_an_sdk_style_client_started_after_the_sim_joins_and_ends_on_ctrl_c():
    port = _free_port()
    proc = _sim(port, "2.7", 120.0)
    try:
        line = proc.stdout.readline()
        while line and "running for up to" not in line:
            line = proc.stdout.readline()
        client = SdkStyleClient(port, "2.7", CONTROLLER_HOST)
        client.start()
        deadline = time.monotonic() + 30.0
        while client.t_active is None and client.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert client.t_active is not None, f"{client.ended}; states {sorted(set(client.states))}"
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        client.finish(30.0)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert client.ended == "idle", f"{client.ended}\n{out}"
    assert "stopping" in out
