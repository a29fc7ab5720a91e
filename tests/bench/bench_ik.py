"""IK throughput of ``calib.ik`` for every shipped robot, against a brute-force numeric search.

Run: ``python tests/bench/bench_ik.py [--poses 2000] [--baseline-poses 3] [--starts 1000]``

Workload: FK of seeded random joint vectors inside the limits (reachable poses, as the pose
plan produces them). Measured per robot:

- ``solve_many``: all poses in one vectorised call (what the pose plan should use);
- ``solve_all`` loop: one call per pose;
- 7R: at the pose's own arm angle, and with ``arm_angle=None`` (the solver first finds each
  pose's feasible arm-angle intervals and picks the centre of the widest); the interval
  computation alone, vectorised (``arm_angle_intervals_many``) and one pose per call.

Rates are poses/s and solutions/s (rows returned: every branch and ±360° equivalent within
limits). Baseline, in the same run: ``calib.ik_numeric.solve_numeric`` — random-start
Levenberg–Marquardt (``--starts`` starts per pose, batched in numpy, clustered), the brute-force
way to find every solution within limits; it also reports whether it found as many solutions
as the analytic solver did. Ratio = analytic poses/s ÷ numeric poses/s.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib import ik  # noqa: E402
from calib.ik_numeric import solve_numeric  # noqa: E402
from calib.kinematics import Chain  # noqa: E402
from calib.model import load_robot_model  # noqa: E402

ROBOTS = ["kuka_kr6_r900_2", "staubli_tx60", "kuka_iiwa14_r820", "kuka_iiwa7_r800"]


def best_of(fn, repeats: int = 3) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=2000)
    ap.add_argument("--baseline-poses", type=int, default=3)
    ap.add_argument("--starts", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    header = f"{'robot':<22} {'what':<34} {'poses/s':>10} {'solutions/s':>12} {'sol/pose':>9} {'vs numeric':>11}"
    print(header)
    print("-" * len(header))
    for name in ROBOTS:
        model = load_robot_model(ROOT / "fixtures" / "robots" / f"{name}.yaml")
        chain = Chain(model)
        rng = np.random.default_rng(args.seed)
        q = rng.uniform(model.lower_limits_rad, model.upper_limits_rad, (args.poses, model.n_joints))
        poses = chain.fk(q)
        seven = model.n_joints == 7
        psi = ik.arm_angle_of(model, q) if seven else None
        ik.solve_many(model, poses[:10], arm_angle=None if psi is None else psi[:10])  # warm the cache

        # baseline: brute-force numeric search, per pose
        nb = args.baseline_poses
        t0 = time.perf_counter()
        numeric_counts = [
            len(solve_numeric(model, poses[i], n_starts=args.starts, seed=i, arm_angle=None if psi is None else float(psi[i])))
            for i in range(nb)
        ]
        numeric_rate = nb / (time.perf_counter() - t0)
        analytic_counts = [
            len(ik.solve_all(model, poses[i], arm_angle=None if psi is None else float(psi[i]))) for i in range(nb)
        ]

        rows = []
        t, res = best_of(lambda: ik.solve_many(model, poses, arm_angle=psi))
        rows.append(("solve_many (vectorised)" + (", given ψ" if seven else ""), len(poses) / t, sum(map(len, res)) / t, res))
        m = min(len(poses), 500)
        t, res = best_of(
            lambda: [ik.solve_all(model, poses[i], arm_angle=None if psi is None else float(psi[i])) for i in range(m)], 1
        )
        rows.append(("solve_all loop" + (", given ψ" if seven else ""), m / t, sum(map(len, res)) / t, res))
        if seven:
            m7 = min(len(poses), 200)
            t, res = best_of(lambda: ik.solve_many(model, poses[:m7]), 1)
            rows.append(("solve_many, ψ picked (intervals)", m7 / t, sum(map(len, res)) / t, res))
            t, res = best_of(lambda: [ik.solve_all(model, poses[i]) for i in range(m7)], 1)
            rows.append(("solve_all loop, ψ picked", m7 / t, sum(map(len, res)) / t, res))
            given_rate = rows[1][1]
            print(f"{model.name}: one pose, ψ picked costs {given_rate / (m7 / t):.2f}x a solve at a given ψ (target ≤ 3x)")
            t, _ = best_of(lambda: ik.arm_angle_intervals_many(model, poses[:m7]), 1)
            rows.append(("arm_angle_intervals_many alone", m7 / t, float("nan"), None))
            t, _ = best_of(lambda: [ik.arm_angle_intervals(model, poses[i]) for i in range(m7)], 1)
            rows.append(("arm_angle_intervals loop", m7 / t, float("nan"), None))
        for what, rate, sol_rate, res in rows:
            per_pose = sum(map(len, res)) / len(res) if res else float("nan")
            print(f"{model.name:<22} {what:<34} {rate:>10.1f} {sol_rate:>12.1f} {per_pose:>9.2f} {rate / numeric_rate:>10.0f}x")
        agree = "agree" if numeric_counts == analytic_counts else "DIFFER"
        print(
            f"{model.name:<22} {'numeric search (baseline)':<34} {numeric_rate:>10.2f} "
            f"{numeric_rate * np.mean(numeric_counts):>12.1f} {np.mean(numeric_counts):>9.2f} {'1x':>11}"
            f"   [{args.starts} starts; counts {numeric_counts} vs analytic {analytic_counts}: {agree}]"
        )


if __name__ == "__main__":
    main()
