"""Benchmark of the MCAP run log against plain JSON lines.

    python tests/bench/bench_recorder.py [--seconds 60] [--repeat 3]

Workload: ``--seconds`` of cell time of a 240 Hz marker stream (3 markers; every frame in mm,
plus a Foxglove SceneUpdate at 30 Hz), a 250 Hz joint stream (7 joints), and one fsync'd sample
plus two fsync'd events every 2 s, written as fast as possible.

Reported: records/s and the real-time margin (how many times faster than the cell produces
them), and the latency of ``sample()`` (JSON encode + write + flush + fsync) as median / p95 /
max. Baseline in the same run: the same JSON payloads written as lines to a plain file with the
same flush/fsync policy — the cheapest crash-safe log one could write.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from acquire.record.jsonpayload import encode_json
from acquire.record.recorder import RunLog, read_run, scene_update

MARKER_HZ = 240.0
JOINT_HZ = 250.0
SCENE_HZ = 30.0
SAMPLE_EVERY_S = 2.0


def workload(seconds: float, seed: int = 0) -> list[tuple[float, str, object]]:
    """Time-ordered (t_s, kind, payload) with kind in markers | joints | sample."""
    rng = np.random.default_rng(seed)
    items: list[tuple[float, str, object]] = []
    for i in range(int(seconds * MARKER_HZ)):
        items.append((i / MARKER_HZ, "markers", {f"m{j}": rng.normal(0, 500, 3) for j in range(3)}))
    for i in range(int(seconds * JOINT_HZ)):
        items.append((i / JOINT_HZ, "joints", rng.normal(0, 1, 7)))
    for i in range(int(seconds / SAMPLE_EVERY_S)):
        sample = {
            "config_id": f"p{i:03d}-b0", "pose": f"p{i:03d}", "branch": "b0",
            "q_target_deg": rng.normal(0, 40, 7).tolist(), "q_measured_deg": rng.normal(0, 40, 7).tolist(),
            "q_measured_std_deg": [1e-4] * 7,
            "markers": [{"sensor": "mocap", "marker": f"m{j}", "mean_mm": rng.normal(0, 500, 3).tolist(),
                         "std_mm": [0.02] * 3, "count": 20, "device_time": 1.0 * i, "host_time": 1.7e9 + i} for j in range(3)],
            "t_start": 1.7e9 + i, "t_end": 1.7e9 + i + 0.4, "attempts": 1,
        }
        items.append(((i + 1) * SAMPLE_EVERY_S - 1e-6, "sample", sample))
    items.sort(key=lambda it: it[0])
    return items


def run_mcap(path: Path, items, t0_ns: int) -> tuple[float, list[float], int]:
    latencies = []
    start = time.perf_counter()
    lg = RunLog.create(path, run_id="bench", plan_text="plan", model_text="model", metadata={}, scene_rate_hz=SCENE_HZ)
    for t, kind, payload in items:
        t_ns = t0_ns + int(t * 1e9)
        if kind == "markers":
            lg.record_markers("mocap", payload, log_time_ns=t_ns)
        elif kind == "joints":
            lg.record_joint_state("robot", payload, log_time_ns=t_ns)
        else:
            lg.event("moved", config_id=payload["config_id"])
            lg.event("settled", config_id=payload["config_id"])
            a = time.perf_counter()
            lg.sample(payload)
            latencies.append(time.perf_counter() - a)
    lg.close()
    wall = time.perf_counter() - start
    n = sum(read_run(path).message_counts.values())
    return wall, latencies, n


def run_jsonl(path: Path, items, t0_ns: int, flush_interval_s: float = 0.05) -> tuple[float, list[float], int]:
    """The same payloads as JSON lines; flush every flush_interval_s, flush+fsync on samples/events."""
    latencies = []
    n = 0
    start = time.perf_counter()
    last_flush = time.monotonic()
    next_scene_ns = None
    with open(path, "wb") as fh:
        def line(topic: str, obj: dict) -> None:
            fh.write(encode_json({"topic": topic, "msg": obj}) + b"\n")

        def durable() -> None:
            nonlocal last_flush
            fh.flush()
            os.fsync(fh.fileno())
            last_flush = time.monotonic()

        for t, kind, payload in items:
            t_ns = t0_ns + int(t * 1e9)
            stamp = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
            if kind == "markers":
                line("/mocap/markers", {"timestamp": stamp, "frame_id": "mocap", "device_time": None,
                                        "markers": [{"name": k, "position_mm": np.round(v, 4), "quality": None} for k, v in payload.items()]})
                n += 1
                if next_scene_ns is None or t_ns >= next_scene_ns:  # RunLog's fixed 30 Hz schedule
                    line("/mocap/markers/scene", scene_update("mocap", payload, t_ns))
                    next_scene_ns = (next_scene_ns if next_scene_ns is not None else t_ns) + 1e9 / SCENE_HZ
                    n += 1
            elif kind == "joints":
                line("/robot/joint_state", {"timestamp": stamp, "name": [f"A{i + 1}" for i in range(7)],
                                            "position_deg": np.round(np.degrees(payload), 6), "device_time": None})
                n += 1
            else:
                for ev in ("moved", "settled"):
                    line("/run/event", {"kind": ev, "t": time.time(), "config_id": payload["config_id"]})
                    durable()
                a = time.perf_counter()
                line("/run/sample", payload)
                durable()
                latencies.append(time.perf_counter() - a)
                n += 3
                continue
            if time.monotonic() - last_flush >= flush_interval_s:
                fh.flush()
                last_flush = time.monotonic()
        durable()
    return time.perf_counter() - start, latencies, n


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="cell time to simulate (s)")
    ap.add_argument("--repeat", type=int, default=3, help="repetitions; the best wall time is reported")
    args = ap.parse_args()
    items = workload(args.seconds)
    t0_ns = time.time_ns()
    results: dict[str, list[tuple[float, list[float], int, int]]] = {"mcap": [], "jsonl": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            for name, fn, suffix in (("mcap", run_mcap, ".mcap"), ("jsonl", run_jsonl, ".jsonl")):
                path = Path(tmp) / f"{name}{r}{suffix}"
                wall, lat, n = fn(path, items, t0_ns)
                results[name].append((wall, lat, n, path.stat().st_size))
    print(f"workload: {args.seconds:.0f} s of cell time — {MARKER_HZ:.0f} Hz markers, "
          f"{JOINT_HZ:.0f} Hz joints, scene at {SCENE_HZ:.0f} Hz, 1 sample + 2 events every {SAMPLE_EVERY_S:.0f} s; best of {args.repeat}")
    summary = {}
    for name in ("mcap", "jsonl"):
        wall, _, n, size = min(results[name], key=lambda x: x[0])
        lat = [v for run in results[name] for v in run[1]]
        summary[name] = {
            "records_per_s": n / wall, "realtime_x": args.seconds / wall, "bytes": size,
            "lat_med_ms": 1e3 * statistics.median(lat), "lat_p95_ms": 1e3 * pct(lat, 95), "lat_max_ms": 1e3 * max(lat), "n": n,
        }
        s = summary[name]
        label = "MCAP RunLog" if name == "mcap" else "baseline JSON lines"
        print(f"{label:<20} {s['n']} records in {wall:.3f} s: {s['records_per_s']:,.0f} records/s "
              f"({s['realtime_x']:.1f}x real time), {s['bytes'] / 1e6:.2f} MB; fsync'd sample latency "
              f"median {s['lat_med_ms']:.3f} ms, p95 {s['lat_p95_ms']:.3f} ms, max {s['lat_max_ms']:.3f} ms")
    m, b = summary["mcap"], summary["jsonl"]
    print(f"ratio MCAP/baseline: throughput {m['records_per_s'] / b['records_per_s']:.2f}x, "
          f"sample latency (median) {m['lat_med_ms'] / b['lat_med_ms']:.2f}x, file size {m['bytes'] / b['bytes']:.2f}x")
    # Recovery read (what resume and `acquire fit` pay): read_run vs parsing the JSON lines.
    with tempfile.TemporaryDirectory() as tmp:
        mpath, jpath = Path(tmp) / "r.mcap", Path(tmp) / "r.jsonl"
        run_mcap(mpath, items, t0_ns)
        run_jsonl(jpath, items, t0_ns)
        a = time.perf_counter()
        run = read_run(mpath)
        t_mcap = time.perf_counter() - a
        a = time.perf_counter()
        with open(jpath, "rb") as fh:
            lines = [json.loads(line) for line in fh]
        samples = [d["msg"] for d in lines if d["topic"] == "/run/sample"]
        t_jsonl = time.perf_counter() - a
        assert len(samples) == len(run.samples)
    print(f"recovery read: read_run {m['n'] / t_mcap:,.0f} records/s ({t_mcap * 1e3:.1f} ms), "
          f"JSON lines parse {b['n'] / t_jsonl:,.0f} records/s ({t_jsonl * 1e3:.1f} ms); ratio {t_jsonl / t_mcap:.1f}x faster")
    print(json.dumps({"mcap": m, "jsonl": b}, indent=None, default=float))


if __name__ == "__main__":
    main()
