"""Benchmark: full identification against pybotics 3.1.2, and IOOPS 50-of-200.

Peer, measured in the same run on the same data: **pybotics 3.1.2**'s own calibration
machinery — ``pybotics.optimization.OptimizationHandler`` packs/unpacks the masked modified-DH
chain, tool and world parameters, ``Robot.fk`` gives each configuration's pose — driven by
scipy ``least_squares`` as pybotics' calibration example does, but with x/y/z residuals (its
``optimize_accuracy`` returns only |error| per configuration, which fits worse and slower).
pybotics has one tool point, so both sides fit the same single-marker data (the first marker).

The truth perturbs every identifiable parameter except the Hayati torsions β (pybotics'
modified DH cannot represent β, so perturbing it would give pybotics a model error, not a
slower fit). The pybotics nominal is our nominal regrouped exactly into Craig's modified DH
(checked against our FK before timing). Its free parameters are chosen by a pivoted QR of its
Jacobian at the nominal (not timed); both sides start from the same registration estimate
(ours computes it inside its timed call). Ours is timed with one start (the staged solve from
nominal), as the peer solves once, and again with the default multi-start. Prints wall times (ours best of 3, pybotics once),
held-out mean errors on 500 noiseless configurations, and the ratios.

    pip install --no-deps pybotics==3.1.2   # pins numpy<2 but runs on numpy 2
    python tests/bench/bench_identification.py [--robot staubli_tx60] [--configs 1000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.fit.offsets import initial_registrations  # noqa: E402
from calib.fit.identification import IdentOptions, identify, information_blocks, pose_errors  # noqa: E402
from calib.robot.kinematics import Chain  # noqa: E402
from calib.robot.model import load_robot_model  # noqa: E402
from calib.plan.observability import ioops  # noqa: E402
from tests.calib.test_identification import measure, perturbed_truth  # noqa: E402


def craig_robot(chain: Chain, params: np.ndarray, world: np.ndarray, marker: int):
    """Our chain (standard DH + β, β must be 0) regrouped into a pybotics modified-DH robot.

    ``Rz(θ1)Tz(d1)·[Tx(a1)Rx(α1)Rz(θ2)Tz(d2)]·…·Tx(a6)Rx(α6)``: Craig link i carries (α_{i-1},
    a_{i-1}, θ_i, d_i); the last Tx(a_n)Rx(α_n), the flange and the marker go into the tool.
    ``world`` (4, 4) is sensor←robot-base (our base transform included). mm and radians; the
    robot's joint values are ours times ``chain.sign``.
    """
    from pybotics.kinematic_chain import MDHKinematicChain
    from pybotics.robot import Robot
    from pybotics.tool import Tool

    n = chain.n
    if np.any(np.abs(params[chain.index("beta")]) > 0):
        raise ValueError("pybotics' modified DH has no β: use parameters with β = 0")
    off, d, a, al = (params[chain.index(k)] for k in ("offset", "d", "a", "alpha"))
    # θ = theta + sign·(q + δ): pybotics adds its joint value to θ, so it is given sign·q.
    rows = [[0.0 if i == 0 else al[i - 1], 0.0 if i == 0 else a[i - 1], chain.theta0[i] + chain.sign[i] * off[i], d[i]]
            for i in range(n)]
    kc = MDHKinematicChain.from_parameters(np.array(rows))
    c, s = np.cos(al[-1]), np.sin(al[-1])
    last = np.array([[1, 0, 0, a[-1]], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])
    mk = np.eye(4)
    mk[:3, 3] = params[chain.marker_slice()].reshape(-1, 3)[marker]
    return Robot(kinematic_chain=kc, tool=Tool(matrix=last @ chain.flange @ mk), world_frame=world @ chain.base)


def pybotics_mask(robot, q: np.ndarray, xyz: np.ndarray, mask_rows: int = 150):
    """The identifiable subset of pybotics' parameters (chain 4·n, tool 6, world 6), as its
    boolean mask, from a pivoted QR of the column-scaled Jacobian at the nominal.

    q (k, n) rad, xyz (k, 3) mm (only the first ``mask_rows`` configurations are used).
    """
    from pybotics.optimization import OptimizationHandler

    n_kc = robot.kinematic_chain.num_parameters

    def make(mask):
        return OptimizationHandler(robot=robot, kinematic_chain_mask=list(mask[:n_kc]),
                                   tool_mask=list(mask[n_kc:n_kc + 6]), world_mask=list(mask[n_kc + 6:]))

    def fun(x, h, qq, pp):
        h.apply_optimization_vector(x)
        pred = np.array([h.robot.fk(qi)[:3, 3] for qi in qq])
        return (pp - pred).ravel()

    # Free parameters: pivoted QR of the scaled Jacobian at the nominal (setup, not timed by the caller).
    full = np.ones(n_kc + 12, dtype=bool)
    full[n_kc + 3:n_kc + 6] = False  # a point measurement cannot see the tool's orientation
    h = make(full)
    x0 = h.generate_optimization_vector()
    qs, ps = q[:mask_rows], xyz[:mask_rows]
    jac = np.empty((3 * len(qs), x0.size))
    for j in range(x0.size):  # central differences: truncation and rounding far below the cut
        xp, xm = x0.copy(), x0.copy()
        xp[j] += 1e-5
        xm[j] -= 1e-5
        jac[:, j] = (fun(xp, h, qs, ps) - fun(xm, h, qs, ps)) / 2e-5
    jac /= np.maximum(np.linalg.norm(jac, axis=0), 1e-300)
    _, r, piv = scipy.linalg.qr(jac, mode="economic", pivoting=True)
    keep = piv[np.abs(np.diag(r)) > 1e-5 * abs(r[0, 0])]
    mask = np.zeros_like(full)
    mask[np.flatnonzero(full)[keep]] = True
    return mask


def run_pybotics(robot, mask, q, xyz):
    """pybotics' OptimizationHandler + Robot.fk per configuration, x/y/z residuals, scipy TRF
    with a finite-difference Jacobian. q (k, n) rad, xyz (k, 3) mm → (fitted robot, nfev)."""
    from pybotics.optimization import OptimizationHandler

    n_kc = robot.kinematic_chain.num_parameters
    h = OptimizationHandler(robot=robot, kinematic_chain_mask=list(mask[:n_kc]),
                            tool_mask=list(mask[n_kc:n_kc + 6]), world_mask=list(mask[n_kc + 6:]))

    def fun(x):
        h.apply_optimization_vector(x)
        return (xyz - np.array([h.robot.fk(qi)[:3, 3] for qi in q])).ravel()

    sol = least_squares(fun, h.generate_optimization_vector(), method="trf", x_scale="jac", xtol=1e-10, ftol=1e-10)
    h.apply_optimization_vector(sol.x)
    return h.robot, sol.nfev


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--robot", default="staubli_tx60")
    ap.add_argument("--configs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    try:
        import pybotics  # noqa: F401
    except ImportError:
        sys.exit("needs the peer: python3 -m pip install --no-deps pybotics==3.1.2")
    model = load_robot_model(ROOT / "fixtures" / "robots" / f"{args.robot}.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(args.seed)
    lo, hi = model.lower_limits_rad * 0.8, model.upper_limits_rad * 0.8
    q = rng.uniform(lo, hi, (args.configs, model.n_joints))
    q_val = rng.uniform(lo, hi, (500, model.n_joints))
    marker = chain.marker_names[0]

    def one_marker(d):
        return d.subset(np.array([mk == marker for mk in d.marker]))

    names = identify(model, one_marker(measure(model, chain, q[:100], chain.nominal, rng, 0.0))).free_names
    truth, _ = perturbed_truth(chain, [nm for nm in names if not nm.endswith(".beta")], rng)
    data = one_marker(measure(model, chain, q, truth, rng, 0.03))
    val = one_marker(measure(model, chain, q_val, truth, rng, 0.0))

    # Setup for the peer (not timed): same starting registration, exact nominal, its free set.
    b2s0 = initial_registrations(chain, data, "least-squares", 0)["sensor"]
    nominal_robot = craig_robot(chain, chain.nominal, b2s0, 0)
    ours_nominal = chain.marker_positions(data.q_rad[:50])[:, 0] @ b2s0[:3, :3].T + b2s0[:3, 3]
    q_peer, q_val_peer = data.q_rad * chain.sign, val.q_rad * chain.sign  # pybotics' joint values
    peer_nominal = np.array([nominal_robot.fk(qi)[:3, 3] for qi in q_peer[:50]])
    assert np.abs(ours_nominal - peer_nominal).max() < 1e-6, "pybotics model is not our nominal"
    mask = pybotics_mask(nominal_robot, q_peer, data.xyz_mm)

    def best_of(f, n):
        best, out = np.inf, None
        for _ in range(n):
            t0 = time.perf_counter()
            out = f()
            best = min(best, time.perf_counter() - t0)
        return best, out

    t_ours, ours = best_of(lambda: identify(model, data, IdentOptions(n_starts=1)), 3)  # one start, as the peer
    t_multi, _ = best_of(lambda: identify(model, data), 3)
    t_peer, (peer, nfev) = best_of(lambda: run_pybotics(nominal_robot, mask, q_peer, data.xyz_mm), 1)
    e_ours = pose_errors(model, ours.params, val, ours.base2sensor).mean()
    e_peer = np.linalg.norm(val.xyz_mm - np.array([peer.fk(qi)[:3, 3] for qi in q_val_peer]), axis=1).mean()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"robot {model.name}, {args.configs} calibration / 500 held-out configurations, marker {marker}, noise 0.03 mm")
    print(f"  ours (analytic Jacobian, LM, vectorised): {t_ours:8.3f} s  {len(ours.free_names):2d} parameters  "
          f"held-out mean error {e_ours:.4f} mm")
    print(f"  pybotics 3.1.2 (handler + Robot.fk, x/y/z, TRF): {t_peer:8.3f} s  {int(mask.sum()):2d} parameters  "
          f"held-out mean error {e_peer:.4f} mm  ({nfev} evaluations)")
    print(f"  speed ratio pybotics/ours: {t_peer / t_ours:.1f}×   held-out error ratio ours/pybotics: {e_ours / e_peer:.3f}")
    print(f"  ours with the default {IdentOptions().n_starts} starts (staged, plain, random): {t_multi:8.3f} s "
          f"(pybotics/ours {t_peer / t_multi:.1f}×)")

    q200 = q[:200]
    t0 = time.perf_counter()
    blocks, _, _ = information_blocks(model, q200)
    t_blocks = time.perf_counter() - t0
    t0 = time.perf_counter()
    sel = ioops(blocks, 50, index="O6", seed=args.seed)
    t_ioops = time.perf_counter() - t0
    print(f"IOOPS 50 of 200 on O6 (no peer): blocks {t_blocks:.3f} s + search {t_ioops:.3f} s ({sel.iterations} iterations), "
          f"O6 {sel.start_value:.4g} → {sel.value:.4g}")


if __name__ == "__main__":
    main()
