"""Unit mix-ups in joint angles: a list of degrees that is really radians.

One heuristic, used by every reader of joint angles in degrees: plan joint targets and
configuration files (``acquire.plan.guards``) and measurement CSVs (``calib.measure.dataset``).

Joint angles (degrees) that all lie within ±π "degrees" (±3.15°, and not all ~0) although the
model's axes move through tens or hundreds of degrees, and that read as radians fall within
the limits, are radians: a calibration that never moves any axis more than 3° is useless, and
this is exactly what a list of radians looks like. Values that would leave the limits when read
as radians are not a units mix-up, so they pass.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

from calib.robot.model import RobotModel

#: Joint angles all within this (deg) look like radians (π plus rounding).
RADIANS_MAX_DEG = math.pi + 0.005
#: Axes whose limits span at least this (deg) take part in the radians check of joint angles.
MOVING_AXIS_SPAN_DEG = 90.0
#: Read as radians, angles may pass a limit by this much (deg): rounding, or a measured angle at the limit.
LIMIT_SLACK_DEG = 0.5
#: A row whose largest |angle| is below this (deg) says nothing (the zero pose).
TELLING_ROW_DEG = 0.05


def _fmt(values: Iterable[float]) -> str:
    return "[" + ", ".join(f"{float(v):g}" for v in values) + "]"


def radians_row(rows_deg: Sequence[Sequence[float]], model: RobotModel) -> tuple[int, str] | None:
    """If joint angles ``rows_deg`` ((m, n) degrees, n = model joints) look like radians: the index
    of the first row that shows it and why (``… (given …; allowed degrees, e.g. …)``); else None."""
    q = np.asarray(rows_deg, dtype=float)
    if q.ndim != 2 or q.shape[1] != model.n_joints or q.size == 0:
        return None
    span = np.array([hi - lo for lo, hi in (j.limits for j in model.joints)])
    moving = span >= MOVING_AXIS_SPAN_DEG
    if not moving.any() or np.max(np.abs(q)) > RADIANS_MAX_DEG or np.max(np.abs(q)) < TELLING_ROW_DEG:
        return None
    as_deg = np.degrees(q)
    lower = np.array([lo for lo, _ in (j.limits for j in model.joints)]) - LIMIT_SLACK_DEG
    upper = np.array([hi for _, hi in (j.limits for j in model.joints)]) + LIMIT_SLACK_DEG
    if not np.all((as_deg >= lower) & (as_deg <= upper)):
        return None  # read as radians they would leave the limits: not a units mix-up
    widest = int(np.argmax(span))
    lo, hi = model.joints[widest].limits
    first = next(i for i, r in enumerate(q) if np.max(np.abs(r)) >= TELLING_ROW_DEG)
    return first, (f"every joint angle of the {len(q)} configuration(s) lies within ±{math.pi:.2f}°, while "
                   f"{model.name}'s axes move through up to {hi - lo:g}° ({model.joints[widest].axis}: [{lo:g}, {hi:g}]°): "
                   f"these look like radians (given {_fmt(q[first])}; allowed degrees, e.g. "
                   f"{_fmt(np.round(as_deg[first], 2))} — multiply radians by 180/π)")


def radians_problem(rows_deg: Sequence[Sequence[float]], model: RobotModel) -> str | None:
    """Why joint angles (rows of degrees) look like radians, or None (see ``radians_row``)."""
    found = radians_row(rows_deg, model)
    return found[1] if found else None
