"""Forward-kinematics and Jacobian throughput of ``calib.kinematics.Chain`` against a naive loop.

Run: ``python tests/bench/bench_fk.py [--robot fixtures/robots/kuka_iiwa14_r820.yaml]``

Workload: the paper's 173 joint configurations (seeded, inside the limits) × {1, 100, 2000}
parameter vectors (nominal plus seeded perturbations), i.e. what a sampler or a fitter asks for.
Throughput is (configurations × parameter sets) per second, best of a few repeats.

Baseline, measured in the same run: the straightforward implementation — for every parameter
set and every configuration, a Python loop over the joints building 4×4 matrices
``Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)`` with numpy and multiplying them; for the Jacobian, forward
differences of that loop over every parameter. The baseline runs on a subset (it is slow); its
rate is per evaluation, so the ratio is like for like. Both must agree numerically (checked).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from calib.kinematics import Chain
from calib.model import load_robot_model

ROOT = Path(__file__).resolve().parents[2]


def naive_link(theta: float, d: float, a: float, alpha: float, beta: float) -> np.ndarray:
    ct, st, ca, sa, cb, sb = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
    rz = np.array([[ct, -st, 0, 0], [st, ct, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    tz = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, d], [0, 0, 0, 1.0]])
    tx = np.array([[1, 0, 0, a], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    rx = np.array([[1, 0, 0, 0], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1.0]])
    ry = np.array([[cb, 0, sb, 0], [0, 1, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])
    return rz @ tz @ tx @ rx @ ry


def naive_fk(chain: Chain, q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """One configuration, one parameter vector: (4, 4) flange frame the textbook way."""
    n = chain.n
    t = chain.base.copy()
    for i in range(n):
        theta = chain.theta0[i] + chain.sign[i] * (q[i] + p[i])
        t = t @ naive_link(theta, p[n + i], p[2 * n + i], p[3 * n + i], p[4 * n + i])
    return t @ chain.flange


def naive_fk_all(chain: Chain, q: np.ndarray, params: np.ndarray) -> np.ndarray:
    return np.array([[naive_fk(chain, x, p) for x in q] for p in params])


def naive_marker_jacobian(chain: Chain, q: np.ndarray, p: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """Forward differences of the naive loop: (n_q, m, 3, P)."""
    mk = p[chain.marker_slice()].reshape(chain.m, 3)

    def markers(x, pp):
        t = naive_fk(chain, x, pp)
        return (t[:3, :3] @ pp[chain.marker_slice()].reshape(chain.m, 3).T).T + t[:3, 3]

    out = np.zeros((len(q), chain.m, 3, chain.n_params))
    for j, x in enumerate(q):
        base = (naive_fk(chain, x, p)[:3, :3] @ mk.T).T + naive_fk(chain, x, p)[:3, 3]
        for k in range(chain.n_params):
            pp = p.copy()
            pp[k] += h
            out[j, :, :, k] = (markers(x, pp) - base) / h
    return out


def best_time(fn, repeats: int = 3) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default=str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"))
    ap.add_argument("--configs", type=int, default=173)
    args = ap.parse_args()

    model = load_robot_model(args.robot)
    chain = Chain(model)
    rng = np.random.default_rng(0)
    q = rng.uniform(model.lower_limits_rad, model.upper_limits_rad, (args.configs, model.n_joints))
    scale = np.concatenate([np.full(chain.n, 1e-3), np.full(2 * chain.n, 0.1), np.full(2 * chain.n, 1e-3), np.full(3 * chain.m, 0.1)])
    all_params = chain.nominal + rng.normal(size=(2000, chain.n_params)) * scale
    all_params[0] = chain.nominal

    print(f"robot: {model.name} ({chain.n} joints, {chain.n_params} parameters), {len(q)} configurations")
    print(f"{'what':<34} {'param sets':>10} {'ours evals/s':>14} {'naive evals/s':>14} {'ratio':>8}")

    # Naive baseline rate, measured once on a subset (same for every batch size: it is a loop).
    sub_q, sub_p = q[:40], all_params[:3]
    naive_t = best_time(lambda: naive_fk_all(chain, sub_q, sub_p), repeats=2)
    naive_rate = len(sub_q) * len(sub_p) / naive_t
    np.testing.assert_allclose(naive_fk_all(chain, sub_q, sub_p), chain.fk(sub_q, sub_p), atol=1e-9)

    for k in (1, 100, 2000):
        params = all_params[:k]
        t = best_time(lambda: chain.fk(q, params))
        rate = len(q) * k / t
        print(f"{'flange FK (4x4)':<34} {k:>10} {rate:>14.3e} {naive_rate:>14.3e} {rate / naive_rate:>8.1f}x")
    for k in (1, 100, 2000):
        params = all_params[:k]
        t = best_time(lambda: chain.marker_positions(q, params))
        rate = len(q) * k / t
        print(f"{'marker positions':<34} {k:>10} {rate:>14.3e} {naive_rate:>14.3e} {rate / naive_rate:>8.1f}x")

    # Jacobian: analytic, batched vs forward differences of the naive loop.
    sub_j = q[:10]
    naive_jt = best_time(lambda: naive_marker_jacobian(chain, sub_j, chain.nominal), repeats=1)
    naive_jrate = len(sub_j) / naive_jt
    ours_j = chain.marker_jacobian(sub_j, chain.nominal)[1]
    np.testing.assert_allclose(ours_j, naive_marker_jacobian(chain, sub_j, chain.nominal), atol=1e-3)
    for k in (1, 100):
        params = all_params[:k]
        t = best_time(lambda: chain.marker_jacobian(q, params))
        rate = len(q) * k / t
        print(f"{'marker Jacobian (all params)':<34} {k:>10} {rate:>14.3e} {naive_jrate:>14.3e} {rate / naive_jrate:>8.1f}x")
    print(f"(naive FK measured on {len(sub_q)}x{len(sub_p)} evaluations in {naive_t:.3f} s; "
          f"naive Jacobian on {len(sub_j)} configurations in {naive_jt:.3f} s)")


if __name__ == "__main__":
    main()
