"""The shared driver base: refusals before motion, stale state, stability-window settling on an
injected clock, averaging with lost targets, and the lazy registry."""

import math

import numpy as np
import pytest

from drivers.base import CommanderBase, SensorBase, check_timeout
from drivers.errors import DeviceTimeoutError, DriverUnavailableError, LimitError, TargetLostError
from drivers.protocols import JointLimits, JointState, MarkerSample
from drivers.registry import BUILTIN, known_drivers, load_driver

LIMITS = JointLimits(
    lower_rad=np.radians([-170.0, -120.0]),
    upper_rad=np.radians([170.0, 120.0]),
    max_velocity_rad_s=np.radians([85.0, 85.0]),
    max_acceleration_rad_s2=np.radians([255.0, 255.0]),
    names=("A1", "A2"),
)


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class ScriptedCommander(CommanderBase):
    """Reports a scripted sequence of positions, one per poll, on a fake clock."""

    def __init__(self, positions, clock, **kw) -> None:
        super().__init__("scripted", LIMITS, clock=clock, **kw)
        self.positions = list(positions)
        self.moves = []

    def joint_state(self) -> JointState:
        q = self.positions.pop(0) if len(self.positions) > 1 else self.positions[0]
        return JointState(np.asarray(q, dtype=float), device_time=self.clock(), host_time=self.clock())

    def _move_internal(self, start, target, speed, timeout) -> None:
        self.moves.append((start.position_rad.copy(), target, speed))

    def _sleep(self, dt: float) -> None:
        self.clock.t += dt


def test_targets_outside_limits_or_margin_are_refused_before_moving():
    clock = FakeClock()
    c = ScriptedCommander([[0.0, 0.0]], clock, max_speed=0.3)
    with pytest.raises(LimitError, match=r"A2=119\.800° not in \[-119\.500, 119\.500\]°"):
        c.move_to(np.radians([0.0, 119.8]), speed=0.1, timeout=1.0)
    with pytest.raises(LimitError, match="speed 0.5 is not allowed; the plan allows \\(0, 0.3\\]"):
        c.move_to(np.zeros(2), speed=0.5, timeout=1.0)
    with pytest.raises(LimitError, match="shape"):
        c.move_to(np.zeros(3), speed=0.1, timeout=1.0)
    with pytest.raises(LimitError, match="not finite"):
        c.move_to(np.array([0.0, np.nan]), speed=0.1, timeout=1.0)
    assert c.moves == []
    c.move_to(np.radians([10.0, -20.0]), speed=0.3, timeout=1.0)
    assert len(c.moves) == 1


def test_stale_or_wrongly_sized_state_is_refused():
    clock = FakeClock()
    c = ScriptedCommander([[0.0, 0.0]], clock)
    state = JointState(np.zeros(2), device_time=0.0, host_time=clock.t - 0.5)
    with pytest.raises(LimitError, match="500 ms old"):
        c.check_state(state)
    with pytest.raises(LimitError, match="reports 3 axes"):
        c.check_state(JointState(np.zeros(3), 0.0, clock.t))


def test_settled_only_after_the_window_holds_and_restarts_when_it_breaks():
    clock = FakeClock()
    moving = [[0.0, 0.0], [0.001, 0.0], [0.002, 0.0]]  # still moving: window restarts
    still = [[0.002, 0.0]] * 400
    c = ScriptedCommander(moving + still, clock)
    t0 = clock.t
    c.wait_settled(tolerance_rad=1e-4, window_s=0.5, timeout=5.0, poll_s=0.01)
    # The last change is seen at t0 + 0.01 (first poll without a sleep, second after one), so
    # the window ends half a second after that, not half a second after the start.
    assert 0.5 + 0.01 <= clock.t - t0 < 0.5 + 0.03


def test_settle_times_out_and_rejects_a_window_longer_than_the_timeout():
    clock = FakeClock()
    c = ScriptedCommander([[0.0, 0.0], [0.01, 0.0]] * 1000, clock)
    with pytest.raises(DeviceTimeoutError):
        c.wait_settled(tolerance_rad=1e-4, window_s=0.2, timeout=1.0, poll_s=0.01)
    with pytest.raises(ValueError, match="shorter than timeout"):
        c.wait_settled(tolerance_rad=1e-4, window_s=2.0, timeout=1.0)


class ListSensor(SensorBase):
    def __init__(self, frames) -> None:
        super().__init__("list")
        self.frames = list(frames)

    def _read_internal(self, timeout: float):
        if not self.frames:
            raise DeviceTimeoutError("no more frames")
        return self.frames.pop(0)


def sample(marker, xyz, visible=True):
    return MarkerSample(marker, np.asarray(xyz, dtype=float), device_time=0.0, host_time=0.0, visible=visible)


def test_measure_averages_only_the_requested_marker():
    frames = [[sample("a", [i, 0, 0]), sample("b", [100, 0, 0])] for i in range(4)]
    m = ListSensor(frames).measure("a", 4, timeout=1.0)
    np.testing.assert_allclose(m.mean_mm, [1.5, 0, 0])
    assert m.count == 4 and m.std_mm[0] == pytest.approx(np.std([0, 1, 2, 3], ddof=1))


def test_measure_reports_a_lost_target():
    frames = [[sample("a", [0, 0, 0])], [sample("a", [np.nan] * 3, visible=False)]]
    with pytest.raises(TargetLostError, match="'a' is not visible"):
        ListSensor(frames).measure("a", 3, timeout=1.0)


def test_visible_non_finite_samples_are_a_driver_bug():
    with pytest.raises(ValueError, match="non-finite"):
        ListSensor([[sample("a", [np.nan, 0, 0])]]).read(1.0)


@pytest.mark.parametrize("bad", [0, -1, math.inf, math.nan, "1"])
def test_bad_timeouts_are_refused(bad):
    with pytest.raises(ValueError, match="timeout"):
        check_timeout(bad)


def test_registry_lists_known_drivers_and_loads_lazily():
    assert set(BUILTIN) <= set(known_drivers())
    with pytest.raises(ValueError, match="known drivers: .*natnet"):
        load_driver("no-such-driver")


def test_registry_wraps_import_failures(monkeypatch):
    monkeypatch.setitem(BUILTIN, "broken", "drivers.does_not_exist:Nothing")
    with pytest.raises(DriverUnavailableError) as err:
        load_driver("broken")
    assert isinstance(err.value.__cause__, ImportError)
