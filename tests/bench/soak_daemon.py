"""The daemon on a busy shared cell PC: start/abort cycles, then full runs back to back.

Run: ``python tests/bench/soak_daemon.py [--cycles 12] [--runs 2] [--load]``

The daemon (``python -m acquire daemon``, the simulated cell: an LBR iiwa 14 over FRI against a
fake Sunrise, a fake Motive, a fake tracker, all on loopback) is started with
``PYTHONTRACEMALLOC=1``. Through its control channel (as the operator) this script:

1. starts the example plan and aborts it once running, ``--cycles`` times — threads, descriptors,
   sockets, resident memory and the Python heap after each (``daemon_harness.leak_figures``:
   the leak criterion is the heap's robust slope, ≤ 8 kB/cycle as in
   ``tests/acquire/test_daemon_soak.py``);
2. runs the example plan to its end ``--runs`` times back to back — each run's log must be
   complete with nothing dropped, every planned configuration measured (none skipped or
   failed) with every marker record averaging all the frames the plan asks for, a result written,
   and the run's ``link`` event must show no late real-time answer.

``--load``: four CPU-bound hog processes for the whole soak (``loadgen.Hogs``); the daemon's
own fit at the end of each run, its MCAP writing and NatNet decoding are the rest of the load.
A ``loadgen.StallProbe`` prints the machine's own stalls over the soak. Prints the figures and
PASS/FAIL per criterion; exits 1 on a failure.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "tests" / "acquire"))

from daemon_harness import (  # noqa: E402
    OPERATOR_TOKEN,
    DaemonProcess,
    NotifySocket,
    control,
    free_port,
    leak_figures,
    open_client,
    start_abort_cycles,
    wait_until,
    write_config,
)
from loadgen import Hogs, StallProbe, load_average  # noqa: E402

WARM_UP = 4
MAX_HEAP_SLOPE_KB = 8


def short_samples(rc, asked: int) -> tuple[int, int]:
    """(marker records, records averaging fewer than the ``asked`` frames) over a run's samples:
    a frame lost between the sensor and the record shows as a short count."""
    counts = [m["count"] for s in rc.samples for m in s["markers"]]
    return len(counts), sum(c < asked for c in counts)


def full_run(op, state_dir: Path, timeout: float) -> dict:
    """Run the example plan to its end; the figures of its log."""
    from acquire.record.recorder import read_run

    t0 = time.monotonic()
    run_id = op.call("start", {"plan": "example.yaml"})["run_id"]
    wait_until(lambda: op.call("status")["run"] is None, timeout, f"run {run_id} ended", poll=0.5)
    wall = time.monotonic() - t0
    log = state_dir / "runs" / run_id / f"{run_id}.mcap"
    rc = read_run(log)
    started = next((e for e in rc.events if e.get("kind") == "run_started"), {})
    kinds = [e.get("kind") for e in rc.events]
    link = next((e for e in rc.events if e.get("kind") == "link"), {})
    import yaml

    asked = int(yaml.safe_load(rc.plan_text)["sequencing"]["samples"])
    records, short = short_samples(rc, asked)
    return {
        "run_id": run_id, "wall_s": wall, "complete": rc.complete, "dropped_bytes": rc.dropped_bytes,
        "measured": len(rc.measured_config_ids), "planned": started.get("total"),
        "skipped": kinds.count("skipped"), "failed": kinds.count("failed"), "finished": "run_finished" in kinds,
        "result": (log.parent / "result.json").exists(), "link": link, "records": records, "short": short, "asked": asked,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=12)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--load", action="store_true", help="four CPU hogs for the whole soak")
    args = ap.parse_args()
    failures: list[str] = []
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        tmp_path = Path(tmp)
        if args.load:
            stack.enter_context(Hogs(4))
        probe = stack.enter_context(StallProbe())
        notify = NotifySocket()
        port = free_port()
        proc = DaemonProcess(write_config(tmp_path, port), notify, watchdog_usec=2_000_000,
                             env={"PYTHONTRACEMALLOC": "1"})
        try:
            proc.wait_ready(60)
            with open_client(port) as bus:
                op = control(bus, "operator", OPERATOR_TOKEN)
                rows = start_abort_cycles(proc, op, args.cycles)
                runs = [full_run(op, tmp_path / "state", 600) for _ in range(args.runs)]
                st = op.call("status")
            pings = notify.count("WATCHDOG", "1")
            code = proc.stop()
        finally:
            proc.kill()
            notify.close()
        traceback = "Traceback" in proc.log()
    print(f"daemon soak, {'four CPU hogs, ' if args.load else ''}load average now {load_average()}")
    leak = leak_figures(rows, WARM_UP)
    print(f"{leak['line']}; watchdog pings {pings}; daemon exit {code}; healthy at the end: {st['healthy']}")
    if leak["heap_slope"] > MAX_HEAP_SLOPE_KB:
        failures.append(f"heap slope {leak['heap_slope']:+.1f} kB/cycle > {MAX_HEAP_SLOPE_KB}")
    for r in runs:
        link = r["link"]
        print(f"run {r['run_id']}: {r['wall_s']:.0f} s, {r['measured']}/{r['planned']} configurations measured, "
              f"{r['skipped']} skipped, {r['failed']} failed, log complete {r['complete']}, dropped bytes "
              f"{r['dropped_bytes']}, result {r['result']}; marker records {r['records']}, short of the {r['asked']} frames asked {r['short']}; "
              f"link: {link.get('packets')} cycles, {link.get('late_answers')} late, latency p50/p99/max "
              f"{link.get('latency_p50_us')}/{link.get('latency_p99_us')}/{link.get('latency_max_us')} µs, "
              f"{'; '.join(link.get('notes', []))}")
        if not (r["finished"] and r["complete"] and r["result"] and r["dropped_bytes"] == 0):
            failures.append(f"run {r['run_id']} did not finish whole with a result")
        if r["skipped"] or r["failed"] or (r["planned"] is not None and r["measured"] != r["planned"]):
            failures.append(f"run {r['run_id']}: configurations not measured")
        if r["short"] or not r["records"]:
            failures.append(f"run {r['run_id']}: {r['short']} marker records short of frames")
        if link.get("late_answers") != 0:
            failures.append(f"run {r['run_id']}: {link.get('late_answers')} late real-time answers")
    if traceback or code != 0:
        failures.append("the daemon logged a traceback or did not stop cleanly")
    print(probe.summary(np.zeros((0, 2))).split(";")[0])
    print("PASS" if not failures else "FAIL: " + "; ".join(failures))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
