"""Approach configurations for socket calibration: the ball on the flange at a socket, in many
orientations, chosen so that the gravity torques differ as much as possible between them.

For each socket (its position known roughly, e.g. with a tape, in the robot base frame) the
candidates are flange orientations whose ball direction (flange z) points down into the socket,
tilted by up to ``tilt_deg`` from the vertical at a random azimuth and rolled about itself;
each is solved by the model's analytic IK (``calib.ik.ik``), every branch within the limits kept.
From the candidates, ``n`` are kept by greedy farthest-point selection in the space of the
gravity torques (``calib.robot.gravity``, N·m) and the joint angles (rad), each scaled by its spread:
configurations that load the joints differently let a fit tell the gravity sag (a compliance
times the torque) from a constant zero-offset, and different joint angles separate the offsets
from each other. Without link masses in the model the joint angles alone decide.

The robot only *approaches* with these: the nominal model puts the ball within millimetres of
the socket, and the operator guides it the rest of the way in (``drivers.socket``).

Units: mm and radians inside; seeded, so the same plan gives the same configurations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.robot.model import RobotModel


@dataclass(frozen=True)
class SocketApproach:
    """One approach configuration: q (n,) rad, its IK branch label, and the flange pose's
    tilt from the vertical (rad)."""

    q: np.ndarray
    branch: str
    tilt_rad: float


def _frame_down(tilt: float, azimuth: float, roll: float) -> np.ndarray:
    """Rotation (3, 3) whose z axis points down, tilted by ``tilt`` towards ``azimuth``, rolled
    by ``roll`` about that z axis."""
    z = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), -math.cos(tilt)])
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def socket_approaches(model: RobotModel, socket_mm, ball_mm, n: int, *, seed: int = 0,
                      tilt_deg: tuple[float, float] = (0.0, 45.0), limit_margin_rad: float = 0.0,
                      candidates: int | None = None) -> list[SocketApproach]:
    """``n`` approach configurations that put the nominal ball (``ball_mm`` (3,), flange frame)
    at ``socket_mm`` (3,) robot base frame. Raises ValueError when fewer than ``n`` candidates
    reach the socket within the limits (less the margin), saying how many did."""
    from calib.ik import ik
    from calib.robot.kinematics import Chain

    socket = np.asarray(socket_mm, dtype=float)
    ball = np.asarray(ball_mm, dtype=float)
    rng = np.random.default_rng(seed)
    m = candidates or max(8 * n, 24)
    lo, hi = np.radians(tilt_deg[0]), np.radians(tilt_deg[1])
    poses, tilts = [], []
    for _ in range(m):
        tilt = float(rng.uniform(lo, hi))
        rot = _frame_down(tilt, float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(-math.pi, math.pi)))
        pose = np.eye(4)
        pose[:3, :3] = rot
        pose[:3, 3] = socket - rot @ ball
        poses.append(pose)
        tilts.append(tilt)
    qs, labels, tilt_of = [], [], []
    for sol, tilt in zip(ik.solve_many(model, np.array(poses), within_limits=True), tilts):
        if len(sol) == 0:
            continue
        keep = model.within_limits(np.asarray(sol.q), limit_margin_rad)
        for q, label, k in zip(sol.q, sol.branch, keep):
            if k:
                qs.append(np.asarray(q, dtype=float))
                labels.append(label)
                tilt_of.append(tilt)
    if len(qs) < n:
        raise ValueError(f"only {len(qs)} of {m} orientations reach the socket at {socket.round(1).tolist()} mm "
                         f"within the limits of {model.name} (wanted {n}); move the socket closer or lower the tilt")
    q = np.array(qs)
    feats = [q]
    if model.has_dynamics:
        from calib.robot.gravity import gravity_torques

        feats.append(gravity_torques(Chain(model), q))
    x = np.concatenate([f / np.maximum(f.std(axis=0), 1e-9) for f in feats], axis=1)
    chosen = [int(np.argmax(np.linalg.norm(x - x.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(x - x[chosen[0]], axis=1)
    while len(chosen) < n:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(x - x[nxt], axis=1))
    return [SocketApproach(q[i], labels[i], tilt_of[i]) for i in chosen]
