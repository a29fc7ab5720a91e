"""CommanderBase.first_state: waits for a controller that has not sent yet, and gives up."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import CommanderBase
from drivers.errors import DeviceTimeoutError
from drivers.protocols import JointLimits, JointState


class _LateController(CommanderBase):
    """A commander whose controller starts streaming ``after_s`` wall seconds after creation."""

    def __init__(self, after_s: float) -> None:
        limits = JointLimits(np.full(2, -1.0), np.full(2, 1.0), np.full(2, 1.0), np.full(2, 2.0))
        super().__init__("late", limits)
        self.t0, self.after_s, self.calls = time.monotonic(), after_s, 0

    def joint_state(self) -> JointState:
        self.calls += 1
        if time.monotonic() - self.t0 < self.after_s:
            raise DeviceTimeoutError("late: no monitoring message received yet")
        now = self.clock()
        return JointState(np.zeros(2), now, now)


def test_first_state_waits_for_a_controller_that_starts_late():
    c = _LateController(0.3)
    state = c.first_state(10.0)
    assert np.array_equal(state.position_rad, np.zeros(2)) and c.calls > 1
    assert time.monotonic() - c.t0 >= 0.3


def test_first_state_gives_up_with_the_controllers_reason():
    c = _LateController(60.0)
    with pytest.raises(DeviceTimeoutError, match="no monitoring message received yet"):
        c.first_state(0.2)
