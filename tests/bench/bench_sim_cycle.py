"""Benchmark: the simulated controller's send period on a loaded host, in the run's process or its own.

    python tests/bench/bench_sim_cycle.py [--seconds 15] [--hogs 4] [--fit] [--phases threads,proc0,proc]

The simulated cell of ``acquire run --fake`` (``drivers.sim.running.SimulatedCell``, the
bundled iiwa cell at time scale 1: a fake Sunrise sending every 5 ms, a fake Motive, a fake
tracker) is started as ``acquire run --fake`` starts it, and an ``FriCommander`` in this process
answers it; its exchange process stamps every monitoring message's arrival in the kernel, so
the intervals between arrivals are the send period the controller kept.

Phases, each ``--seconds`` long, in the same run:

  threads   every fake a thread of this process (``SimulatedCell(process=False)``, the fake
            Sunrise's sending thread at SCHED_FIFO 30: how ``acquire run --fake`` ran before),
  proc0     the cell in a process of its own (``CellProcess``) at normal priority,
  proc      the cell in a process of its own at SCHED_FIFO 30, every thread of it (the default),

each with ``--hogs`` CPU-bound processes running (``loadgen.Hogs``), and with ``--fit`` also a
zero-offset fit over and over in this process (``loadgen.FitLoop``: what a run's process does
beside its cell). Printed per phase: messages, send period p50 / p99 / max (ms), periods
longer than 2x the nominal and longer than the fake's 100 ms watchdog. Target: p99 within 2x
the period and none past the watchdog with the hogs and the fit.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from loadgen import FitLoop, Hogs  # noqa: E402


#: The fake Sunrise's watchdog on its client's answers (ms): a longer gap drops the session.
WATCHDOG_MS = 100.0


def phase(name: str, seconds: float, hogs: int, fit: bool) -> dict:
    from drivers.kuka_fri.commander import FriCommander
    from drivers.protocols import JointLimits
    from drivers.sim import running
    from drivers.sim.process import CellProcess

    sim = running.SimulatedCell(time_scale=1.0, max_runtime_s=seconds + 60, process=name != "threads")
    real = running.CellProcess
    if name == "proc0":  # the one knob this phase turns: the cell process at normal priority
        running.CellProcess = functools.partial(CellProcess, rt_priority=0)
    try:
        sim.start()
    finally:
        running.CellProcess = real
    try:
        cmd = FriCommander.from_url(sim.commander_url("fri"), limits=JointLimits.from_model(sim.model))
        cmd.connect()
        try:
            cmd.first_state(30.0)
            time.sleep(1.0)  # warm-up
            with Hogs(hogs), (FitLoop() if fit else contextlib.nullcontext()) as loop:
                n0 = cmd.answer_log()[0]
                time.sleep(seconds)
                n1, arrived, _ = cmd.answer_log()
        finally:
            cmd.close()
    finally:
        sim.close()
    period_ms = np.diff(arrived[-min(n1 - n0, len(arrived)):]) * 1e3
    nominal = sim.fri_send_period_ms()
    return {"phase": name, "messages": int(n1 - n0), "p50": float(np.percentile(period_ms, 50)),
            "p99": float(np.percentile(period_ms, 99)), "max": float(period_ms.max()),
            "long": int(np.sum(period_ms > 2 * nominal)), "watchdog": int(np.sum(period_ms > WATCHDOG_MS)),
            "nominal": nominal, "fits": getattr(loop, "fits", None)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--hogs", type=int, default=4)
    ap.add_argument("--fit", action="store_true", help="also fit over and over in this process")
    ap.add_argument("--phases", default="threads,proc0,proc", help="comma-separated: threads, proc0, proc")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    print(f"simulated controller send period with {args.hogs} CPU hogs{' and a fit loop' if args.fit else ''}, "
          f"{args.seconds:g} s per phase")
    print(f"{'phase':8} {'messages':>8} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'>2x':>5} {'>100ms':>6} {'fits':>5}")
    for name in args.phases.split(","):
        r = phase(name.strip(), args.seconds, args.hogs, args.fit)
        print(f"{r['phase']:<8} {r['messages']:>8} {r['p50']:>7.2f} {r['p99']:>7.2f} {r['max']:>7.1f} "
              f"{r['long']:>5} {r['watchdog']:>6} {r['fits'] if r['fits'] is not None else '-':>5}"
              f"   (nominal {r['nominal']} ms)", flush=True)


if __name__ == "__main__":
    main()
