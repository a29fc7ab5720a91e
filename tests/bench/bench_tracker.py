"""Benchmark: one tracker command round trip (MEAS) over TCP loopback and over a pty.

For each transport it measures, in the same run:

- ``echo``: a bare echo server on the same transport; the client sends the same request line
  through the same pyserial port and line reader and reads it back (transport floor);
- ``protocol``: ``TrackerSensor.read()`` against the fake tracker (encode, device logic with
  the scene, checksum, decode, sample record).

and prints p50 / p99 latency, the call rate (1 / mean latency), and protocol/echo ratios. The
two cases run interleaved in blocks so both see the same machine load. A codec-only line
(encode request + decode reply, no transport) is printed for scale.

Run: ``python tests/bench/bench_tracker.py [--n 3000]``. The fake's simulated measurement time
is set to 0 so only software and transport are timed.
"""

from __future__ import annotations

import argparse
import logging
import os
import select
import socket
import threading
import time
import tty

import numpy as np
import serial

from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerObservation
from drivers.tracker.client import LinePort, TrackerSensor
from drivers.tracker.codec import LineCodec, MeasurePoint, PointReply
from drivers.tracker.fake import FakeTracker, PtyTrackerServer, TcpTrackerServer

log = logging.getLogger("bench.tracker")


class FixedReflector:
    """A scene with one visible reflector at 2 m."""

    def observe(self, sensor: str) -> list[MarkerObservation]:
        return [MarkerObservation("smr", np.array([2000.0, 300.0, -100.0]), True)]


class EchoServer:
    """Echoes every byte back, on 127.0.0.1 TCP or on a pty; ``url`` to open with pyserial."""

    def __init__(self, kind: str) -> None:
        self._stop = threading.Event()
        if kind == "tcp":
            self._listen = socket.create_server(("127.0.0.1", 0))
            self.url = f"socket://127.0.0.1:{self._listen.getsockname()[1]}"
            target = self._tcp
        else:
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)
            self.url = os.ttyname(self._slave)
            target = self._pty
        self._thread = threading.Thread(target=target, daemon=True)
        self._thread.start()

    def _tcp(self) -> None:
        ready, _, _ = select.select([self._listen], [], [], 5.0)
        if not ready:
            return
        conn, _ = self._listen.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with conn:
            while not self._stop.is_set():
                r, _, _ = select.select([conn], [], [], 0.05)
                if r:
                    data = conn.recv(4096)
                    if not data:
                        return
                    conn.sendall(data)

    def _pty(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self._master], [], [], 0.05)
            if r:
                os.write(self._master, os.read(self._master, 4096))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        if hasattr(self, "_listen"):
            self._listen.close()
        else:
            os.close(self._master)
            os.close(self._slave)


def _stats(lat_s: list[float]) -> tuple[float, float, float]:
    a = np.asarray(lat_s)
    return float(np.percentile(a, 50) * 1e6), float(np.percentile(a, 99) * 1e6), len(a) / float(a.sum())


def bench_echo(port: LinePort, line: bytes, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        port.write(line)
        frame = port.read_frame(time.monotonic() + 2.0)
        out.append(time.perf_counter() - t0)
        if frame != line:
            raise RuntimeError(f"echo returned {frame!r} for {line!r}")
    return out


def bench_protocol(sensor: TrackerSensor, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        (sample,) = sensor.read(timeout=2.0)
        out.append(time.perf_counter() - t0)
        if not sample.visible:
            raise RuntimeError("the reflector should be visible")
    return out


def bench_codec(n: int) -> list[float]:
    host, dev = LineCodec(require_checksum=True), LineCodec()
    reply = dev.encode_reply(1, PointReply(2000.0021, 299.9987, -100.0004, 0.027, 12.101))
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        dev.decode_request(host.encode_request(1, MeasurePoint()))
        host.decode_reply(reply)
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3000, help="round trips per case (after 100 warm-up)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    line = LineCodec().encode_request(1, MeasurePoint())
    p50, p99, rate = _stats(bench_codec(args.n))
    print(f"codec only (encode MEAS + decode reply, both sides): p50 {p50:7.1f} µs  p99 {p99:7.1f} µs")
    print(f"{'transport':9} {'case':9} {'p50 µs':>9} {'p99 µs':>9} {'rate /s':>9}")
    for kind in ("tcp", "pty"):
        echo = EchoServer(kind)
        device = FakeTracker(FixedReflector(), clock=SimClock(time_scale=1.0), measure_time_s=0.0, seed=0)
        server = TcpTrackerServer(device) if kind == "tcp" else PtyTrackerServer(device)
        port = LinePort(serial.serial_for_url(echo.url, timeout=0), LineCodec.split_frames)
        sensor = TrackerSensor.from_url(server.url)
        e_lat: list[float] = []
        p_lat: list[float] = []
        try:
            bench_echo(port, line, 100)  # warm-up
            bench_protocol(sensor, 100)
            block = max(1, args.n // 10)
            for _ in range(10):  # interleave so both cases see the same machine load
                e_lat += bench_echo(port, line, block)
                p_lat += bench_protocol(sensor, block)
        finally:
            sensor.close()
            port.close()
            server.close()
            echo.close()
        e, p = _stats(e_lat), _stats(p_lat)
        print(f"{kind:9} {'echo':9} {e[0]:9.1f} {e[1]:9.1f} {e[2]:9.0f}")
        print(f"{kind:9} {'protocol':9} {p[0]:9.1f} {p[1]:9.1f} {p[2]:9.0f}")
        print(f"{kind:9} {'ratio':9} {p[0] / e[0]:9.2f} {p[1] / e[1]:9.2f} {p[2] / e[2]:9.2f}  (protocol / echo)")

if __name__ == "__main__":
    main()
