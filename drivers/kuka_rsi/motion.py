"""An RSI move checked against the verified state and planned as a table of corrections.

``plan_move`` is everything slow about a move, done in the caller's process before the
exchange gets it: the state must be verified (a packet received, the session not ended with
the Stop flag, no motion running, measured and commanded positions within
``max_deviation_rad``), the jerk-limited trajectory from the commanded position must fit in the
timeout, and it is sampled once per cycle into ``RSI_ON(#ABSOLUTE)`` corrections ``AK``:
degrees from the session reference ``ASPos``, the last row exactly the target.
Every refusal is a LimitError (DeviceTimeoutError before the first packet): nothing moved. A refusal
for the state (session ended, a motion running, not at rest) is a NotReadyError: it may clear by itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.errors import DeviceTimeoutError, LimitError, NotReadyError
from drivers.protocols import JointLimits
from drivers.trajectory import JointTrajectory, scaled_limits


@dataclass(frozen=True)
class PlannedMove:
    """rows: shape (cycles, n_axes), corrections in degrees from the session reference, one per
    cycle; trajectory: the plan they sample (rad, s); session: the RSI session checked."""

    rows: np.ndarray
    trajectory: JointTrajectory
    cycles: int
    session: int


def plan_move(snap: dict | None, busy: bool, start_rad: np.ndarray, target_rad: np.ndarray, speed: float, *,
              limits: JointLimits, max_jerk_rad_s3: np.ndarray, max_deviation_rad: float, dt: float,
              timeout: float, name: str) -> PlannedMove:
    """Check and plan a move from the exchange's latest state ``snap`` (``RsiLink.snapshot``:
    ``ref`` / ``cmd`` in degrees, ``session_ended``, ``session``), ``busy`` (a motion running),
    the measured ``start_rad`` and ``target_rad`` (shape (n_axes,), rad) at ``speed`` (fraction of
    the limits), cycle ``dt`` (s) within ``timeout`` (s). See the module docstring."""
    if snap is None:
        raise DeviceTimeoutError(f"{name}: no packet from the controller yet (call connect())")
    if snap["session_ended"][0]:
        raise NotReadyError(f"{name}: the RSI session was ended with the Stop flag; restart the RSI program")
    if busy:
        raise NotReadyError(f"{name}: a motion is already running")
    ref = snap["ref"]
    commanded = np.radians(ref + snap["cmd"])
    deviation = np.abs(start_rad - commanded)
    if np.max(deviation) > max_deviation_rad:
        i = int(np.argmax(deviation))
        raise NotReadyError(
            f"{name}: measured and commanded positions disagree by {math.degrees(deviation[i]):.3f}° "
            f"on axis {i + 1} (allowed {math.degrees(max_deviation_rad):.3f}°); wait until settled"
        )
    v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed, max_jerk_rad_s3)
    traj = JointTrajectory.plan(commanded, target_rad, v, a, j)
    m = max(1, math.ceil(traj.duration / dt - 1e-9))
    wall = m * dt
    if wall + 10 * dt > timeout:
        raise LimitError(
            f"{name}: the move takes {wall:.3f} s at speed {speed}, longer than the timeout {timeout:.3f} s"
        )
    pos, _, _ = traj.sample(dt * np.arange(1, m + 1))
    pos[-1] = target_rad
    return PlannedMove(rows=np.degrees(pos) - ref, trajectory=traj, cycles=m, session=int(snap["session"][0]))
