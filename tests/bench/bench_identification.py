"""Benchmark: full identification of 1000 configurations, and IOOPS 50-of-200.

Reference, measured in the same run on the same data: a careful scipy ``least_squares`` fit
(trust-region reflective, ``x_scale='jac'``) of the same identifiable parameters with a
finite-difference Jacobian and forward kinematics evaluated configuration by configuration —
how popular Python calibration toolboxes do it (pybotics: ``list(map(robot.fk, joints))`` inside
the residual). A second line shows the same finite-difference fit on our vectorised residual, so
the gain of the analytic Jacobian alone is visible too. Prints wall times (best of 3), the speed
ratios and held-out mean position error (target: ≥ 10× faster than the reference at equal or
better held-out error).

    python tests/bench/bench_identification.py [--robot staubli_tx60] [--configs 1000]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.identification import _Problem, identify, information_blocks, pose_errors  # noqa: E402
from calib.kinematics import Chain  # noqa: E402
from calib.model import load_robot_model  # noqa: E402
from calib.observability import ioops  # noqa: E402
from calib.transforms import euler_zyx_to_matrix  # noqa: E402
from tests.calib.test_identification import measure, perturbed_truth  # noqa: E402


def reference_fit(model, data, free_names, b2s0, per_config: bool):
    """Same free parameters, finite-difference Jacobian, scipy TRF; FK per configuration
    (toolbox style) or vectorised."""
    chain = Chain(model)
    problem = _Problem(chain, data, b2s0, None, 100.0)
    free = [problem.names.index(n) for n in free_names]
    x0 = np.concatenate([chain.nominal, np.zeros(6)])
    midx = np.array([chain.marker_names.index(mk) for mk in data.marker])

    def residual_per_config(x):
        params, reg = problem.split(x)
        t = np.eye(4)
        t[:3, :3] = euler_zyx_to_matrix(*reg[0, 3:])
        t[:3, 3] = reg[0, :3]
        t = t @ b2s0["sensor"]
        pred = np.array([chain.marker_positions(q, params)[mi] for q, mi in zip(data.q_rad, midx)])
        return (data.xyz_mm - (pred @ t[:3, :3].T + t[:3, 3])).ravel()

    def fun(z):
        x = x0.copy()
        x[free] = z
        if per_config:
            return residual_per_config(x)
        return problem.residuals_and_jacobian(x, want_jac=False)[0]

    sol = least_squares(fun, x0[free], jac="2-point", method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12)
    x = x0.copy()
    x[free] = sol.x
    params, reg = problem.split(x)
    t = np.eye(4)
    t[:3, :3] = euler_zyx_to_matrix(*reg[0, 3:])
    t[:3, 3] = reg[0, :3]
    return params, {"sensor": t @ b2s0["sensor"]}, sol.nfev


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--robot", default="staubli_tx60")
    ap.add_argument("--configs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = load_robot_model(ROOT / "fixtures" / "robots" / f"{args.robot}.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(args.seed)
    q = rng.uniform(model.lower_limits_rad * 0.8, model.upper_limits_rad * 0.8, (args.configs, model.n_joints))
    q_val = rng.uniform(model.lower_limits_rad * 0.8, model.upper_limits_rad * 0.8, (500, model.n_joints))
    names = identify(model, measure(model, chain, q[:100], chain.nominal, rng, 0.0)).free_names
    truth, _ = perturbed_truth(chain, names, rng)
    data = measure(model, chain, q, truth, rng, 0.03)
    val = measure(model, chain, q_val, truth, rng, 0.0)

    from calib.fit import initial_registrations

    def best_of(f, n=3):
        best, out = np.inf, None
        for _ in range(n):
            t0 = time.perf_counter()
            out = f()
            best = min(best, time.perf_counter() - t0)
        return best, out

    t_ours, ours = best_of(lambda: identify(model, data))
    b2s0 = initial_registrations(chain, data, "least-squares", 0)
    t_ref, (ref_params, ref_b2s, ref_nfev) = best_of(lambda: reference_fit(model, data, ours.free_names, b2s0, True), 1)
    t_vec, (vec_params, vec_b2s, vec_nfev) = best_of(lambda: reference_fit(model, data, ours.free_names, b2s0, False))
    e_ours = pose_errors(model, ours.params, val, ours.base2sensor).mean()
    e_ref = pose_errors(model, ref_params, val, ref_b2s).mean()
    e_vec = pose_errors(model, vec_params, val, vec_b2s).mean()
    print(f"robot {model.name}, {args.configs} configurations × {chain.m} markers, {len(ours.free_names)} identified parameters")
    print(f"  ours (analytic Jacobian, LM, vectorised):   {t_ours:8.3f} s  held-out mean error {e_ours:.4f} mm")
    print(f"  reference (toolbox style: FK per config, FD, TRF): {t_ref:8.3f} s  held-out mean error {e_ref:.4f} mm")
    print(f"  FD + TRF on our vectorised residual:        {t_vec:8.3f} s  held-out mean error {e_vec:.4f} mm")
    print(f"  speed ratio reference/ours: {t_ref / t_ours:.1f}×  (vectorised FD/ours: {t_vec / t_ours:.1f}×)   "
          f"held-out error ratio ours/reference: {e_ours / e_ref:.3f}")

    q200 = q[:200]
    t0 = time.perf_counter()
    blocks, _, _ = information_blocks(model, q200)
    t_blocks = time.perf_counter() - t0
    t0 = time.perf_counter()
    sel = ioops(blocks, 50, index="O6", seed=args.seed)
    t_ioops = time.perf_counter() - t0
    t0 = time.perf_counter()
    for s in range(20):
        np.random.default_rng(s).choice(200, 50, replace=False)
    print(f"IOOPS 50 of 200 on O6: blocks {t_blocks:.3f} s + search {t_ioops:.3f} s ({sel.iterations} iterations), O6 {sel.start_value:.4g} → {sel.value:.4g}")


if __name__ == "__main__":
    main()
