"""``plan_move``: an RSI move is refused from an unverified state and planned within the limits.

Pure planning, no controller: the state is the exchange's snapshot as ``RsiLink.snapshot``
gives it (degrees), built here by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.errors import DeviceTimeoutError, LimitError, NotReadyError
from drivers.kuka_rsi.motion import plan_move
from drivers.trajectory import default_jerk

DT = 0.004


def _snap(ref_deg, cmd_deg=None, *, ended=False, session=3) -> dict:
    ref = np.asarray(ref_deg, float)
    return {"ref": ref, "cmd": np.zeros_like(ref) if cmd_deg is None else np.asarray(cmd_deg, float),
            "session_ended": np.array([1.0 if ended else 0.0]), "session": np.array([float(session)])}


def _plan(limits, snap, start_rad, target_rad, *, busy=False, speed=0.5, timeout=30.0):
    jerk = default_jerk(np.asarray(limits.max_velocity_rad_s), np.asarray(limits.max_acceleration_rad_s2))
    return plan_move(snap, busy, np.asarray(start_rad, float), np.asarray(target_rad, float), speed, limits=limits,
                     max_jerk_rad_s3=jerk, max_deviation_rad=math.radians(2.0), dt=DT, timeout=timeout, name="rsi")


def test_a_planned_move_steps_within_the_scaled_speed_and_ends_exactly_on_target(limits):
    ref = np.array([0.0, -90.0, 90.0, 0.0, 0.0, 0.0])
    target = np.radians(ref + [10.0, -5.0, 20.0, 0.0, 30.0, -15.0])
    move = _plan(limits, _snap(ref), np.radians(ref), target, speed=0.5)
    assert move.rows.shape == (move.cycles, 6) and move.session == 3
    np.testing.assert_allclose(move.rows[-1], np.degrees(target) - ref, atol=1e-9)
    steps = np.abs(np.diff(np.vstack([np.zeros(6), move.rows]), axis=0))  # degrees per cycle
    assert np.all(steps <= np.degrees(0.5 * np.asarray(limits.max_velocity_rad_s)) * DT * (1 + 1e-6))


@pytest.mark.parametrize("change, error, words", [
    (dict(snap=None), DeviceTimeoutError, "no packet from the controller"),
    (dict(ended=True), NotReadyError, "ended with the Stop flag"),  # the program restarts: a run waits for it
    (dict(busy=True), NotReadyError, "already running"),
    (dict(start_offset_deg=3.0), NotReadyError, "disagree by 3.000° on axis 2"),
    (dict(timeout=0.2), LimitError, "longer than the timeout"),  # not a state: the plan's timeout is too short
])
def test_an_unverified_state_or_a_too_long_move_is_refused(limits, change, error, words):
    ref = np.zeros(6)
    snap = None if "snap" in change else _snap(ref, ended=change.get("ended", False))
    start = np.radians(ref)
    start[1] += math.radians(change.get("start_offset_deg", 0.0))
    with pytest.raises(error, match=words) as refused:
        _plan(limits, snap, start, np.radians([20.0, 0, 0, 0, 0, 0]), busy=change.get("busy", False),
              timeout=change.get("timeout", 30.0))
    assert isinstance(refused.value, NotReadyError) == (error is NotReadyError)
