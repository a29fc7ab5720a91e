"""Brute-force numeric IK: many random-start damped least-squares solves, clustered.

This is the independent reference the analytic solvers (``calib.ik.ik``) are checked and
benchmarked against, and a fallback for arms outside their classes. It knows nothing about
branches or ±360° equivalents: it starts ``n_starts`` Levenberg–Marquardt solves uniformly
inside the joint limits, keeps those that converge to the pose (and, for 7R, the arm angle)
inside the limits, and merges converged joint vectors closer than ``cluster_tol`` rad.
Slow (≈0.1–0.5 s per pose) and only probabilistically complete: a solution whose basin of
attraction is tiny may be missed with few starts.
"""

from __future__ import annotations

import numpy as np

from calib.ik.ik import arm_angle_of
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.robot.transforms import log_so3

#: Weight of orientation error rows (mm per rad) so a 1 mrad error counts like 1 mm.
ROTATION_WEIGHT_MM = 1000.0


def _residual(chain: Chain, q: np.ndarray, pose: np.ndarray, params, psi_target, arm_angle_fn):
    rot, pos = chain.flange_pose(q, params)
    e = np.concatenate([pose[:3, 3] - pos, ROTATION_WEIGHT_MM * log_so3(pose[:3, :3] @ np.swapaxes(rot, -1, -2))], -1)
    if arm_angle_fn is not None:
        d = psi_target - arm_angle_fn(q)
        e = np.concatenate([e, ROTATION_WEIGHT_MM * (np.pi - np.mod(np.pi - d, 2 * np.pi))[..., None]], -1)
    return e


def solve_numeric(
    model: RobotModel,
    pose: np.ndarray,
    *,
    n_starts: int = 256,
    seed: int = 0,
    arm_angle: float | None = None,
    params: np.ndarray | None = None,
    max_iter: int = 150,
    cluster_tol: float = 1e-5,
    position_tol_mm: float = 1e-6,
    orientation_tol_rad: float = 1e-9,
) -> np.ndarray:
    """Distinct joint vectors (m, n) rad within limits that reach ``pose`` (4, 4) mm.

    For a 7-joint arm pass ``arm_angle`` (rad): the arm-angle constraint (``calib.ik.ik.arm_angle_of``)
    is added as a seventh residual. Deterministic for a given ``seed``.
    """
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (4, 4):
        raise ValueError(f"pose must be one (4, 4) flange frame, got shape {pose.shape}")
    if n_starts < 1 or max_iter < 1:
        raise ValueError(f"n_starts and max_iter must be positive, got {n_starts}, {max_iter}")
    chain = Chain(model)
    n = chain.n
    arm_angle_fn = None
    if n == 7:
        if arm_angle is None:
            raise ValueError("a 7-joint arm has a continuum of solutions: pass arm_angle (rad)")
        def arm_angle_fn(qq):
            return arm_angle_of(model, qq, params=params)

    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    rng = np.random.default_rng(seed)
    q = rng.uniform(lo, hi, (n_starts, n))
    lam = np.full(n_starts, 1e-2)
    e = _residual(chain, q, pose, params, arm_angle, arm_angle_fn)
    cost = np.sum(e**2, -1)
    for _ in range(max_iter):
        # only starts still converging: not yet at the pose, and not stuck (λ at its cap)
        act = np.flatnonzero((cost > 1e-22) & (lam < 1e8))
        if act.size == 0:
            break
        qa, ea = q[act], e[act]
        fj = chain.flange_jacobian(qa, params)
        jac = np.concatenate([fj.jp[..., :n], ROTATION_WEIGHT_MM * fj.jw[..., :n]], -2)
        if arm_angle_fn is not None:
            h = 1e-7
            base = arm_angle_fn(qa)
            shifted = arm_angle_fn(qa[:, None, :] + h * np.eye(n))  # (a, n)
            grad = (np.pi - np.mod(np.pi - (shifted - base[:, None]), 2 * np.pi)) / h
            jac = np.concatenate([jac, ROTATION_WEIGHT_MM * grad[:, None, :]], -2)
        jtj = np.swapaxes(jac, -1, -2) @ jac
        jte = np.einsum("sji,sj->si", jac, ea)
        diag = np.einsum("sii->si", jtj) + 1e-9
        damped = jtj + lam[act, None, None] * (diag[:, :, None] * np.eye(n))
        q_new = qa + np.linalg.solve(damped, jte[..., None])[..., 0]
        e_new = _residual(chain, q_new, pose, params, arm_angle, arm_angle_fn)
        cost_new = np.sum(e_new**2, -1)
        better = cost_new < cost[act]
        q[act] = np.where(better[:, None], q_new, qa)
        e[act] = np.where(better[:, None], e_new, ea)
        cost[act] = np.where(better, cost_new, cost[act])
        lam[act] = np.where(better, np.maximum(lam[act] / 3.0, 1e-12), lam[act] * 4.0)
    rot, pos = chain.flange_pose(q, params)
    dp = np.linalg.norm(pos - pose[:3, 3], axis=-1)
    dr = np.linalg.norm(log_so3(pose[:3, :3] @ np.swapaxes(rot, -1, -2)), axis=-1)
    ok = (dp <= position_tol_mm) & (dr <= orientation_tol_rad) & model.within_limits(q)
    if arm_angle_fn is not None:
        d = arm_angle - arm_angle_fn(q)
        ok &= np.abs(np.pi - np.mod(np.pi - d, 2 * np.pi)) <= 1e-7
    found: list[np.ndarray] = []
    for row in q[ok]:
        if not any(np.max(np.abs(row - f)) < cluster_tol for f in found):
            found.append(row)
    return np.array(found).reshape(-1, n)
