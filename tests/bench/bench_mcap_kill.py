"""How much of a run log a ``kill -9`` loses: our RunLog against mcap's own chunked Writer.

    PYTHONPATH=. python tests/bench/bench_mcap_kill.py [--kills 8] [--seed 1]

A child process writes a run's streams in real time — 240 Hz marker frames, 250 Hz joint
states (log time = wall clock at the write), an fsync'd event + sample every 2 s — and is killed
with SIGKILL after a random 2–4 s. The file is then read with ``acquire.record.mcapfile.scan`` (every
complete chunk with its message indexes) and the loss is ``t_kill − newest recovered log time``.

Writers, same workload, same run:
- ``remaster``: ``RunLog`` with its defaults (chunks closed at 0.25 s or 256 KiB, a background
  flusher, summary at close).
- ``mcap-writer``: ``mcap.writer.Writer`` with its defaults (chunked, 1 MiB chunks, closed only
  by size) — the peer every MCAP-producing Python tool uses.

Prints the median and max loss (s) per writer, and the ratio peer / ours.

``--runs N`` also kills N real ``acquire run fixtures/plans/example.yaml --fake`` processes 1–3 s
after their first sample and reports the same loss for the whole application (joint states
and frame transforms stream at 25 Hz).
"""

from __future__ import annotations

import argparse
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from acquire.record.mcapfile import scan

ROOT = Path(__file__).resolve().parents[2]

CHILD = r"""
import sys, time, json, os
import numpy as np
kind, path = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(0)
if kind == "remaster":
    from acquire.record.recorder import RunLog
    lg = RunLog.create(__import__("pathlib").Path(path), run_id="k", plan_text="p", model_text="m", metadata={})
    def markers(t): lg.record_markers("mocap", {"m1": rng.normal(0, 500, 3), "m2": rng.normal(0, 500, 3)}, log_time_ns=t)
    def joints(t): lg.record_joint_state("fri", rng.normal(size=7), log_time_ns=t)
    def durable(i): lg.event("settled", config_id=f"c{i}"); lg.sample({"config_id": f"c{i}", "q_measured_deg": [0.0] * 7, "markers": []})
else:
    from mcap.writer import Writer
    fh = open(path, "xb")
    w = Writer(fh)
    w.start(profile="", library="bench")
    sid = w.register_schema("s", "jsonschema", b"{}")
    cm, cj, cs = (w.register_channel(t, "json", sid) for t in ("/mocap/markers", "/joint_state", "/run/sample"))
    def markers(t): w.add_message(cm, t, json.dumps({"m1": rng.normal(0, 500, 3).round(4).tolist(), "m2": rng.normal(0, 500, 3).round(4).tolist()}).encode(), t)
    def joints(t): w.add_message(cj, t, json.dumps({"position_deg": rng.normal(size=7).round(6).tolist()}).encode(), t)
    def durable(i):
        t = time.time_ns(); w.add_message(cs, t, json.dumps({"config_id": f"c{i}"}).encode(), t); fh.flush(); os.fsync(fh.fileno())
print("ready", flush=True)
t0 = time.monotonic()
next_m = next_j = 0.0
next_d, i = 2.0, 0
while True:
    now = time.monotonic() - t0
    if now >= next_m:
        markers(time.time_ns()); next_m += 1 / 240
    if now >= next_j:
        joints(time.time_ns()); next_j += 1 / 250
    if now >= next_d:
        durable(i); i += 1; next_d += 2.0
    time.sleep(max(0.0, min(next_m, next_j, next_d) - (time.monotonic() - t0)))
"""


def newest_log_time(path: Path) -> tuple[int | None, int]:
    newest = None
    with open(path, "rb") as fh:
        res = scan(fh, path.stat().st_size, where=str(path))
    if res.index.message_count:
        newest = res.index.message_end_time
    return newest, res.index.message_count


def one_kill(kind: str, folder: Path, delay_s: float, n: int) -> tuple[float, int]:
    path = folder / f"{kind}-{n}.mcap"
    proc = subprocess.Popen([sys.executable, "-c", CHILD, kind, str(path)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(delay_s)
    t_kill = time.time_ns()
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stdout.close()
    newest, count = newest_log_time(path)
    loss = (t_kill - newest) / 1e9 if newest is not None else delay_s
    return loss, count


def one_run_kill(folder: Path, delay_s: float, n: int) -> tuple[float, int]:
    import os

    from acquire.record.recorder import read_run

    out = folder / f"runs-{n}"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "acquire", "run", "fixtures/plans/example.yaml", "--fake", "--no-bus",
                             "--no-fit", "--out", str(out)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 180
    log = None
    while time.monotonic() < deadline and proc.poll() is None:
        logs = sorted(out.rglob("*.mcap"))
        if logs and read_run(logs[0]).samples:
            log = logs[0]
            break
        time.sleep(0.2)
    if log is None:
        proc.kill()
        raise RuntimeError("the run wrote no sample within 180 s")
    time.sleep(delay_s)
    t_kill = time.time_ns()
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    newest, count = newest_log_time(log)
    return (t_kill - newest) / 1e9, count


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--runs", type=int, default=0, help="also kill this many real `acquire run --fake` processes")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    delays = [rng.uniform(2.0, 4.0) for _ in range(args.kills)]
    out: dict[str, list[float]] = {"remaster": [], "mcap-writer": []}
    with tempfile.TemporaryDirectory() as tmp:
        for n, d in enumerate(delays):
            for kind in out:  # interleaved, so both see the same machine load
                loss, count = one_kill(kind, Path(tmp), d, n)
                out[kind].append(loss)
                print(f"kill {n + 1}/{args.kills} after {d:.2f} s  {kind:12s} lost the last {loss:6.3f} s  ({count} messages kept)")
    print()
    for kind, losses in out.items():
        print(f"{kind:12s} loss after kill -9: median {statistics.median(losses):.3f} s, max {max(losses):.3f} s  (n={len(losses)})")
    ours, peer = out["remaster"], out["mcap-writer"]
    print(f"ratio mcap-writer / remaster: median {statistics.median(peer) / max(statistics.median(ours), 1e-9):.1f}x, "
          f"max {max(peer) / max(max(ours), 1e-9):.1f}x")
    if args.runs:
        losses = []
        with tempfile.TemporaryDirectory() as tmp:
            for n in range(args.runs):
                d = rng.uniform(1.0, 3.0)
                loss, count = one_run_kill(Path(tmp), d, n)
                losses.append(loss)
                print(f"acquire run --fake killed {d:.2f} s after its first sample: lost the last {loss:.3f} s ({count} messages kept)")
        print(f"acquire run   loss after kill -9: median {statistics.median(losses):.3f} s, max {max(losses):.3f} s  (n={len(losses)})")


if __name__ == "__main__":
    main()
