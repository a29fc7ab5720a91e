"""Study (issue 27): how close can ANY choice of the plan's configurations come to the full plan
in a given share of its cell time? Linear predictions only (``calib.plan.adaptive``: the fit's
model linearised at the nominal robot, σ the plan's noise), no fits, no measurements.

For each share of the full plan's estimated cell time (its minimum-time tour), the predicted
held-out error's excess over the full plan's (and the workspace error² ratio) of:

* one-step: the configuration with the largest gain per second from where the robot stands
  (``SequentialDesign.choose``; the run's rule before the batch plan);
* batch: the run's own choice (``AdaptiveOrder.choose``: a batch predicted to meet the rule,
  toured, re-planned after every configuration) under held-out rules of 10, 5 and 2 %: where
  it stops;
* gain-only subsets of n configurations, toured in minimum time (no time in the choice).

    PYTHONPATH=$PWD python3 tests/bench/study_adaptive_bound.py            # iiwa + mocap, 84 configurations
    PYTHONPATH=$PWD python3 tests/bench/study_adaptive_bound.py --cell tx60
    PYTHONPATH=$PWD python3 tests/bench/study_adaptive_bound.py --extra 200   # + a generated pool

``--extra N``: N further poses of the plan's generator (another seed, every IK branch: the
plan's ``adaptive.candidates``) may be chosen too; the full plan and its predicted error stay
the plan's own configurations.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import study_adaptive as S  # noqa: E402

from acquire.plan.schema import load_plan, resolve_candidate_pool, resolve_configurations  # noqa: E402
from acquire.run import SENSOR_RATE_HZ, plan_settings  # noqa: E402
from acquire.run.adaptive import AdaptiveOrder  # noqa: E402
from acquire.run.sequencer import estimate_measure_s, estimate_settle_s, order_configurations  # noqa: E402
from calib.robot.model import load_robot_model  # noqa: E402
from drivers.protocols import JointLimits  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cell", choices=("iiwa", "tx60"), default="iiwa")
    ap.add_argument("--extra", type=int, default=0, help="further generated poses the design may choose (a pool)")
    args = ap.parse_args()
    t0 = time.process_time()
    iiwa = args.cell == "iiwa"
    with tempfile.TemporaryDirectory() as tmp:
        lp = load_plan(S.plan_file(Path(tmp), 60 if iiwa else 20, None, None, 1.0, marker="sir" if iiwa else "smr",
                                   noise_mm=0.03 if iiwa else 0.02, extra=args.extra))
        if iiwa:
            configs, pool = resolve_configurations(lp), resolve_candidate_pool(lp)
        else:
            lp = replace(lp, model=load_robot_model(S.ROOT / "fixtures/robots/staubli_tx60.yaml"))
            configs = S.tx60_configs(lp.model, 20, 3)
            pool = S.tx60_configs(lp.model, args.extra, 4, prefix="x") if args.extra else []
    s = plan_settings(lp.plan)
    limits = JointLimits.from_model(lp.model)
    per = estimate_settle_s(s.settle_window_s) + estimate_measure_s(s.samples, [SENSOR_RATE_HZ["natnet"]])
    start = np.zeros(lp.model.n_joints)
    order = AdaptiveOrder(lp, configs, limits, s.speed, per, pool)
    d = order.design
    cands = order.configs  # the plan's, then the pool's
    full_t = order.full_plan_seconds(start)
    ws_full = d.full_workspace_mm()
    held_full = d.held_out_mm(ws_full)
    print(f"{args.cell}: {len(configs)} configurations + {len(cands) - len(configs)} generated, full plan {full_t:.0f} s, predicted held-out {held_full:.4f} mm "
          f"(workspace {ws_full:.4f} mm, noise {d.sigma_mm} mm)")

    def excess(idx) -> str:
        ws = d.workspace_mm(d.covariance(list(idx)))
        return f"+{100 * (d.held_out_mm(ws) / held_full - 1):4.1f} % (ws² ×{ws**2 / ws_full**2:4.2f})"

    def along(seq) -> list[str]:
        out = []
        for share in (0.3, 0.4, 0.5, 0.6, 0.8):
            k = max((n for n in range(1, len(seq) + 1)
                     if order.visited_seconds([cands[i] for i in seq[:n]], start) <= share * full_t), default=0)
            out.append(f"{share:.0%}: n={k:3d} {excess(seq[:k]) if k else '—'}")
        return out

    # one-step rule
    o1 = order.copy()
    one, here = [], start
    while len(one) < len(cands) and order.visited_seconds([cands[i] for i in one], start) <= 0.8 * full_t:
        c = o1.design.choose(order.seconds_from(here)).index
        o1.design.add(c)
        one.append(c)
        here = cands[c].q_rad
    print("one-step:   " + " | ".join(along(one)))
    for pct in (10, 5, 2):
        o3 = order.copy()
        o3.design.rule = replace(o3.design.rule, held_out_within_pct=float(pct))
        seq, here = [], start
        while not o3.status().stop:
            cfg, _ = o3.choose(here)
            o3.mark(cfg.config_id)
            seq.append(order.index[cfg.config_id])
            here = cfg.q_rad
        t = order.visited_seconds([cands[i] for i in seq], start)
        print(f"batch, rule held-out {pct:2d} %: n={len(seq)} {t / full_t:.0%} of the full plan's time, {excess(seq)}")
    # gain-only subsets, toured; and the floor: configurations needed for +2 % / +1 %, whose settle
    # and measure seconds alone (no motion at all) are a share of the full plan's time
    sel: list[int] = []
    reached: dict[float, int] = {}
    while len(sel) < len(cands) and len(reached) < 2:
        left = np.setdiff1d(np.arange(len(cands)), sel)
        g = _drop(d, left, sel)
        sel.append(int(left[int(np.argmax(g))]))
        n = len(sel)
        ws = d.workspace_mm(d.covariance(sel))
        for pct in (2.0, 1.0):
            if pct not in reached and d.held_out_mm(ws) <= held_full * (1 + pct / 100):
                reached[pct] = n
        if n in (15, 20, 25, 30, 40, 50, 60):
            tour = order_configurations([cands[i] for i in sel], start, limits, s.speed)
            t = order.visited_seconds(tour, start)
            n_gen = sum(i >= len(configs) for i in sel)
            print(f"gain-only n={n:3d} ({n_gen} generated), toured: {t / full_t:.0%} of the full plan's time, "
                  f"{excess(sel)}")
    for pct, n in sorted(reached.items(), reverse=True):
        print(f"floor: +{pct:g} % needs n={n} (gain-only); their settle + measure alone ({per:.2f} s each) are "
              f"{n * per / full_t:.0%} of the full plan's time")
    print(f"CPU {time.process_time() - t0:.0f} s")


def _drop(d, left, planned):
    """Absolute reduction of trace(A Σ) per candidate (the workspace criterion, whatever the rule)."""
    from dataclasses import replace as _r

    saved = d.rule
    d.rule = _r(saved, workspace_within_pct=10.0)
    try:
        return d.gains(left, planned=planned)["workspace"]
    finally:
        d.rule = saved


if __name__ == "__main__":
    main()
