"""Benchmark: measure one point, round trip, emScon TPI beside the line protocol, same run.

Both fakes drive the same kind of simulated tracker (one ``FakeTracker`` each on a fixed
reflector at 2 m, clock at 1000× real time) doing the same device work — one point, 1 ms of
simulated measurement time (a 1 µs wall wait) — over TCP loopback:

- ``emscon``: ``EmsconSensor.read()`` — one ``StartMeasurement`` (1 ms stationary measurement,
  one point) answered by a 156-byte ``SingleMeasResultT``;
- ``line``: ``TrackerSensor.read()`` — one ``MEAS`` line answered by one ``OK MEAS`` line.

The two run interleaved in blocks so both see the same machine load; the script prints p50 /
p99 latency, the call rate and the emscon/line ratios. A codec-only line (encode the request,
decode the answer, no transport) is printed for scale.

Run: ``python tests/bench/bench_emscon.py [--n 3000]``.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from drivers.emscon import codec as es
from drivers.emscon.client import EmsconSensor
from drivers.emscon.fake import EmsconServer, FakeEmscon
from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerObservation
from drivers.tracker.client import TrackerSensor
from drivers.tracker.codec import LineCodec, MeasurePoint, PointReply
from drivers.tracker.fake import FakeTracker, TcpTrackerServer

log = logging.getLogger("bench.emscon")


class FixedReflector:
    """A scene with one visible reflector at about 2 m."""

    def observe(self, sensor: str) -> list[MarkerObservation]:
        return [MarkerObservation("smr", np.array([2000.0, 300.0, -100.0]), True)]


def _tracker() -> FakeTracker:
    # MEAS spends measure_time_s; a 1 ms stationary measurement spends 1 point at average_rate_hz
    return FakeTracker(FixedReflector(), clock=SimClock(1000.0), measure_time_s=0.001, average_rate_hz=1000.0,
                       adm_lock_s=0.0, seed=1)


def _stats(ns: list[int]) -> tuple[float, float, float]:
    a = np.asarray(ns, dtype=float) / 1e3  # µs
    return float(np.percentile(a, 50)), float(np.percentile(a, 99)), 1e6 / float(a.mean())


def codec_only(n: int) -> tuple[float, float]:
    """µs per request+answer encode/decode: (emscon, line)."""
    req = es.Request(es.Cmd.StartMeasurement)
    answer = es.encode(es.DataResult(es.DataType.SingleMeasResult, 0, {
        name: 0 if code in "iI" else 1.5 for name, code in es.RESULT_LAYOUTS[es.DataType.SingleMeasResult]}))
    t0 = time.perf_counter_ns()
    for _ in range(n):
        es.encode(req)
        es.decode(answer)
    t1 = time.perf_counter_ns()
    codec = LineCodec(require_checksum=True)
    line = codec.encode_reply(1, PointReply(2000.0, 300.0, -100.0, 0.027, 12.0))
    for _ in range(n):
        codec.encode_request(1, MeasurePoint())
        codec.decode_reply(line)
    t2 = time.perf_counter_ns()
    return (t1 - t0) / n / 1e3, (t2 - t1) / n / 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3000, help="round trips per protocol")
    ap.add_argument("--block", type=int, default=100, help="round trips per interleaved block")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    em_server = EmsconServer(FakeEmscon(_tracker(), require_initialize=False))
    line_server = TcpTrackerServer(_tracker())
    times: dict[str, list[int]] = {"emscon": [], "line": []}
    try:
        with EmsconSensor(em_server.url, read_time_ms=1) as em, TrackerSensor.from_url(line_server.url) as line:
            calls = {"emscon": lambda: em.read(2.0), "line": lambda: line.read(2.0)}
            for fn in calls.values():  # warm up: first stationary-params command, caches
                for _ in range(20):
                    fn()
            for _ in range(max(1, args.n // args.block)):
                for name, fn in calls.items():
                    out = times[name]
                    for _ in range(args.block):
                        t0 = time.perf_counter_ns()
                        sample = fn()[0]
                        out.append(time.perf_counter_ns() - t0)
                        assert sample.visible
    finally:
        em_server.close()
        line_server.close()

    print(f"measure one point, TCP loopback, {len(times['emscon'])} round trips each, interleaved blocks of {args.block}")
    print(f"{'protocol':<10}{'p50 µs':>10}{'p99 µs':>10}{'calls/s':>10}")
    stats = {k: _stats(v) for k, v in times.items()}
    for name, (p50, p99, rate) in stats.items():
        print(f"{name:<10}{p50:>10.0f}{p99:>10.0f}{rate:>10.0f}")
    (e50, e99, er), (l50, l99, lr) = stats["emscon"], stats["line"]
    print(f"ratio emscon/line: p50 {e50 / l50:.2f}x, p99 {e99 / l99:.2f}x, rate {er / lr:.2f}x")
    ce, cl = codec_only(20_000)
    print(f"codec only (encode request + decode answer): emscon {ce:.1f} µs, line {cl:.1f} µs, ratio {ce / cl:.2f}x")


if __name__ == "__main__":
    main()
