"""Forward kinematics of ``calib.robot.kinematics.Chain`` against pybotics, the published peer.

Run: ``python tests/bench/bench_fk.py [--robot fixtures/robots/kuka_iiwa14_r820.yaml]``
(needs the bench extra: ``pip install -e ".[bench]"``; pybotics 3.1.2 pins numpy<2 but runs on
numpy 2 — install it with ``pip install --no-deps pybotics==3.1.2``).

Peer: pybotics 3.1.2 (``Robot.fk``), built from the same model: our standard-DH links rewritten
as pybotics' modified-DH links (link i takes α, a of link i−1; the last link's a, α and our
flange go into pybotics' tool; our base is its world frame; q_pybotics = sign·q). Both sides are
checked to agree to 1e-9 mm before anything is timed. Models with a Hayati β (M-DH TX60) cannot
be expressed in pybotics and are refused.

Figures, each best of a few repeats:
- one configuration, one call (what an IK polish, a jog or a GUI asks for): µs per call;
- 173 configurations (the paper's plan) × {1, 100} parameter sets: evaluations per second, ours
  batched vs pybotics in a loop (it has no batched FK);
- the parameter Jacobian of the marker positions: ours analytic and batched vs forward
  differences through pybotics' FK as pybotics' own calibration example gets its Jacobian
  (``scipy.optimize.least_squares`` with a 2-point Jacobian over the chain vector): one ``Robot``
  updated in place once per column (``OptimizationHandler.apply_optimization_vector``), then
  the FK of every configuration at that column — P + 1 updates, not P per configuration.

Both sides of every figure are timed the same way (issue 33): the same clock
(``time.perf_counter``), the same number of repetitions, interleaved (ours, peer, ours, peer, …),
best of each.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.robot.kinematics import Chain  # noqa: E402
from calib.robot.model import load_robot_model  # noqa: E402


def pybotics_parameters(chain: Chain, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``chain``'s kinematics at parameter vector ``params`` as pybotics holds them: the MDH
    chain's vector (n links × [α, a, θ, d], rad and mm) and the tool matrix (4×4, mm)."""
    n = chain.n
    if chain.model.convention != "dh" or np.any(params[4 * n:5 * n] != 0):
        raise ValueError(f"{chain.model.name}: only standard-DH models without a Hayati β map onto pybotics' links")
    d, a, alpha = params[n:2 * n], params[2 * n:3 * n], params[3 * n:4 * n]
    theta = chain.theta0 + chain.sign * params[:n]
    links = np.column_stack([np.r_[0.0, alpha[:-1]], np.r_[0.0, a[:-1]], theta, d])
    ca, sa = math.cos(alpha[-1]), math.sin(alpha[-1])
    last = np.array([[1, 0, 0, a[-1]], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1.0]])
    return links.ravel(), last @ chain.flange


def pybotics_robot(chain: Chain, params: np.ndarray):
    """A pybotics ``Robot`` with the kinematics of ``chain`` at parameter vector ``params``."""
    from pybotics.kinematic_chain import MDHKinematicChain
    from pybotics.robot import Robot
    from pybotics.tool import Tool

    links, tool = pybotics_parameters(chain, params)
    return Robot(MDHKinematicChain(links), tool=Tool(matrix=tool), world_frame=chain.base.copy())


def pybotics_update(robot, chain: Chain, params: np.ndarray) -> None:
    """Set ``robot``'s parameters to ``params`` in place, as pybotics' own optimiser does
    (``OptimizationHandler.apply_optimization_vector``: the chain's ``vector``, the tool)."""
    links, tool = pybotics_parameters(chain, params)
    robot.kinematic_chain.vector = links
    robot.tool.matrix = tool


