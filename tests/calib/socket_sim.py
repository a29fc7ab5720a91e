"""A simulated socket cell for the socket-fit tests: a true arm (hidden zero-offsets and link
errors), a ball on its flange, a two-socket tool in several placements, and the configurations
an operator would produce by putting the ball into each socket (position IK of the true arm
from varied starting configurations), with the ball's play in the socket as noise."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.fit.socket import SocketDataset, with_distance


def true_params(chain: Chain, rng: np.random.Generator, *, offset_deg: float = 0.05, link_mm: float = 0.2,
                twist_deg: float = 0.02, ball=(0.5, -0.3, 40.0)) -> np.ndarray:
    """Nominal vector with hidden offsets, link errors (d, a, α drawn from the stated sds) and the ball."""
    n = chain.n
    p = chain.nominal.copy()
    p[:n] = np.radians(rng.normal(0, offset_deg, n))
    p[chain.index("d")] += rng.normal(0, link_mm, n)
    p[chain.index("a")] += rng.normal(0, link_mm, n)
    p[chain.index("alpha")] += np.radians(rng.normal(0, twist_deg, n))
    ms = chain.marker_slice()
    p[ms.start:ms.start + 3] = ball
    return p


def equivalent_ball(chain: Chain, truth: np.ndarray) -> np.ndarray:
    """The true ball expressed through the nominal last link: what a socket fit can recover,
    since the last link's offset, d, a and α only move the ball within the flange frame."""
    from calib.robot.transforms import rot_x, rot_z

    n = chain.n
    j = n - 1

    def link(delta, d, a, alpha):
        t = np.eye(4)
        t[:3, :3] = rot_z(chain.sign[j] * delta)
        t2 = np.eye(4)
        t2[2, 3], t2[0, 3] = d, a
        t3 = np.eye(4)
        t3[:3, :3] = rot_x(alpha)
        return t @ t2 @ t3

    nom, tru = chain.nominal, truth
    ms = chain.marker_slice()
    b = np.append(tru[ms.start:ms.start + 3], 1.0)
    t_true = link(tru[j], tru[n + j], tru[2 * n + j], tru[3 * n + j]) @ chain.flange
    t_nom = link(0.0, nom[n + j], nom[2 * n + j], nom[3 * n + j]) @ chain.flange
    return (np.linalg.inv(t_nom) @ t_true @ b)[:3]


def _ik_points(chain: Chain, truth: np.ndarray, q0: np.ndarray, target: np.ndarray, iterations: int = 30) -> np.ndarray:
    """Joint angles near each row of ``q0`` (k, n) that put the true ball at ``target`` (k, 3) or
    (3,): batched Gauss–Newton with minimum-norm steps (the arm's self-motion is left alone)."""
    q = q0.copy()
    for _ in range(iterations):
        pos, jac = chain.marker_jacobian(q, truth)
        err = pos[:, 0] - target
        if np.max(np.abs(err)) < 1e-9:
            break
        q -= np.einsum("kij,kj->ki", np.linalg.pinv(jac[:, 0, :, : chain.n]), err)
    return q


def _configurations(chain: Chain, truth: np.ndarray, q_ref: np.ndarray, c: np.ndarray, k: int,
                    spread_rad: float, rng: np.random.Generator, tries: int = 5) -> np.ndarray | None:
    """``k`` within-limit configurations that put the true ball at ``c``, or None."""
    lo, hi = chain.model.lower_limits_rad, chain.model.upper_limits_rad
    found: list[np.ndarray] = []
    for _ in range(tries):
        q0 = np.clip(q_ref + rng.normal(0, spread_rad, (2 * k, chain.n)), lo, hi)
        with np.errstate(all="ignore"):
            q = _ik_points(chain, truth, q0, c)
            ok = (np.linalg.norm(chain.marker_positions(q, truth)[:, 0] - c, axis=1) < 1e-6) \
                & np.all((q >= lo) & (q <= hi), axis=1)
        found += list(q[ok])
        if len(found) >= k:
            return np.array(found[:k])
    return None


def _commanded(chain: Chain, truth: np.ndarray, q_phys: np.ndarray, compliance: np.ndarray) -> np.ndarray:
    """The commanded angles (k, n) that sag to ``q_phys``: q = q_phys − sign·k·τ(q; truth), by
    fixed-point iteration (the sag is ~1e-4 rad, so each step gains ~4 digits)."""
    from calib.robot.gravity import gravity_torques

    q = q_phys.copy()
    for _ in range(4):
        q = q_phys - chain.sign * compliance * gravity_torques(chain, q, truth)
    return q


def simulate(model: RobotModel, truth: np.ndarray, rng: np.random.Generator, *, placements: int = 3,
             per_socket: int = 20, distance_mm: float = 50.0, play_mm: float = 0.1,
             spread_rad: float = 0.5, compliance: np.ndarray | None = None) -> tuple[SocketDataset, np.ndarray]:
    """Socket data from the true arm; returns the dataset and the true socket points (g, 3).
    ``compliance`` (n,) rad/(N·m): the arm sags under its own weight (the model needs link
    masses) — the recorded angles are the commanded ones, q_cmd + sign·k·τ(q_cmd) on the true arm
    being the angles that put the ball in the socket (``_commanded``).

    Each placement: a reference configuration puts the ball at socket 0; socket 1 is
    ``distance_mm`` away horizontally. Each recorded configuration starts from the reference
    perturbed by ``spread_rad`` per joint and is solved onto the socket (the arm's self-motion),
    then onto a point off the centre by the ball's play; out-of-limit results are redrawn.
    """
    chain = Chain(model)
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    groups, points, q_all, g_all = [], [], [], []
    while len(groups) < 2 * placements:
        q_ref = rng.uniform(lo * 0.6, hi * 0.6)
        c0 = chain.marker_positions(q_ref, truth)[0]
        if not (300 < np.hypot(c0[0], c0[1]) < 800 and c0[2] > 0):
            continue
        yaw = rng.uniform(0, 2 * np.pi)
        sockets = [c0 + si * distance_mm * np.array([np.cos(yaw), np.sin(yaw), 0.0]) for si in range(2)]
        qs = [_configurations(chain, truth, q_ref, c, per_socket, spread_rad, rng) for c in sockets]
        if any(q is None for q in qs):
            continue  # a placement the arm cannot serve well: the operator moves the tool
        for si, (c, q) in enumerate(zip(sockets, qs)):
            groups.append((f"p{len(groups) // 2}", str(si)))
            points.append(c)
            q_phys = _ik_points(chain, truth, q, c + rng.normal(0, play_mm, (per_socket, 3)))
            q_all += list(q_phys if compliance is None else _commanded(chain, truth, q_phys, compliance))
            g_all += [len(groups) - 1] * per_socket
    ds = SocketDataset(np.array(q_all), np.array(g_all), groups, with_distance(groups, distance_mm),
                       source="simulated socket cell")
    return ds, np.array(points)
