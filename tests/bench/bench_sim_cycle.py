"""Benchmark: the simulated controller's send period on a loaded host, normal priority vs SCHED_FIFO.

    python tests/bench/bench_sim_cycle.py [--seconds 15] [--hogs 4] [--fit]

The simulated cell of ``acquire run --fake`` (``drivers.sim.running.SimulatedCell``, the
bundled iiwa cell at time scale 1: a fake Sunrise sending every 5 ms, a fake Motive, a fake
tracker) is started in this process, as ``acquire run --fake`` starts it, and an ``FriCommander``
answers it; its exchange process stamps every monitoring message's arrival in the kernel, so
the intervals between arrivals are the send period the controller kept.

Phases, each ``--seconds`` long, in the same run:

  rt 0      the fake controller's cycle at normal priority (as before this change),
  rt 30     at SCHED_FIFO 30 (``SimLaunch(controller_rt_priority=30)``, the default now),
  process   the cell in a process of its own (``acquire sim``, SCHED_FIFO 30 inside), the
            commander (and ``--fit``) here: nothing of the run shares the fake's interpreter,

each with ``--hogs`` CPU-bound processes running (``loadgen.Hogs``), and with ``--fit`` also a
zero-offset fit over and over in this process (``loadgen.FitLoop``: the GIL the fake shares
with a run). Printed per phase: messages, send period p50 / p99 / max (ms), periods longer than
2× the nominal, and the session drops the fake saw (missed answer windows past its watchdog).
Target: p99 within 2× the period and no drop with the hogs.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from loadgen import FitLoop, Hogs  # noqa: E402


def phase(rt_priority: int, seconds: float, hogs: int, fit: bool) -> dict:
    from drivers.kuka_fri.commander import FriCommander
    from drivers.protocols import JointLimits
    from drivers.sim import running
    from drivers.sim.launch import SimLaunch

    sim = running.SimulatedCell(time_scale=1.0, max_runtime_s=seconds + 60)
    launch_init = SimLaunch.__init__

    def with_priority(self, *a, **k):  # the one knob this bench turns
        launch_init(self, *a, controller_rt_priority=rt_priority, **k)

    SimLaunch.__init__ = with_priority
    try:
        sim.start()
    finally:
        SimLaunch.__init__ = launch_init
    try:
        cmd = FriCommander.from_url(sim.commander_url("fri"), limits=JointLimits.from_model(sim.model))
        cmd.connect()
        try:
            cmd.first_state(15.0)
            time.sleep(1.0)  # warm-up
            drops0 = sim.launch.controller.stats.session_drops
            with Hogs(hogs), (FitLoop() if fit else contextlib.nullcontext()) as loop:
                n0 = cmd.answer_log()[0]
                time.sleep(seconds)
                n1, arrived, _ = cmd.answer_log()
            drops = sim.launch.controller.stats.session_drops - drops0
        finally:
            cmd.close()
    finally:
        sim.close()
    got = arrived[-min(n1 - n0, len(arrived)):]
    period_ms = np.diff(got) * 1e3
    nominal = sim.fri_send_period_ms()
    return {"rt": rt_priority, "messages": int(n1 - n0), "p50": float(np.percentile(period_ms, 50)),
            "p99": float(np.percentile(period_ms, 99)), "max": float(period_ms.max()),
            "long": int(np.sum(period_ms > 2 * nominal)), "nominal": nominal, "drops": drops,
            "fits": getattr(loop, "fits", None)}


def process_phase(seconds: float, hogs: int, fit: bool) -> dict:
    """The cell served by ``acquire sim`` in a child process; the commander (and the fit) here."""
    import subprocess

    from drivers.kuka_fri.commander import FriCommander
    from drivers.protocols import JointLimits
    from drivers.sim.running import free_udp_port
    from calib.robot.model import load_robot_model

    port = free_udp_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    sim = subprocess.Popen([sys.executable, "-m", "acquire", "sim", "--fri-port", str(port), "--duration",
                            str(seconds + 60), "--no-faults"], cwd=ROOT, env=env, stdin=subprocess.PIPE,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
        cmd = FriCommander.from_url(f"fri://127.0.0.1:{port}?timeout_ms=300&max_state_age_ms=300",
                                    limits=JointLimits.from_model(model))
        cmd.connect()
        try:
            cmd.first_state(30.0)
            time.sleep(1.0)
            with Hogs(hogs), (FitLoop() if fit else contextlib.nullcontext()) as loop:
                n0 = cmd.answer_log()[0]
                time.sleep(seconds)
                n1, arrived, _ = cmd.answer_log()
        finally:
            cmd.close()
    finally:
        sim.terminate()
        sim.wait(10)
    period_ms = np.diff(arrived[-min(n1 - n0, len(arrived)):]) * 1e3
    return {"rt": "proc", "messages": int(n1 - n0), "p50": float(np.percentile(period_ms, 50)),
            "p99": float(np.percentile(period_ms, 99)), "max": float(period_ms.max()),
            "long": int(np.sum(period_ms > 10.0)), "nominal": 5, "drops": None, "fits": getattr(loop, "fits", None)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--hogs", type=int, default=4)
    ap.add_argument("--fit", action="store_true", help="also fit over and over in this process (the GIL)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    print(f"simulated controller send period with {args.hogs} CPU hogs{' and a fit loop' if args.fit else ''}, "
          f"{args.seconds:g} s per phase")
    print(f"{'phase':8} {'messages':>8} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'>2x':>5} {'drops':>5}")
    for rt in (0, 30, "process"):
        r = process_phase(args.seconds, args.hogs, args.fit) if rt == "process" else \
            phase(rt, args.seconds, args.hogs, args.fit)
        print(f"rt {r['rt']!s:<5} {r['messages']:>8} {r['p50']:>7.2f} {r['p99']:>7.2f} {r['max']:>7.1f} "
              f"{r['long']:>5} {r['drops'] if r['drops'] is not None else '-':>5}   (nominal {r['nominal']} ms)")


if __name__ == "__main__":
    main()