def best_times(ours, peer, repeats: int = 3) -> tuple[float, float]:
    """Best wall time (s) of ``ours`` and of ``peer`` over ``repeats`` interleaved calls of each."""
    best = [math.inf, math.inf]
    for _ in range(repeats):
        for k, fn in enumerate((ours, peer)):
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best[0], best[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default=str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"))
    ap.add_argument("--configs", type=int, default=173)
    args = ap.parse_args()
    try:
        import pybotics  # noqa: F401
    except ImportError:
        sys.exit("bench_fk needs pybotics: pip install --no-deps pybotics==3.1.2 (the bench extra)")

    model = load_robot_model(args.robot)
    chain = Chain(model)
    rng = np.random.default_rng(0)
    q = rng.uniform(model.lower_limits_rad, model.upper_limits_rad, (args.configs, model.n_joints))
    scale = np.concatenate([np.full(chain.n, 1e-3), np.full(2 * chain.n, 0.1), np.full(chain.n, 1e-3),
                            np.zeros(chain.n), np.full(3 * chain.m, 0.1)])
    all_params = chain.nominal + rng.normal(size=(100, chain.n_params)) * scale
    all_params[0] = chain.nominal
    robots = [pybotics_robot(chain, p) for p in all_params]
    sq = q * chain.sign

    # Agreement first: a bench of two different computations is meaningless.
    for k in (0, 7):
        ours = chain.fk(q[:20], all_params[k])
        theirs = np.array([robots[k].fk(x) for x in sq[:20]])
        err = np.abs(ours - theirs).max()
        if err > 1e-9 * 1e3:
            sys.exit(f"pybotics and Chain disagree by {err:.3g} mm; fix the mapping before timing")

    print(f"robot: {model.name} ({chain.n} joints, {chain.n_params} parameters), {len(q)} configurations")
    print(f"{'what':<44} {'ours':>14} {'pybotics':>14} {'ratio':>8}")

    n_calls = 2000
    x, r0 = q[0], robots[0]
    ours_t, theirs_t = (t / n_calls for t in best_times(lambda: [chain.fk(x) for _ in range(n_calls)],
                                                         lambda: [r0.fk(sq[0]) for _ in range(n_calls)]))
    print(f"{'FK, one configuration (µs per call)':<44} {ours_t * 1e6:>14.1f} {theirs_t * 1e6:>14.1f} "
          f"{theirs_t / ours_t:>7.1f}x")
    ours_t = best_times(lambda: [chain.marker_positions(x) for _ in range(n_calls)], lambda: None)[0] / n_calls
    print(f"{'marker positions, one configuration (µs)':<44} {ours_t * 1e6:>14.1f} {'—':>14} {'':>8}")

    for k in (1, 100):
        params = all_params[:k]
        sub = robots[:k]
        t, tp = best_times(lambda: chain.fk(q, params), lambda: [r.fk(v) for r in sub for v in sq])
        ours_rate, peer_rate = len(q) * k / t, len(q) * len(sub) / tp
        print(f"{f'FK batched, {k} parameter set(s) (evals/s)':<44} {ours_rate:>14.3e} {peer_rate:>14.3e} "
              f"{ours_rate / peer_rate:>7.1f}x")

    # Parameter Jacobian of one marker: analytic vs 2-point differences through pybotics' FK as
    # least_squares takes them: the robot updated once per column, every configuration at it.
    peer = pybotics_robot(chain, chain.nominal)
    mk = chain.nominal[chain.marker_slice()].reshape(chain.m, 3)[0]
    h = 1e-7
    sq_all = q * chain.sign

    def peer_markers() -> np.ndarray:
        out = np.empty((len(q), 3))
        for j, v in enumerate(sq_all):
            t = peer.fk(v)
            out[j] = t[:3, :3] @ mk + t[:3, 3]
        return out

    def peer_jacobian() -> np.ndarray:
        out = np.zeros((len(q), 3, 4 * chain.n))
        pybotics_update(peer, chain, chain.nominal)
        p0 = peer_markers()
        for kk in range(4 * chain.n):  # offset, d, a, α of every joint
            pp = chain.nominal.copy()
            pp[kk] += h
            pybotics_update(peer, chain, pp)
            out[:, :, kk] = (peer_markers() - p0) / h
        return out

    ours_j = chain.marker_jacobian(q, chain.nominal)[1][:, 0, :, :4 * chain.n]
    np.testing.assert_allclose(ours_j, peer_jacobian(), atol=1e-3)
    tj, tpj = best_times(lambda: chain.marker_jacobian(q, chain.nominal), peer_jacobian)
    ours_rate, peer_rate = len(q) / tj, len(q) / tpj
    print(f"{'marker Jacobian (configs/s)':<44} {ours_rate:>14.3e} {peer_rate:>14.3e} {ours_rate / peer_rate:>7.1f}x")
    print("(ratio = pybotics time / our time; > 1 means we are faster)")


if __name__ == "__main__":
    main()
