"""The socket joint sensor's triggers, on a scripted joint-state stream and a stepped clock
(no wall time): guided off the commanded position and then still → "still"; confirm → at
once; a robot that is never guided is not recorded (a jogged KR needs the confirmation)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.errors import DeviceTimeoutError
from drivers.protocols import JointSensor, JointState
from drivers.registry import load_driver
from drivers.socket import SocketSensor


class SteppedClock:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


class ScriptedArm:
    """joint_state(): commanded position held at zero; measured = path(t) from the clock."""

    def __init__(self, clock: SteppedClock, path) -> None:
        self.clock, self.path = clock, path

    def joint_state(self) -> JointState:
        t = self.clock.now()
        return JointState(position_rad=np.asarray(self.path(t), dtype=float), device_time=t, host_time=t,
                          commanded_rad=np.zeros(7))


def sensor(clock, arm, **kw) -> SocketSensor:
    s = SocketSensor.from_url("operator://none?window_s=0.5&guide_deg=0.05&still_deg=0.01&poll_s=0.01",
                              clock=clock.now, sleep=clock.sleep, commander=arm, **kw)
    s.connect()
    return s


def guided(t: float) -> np.ndarray:
    """At rest until 1 s, pushed by up to 0.3° over 1 s, then held (the ball in the socket)."""
    push = np.radians([0.0, 0.3, -0.2, 0.1, 0.0, 0.05, 0.0])
    return push * min(max(t - 1.0, 0.0), 1.0)


def test_registered_and_a_joint_sensor():
    assert load_driver("socket") is SocketSensor
    clock = SteppedClock()
    assert isinstance(sensor(clock, ScriptedArm(clock, guided)), JointSensor)


def test_records_once_guided_and_held_still_for_the_window():
    clock = SteppedClock()
    cap = sensor(clock, ScriptedArm(clock, guided)).capture("socket 0 of placement front", 5, 30.0)
    assert cap.trigger == "still" and cap.count == 5
    np.testing.assert_allclose(cap.mean_rad, guided(10.0), atol=1e-12)  # the held position, not the approach
    assert np.all(cap.std_rad < 1e-12)
    # still from 2 s (end of the push) plus the 0.5 s window, not before
    assert 2.5 <= clock.t < 2.7


def test_a_robot_that_is_never_guided_is_not_recorded():
    clock = SteppedClock()
    s = sensor(clock, ScriptedArm(clock, lambda t: np.zeros(7)))
    with pytest.raises(DeviceTimeoutError, match="not held in socket 1 within 3 s; guide it in"):
        s.capture("socket 1", 3, 3.0)


def test_moving_arm_is_not_still():
    clock = SteppedClock()
    drift = lambda t: np.radians([0, 0.2 + 0.05 * t, 0, 0, 0, 0, 0])  # guided, never still: 0.05°/s
    with pytest.raises(DeviceTimeoutError):
        sensor(clock, ScriptedArm(clock, drift)).capture("socket 0", 3, 5.0)


def test_confirm_records_at_once_even_unguided():
    clock = SteppedClock()
    s = sensor(clock, ScriptedArm(clock, lambda t: np.full(7, 0.001)))
    step = clock.sleep

    def sleep(dt):  # the operator presses Enter (or the daemon's confirm) at 0.2 s
        step(dt)
        if clock.t >= 0.2:
            s.confirm()

    s._sleep = sleep
    cap = s.capture("socket 0", 2, 30.0)
    assert cap.trigger == "confirm" and 0.2 <= clock.t < 0.3


@pytest.mark.parametrize("url, fragment", [
    ("socket://127.0.0.1:1", "operator://terminal or operator://none"),
    ("operator://none?window=1", "unknown option 'window'"),
    ("operator://none?still_deg=0.1&guide_deg=0.05", "must be below guide_deg"),
])
def test_bad_urls_say_what_is_allowed(url, fragment):
    with pytest.raises(ValueError, match=fragment):
        SocketSensor.from_url(url)


def test_without_a_commander_says_so():
    s = SocketSensor.from_url("operator://none")
    with pytest.raises(Exception, match="no commander attached"):
        s.capture("socket 0", 1, 1.0)


class ArmWithButton(ScriptedArm):
    """A commander that also reads a controller input: pressed while ``button(t)`` is true."""

    def __init__(self, clock, path, button) -> None:
        super().__init__(clock, path)
        self.button = button

    def digital_input(self, name: str) -> bool:
        assert name == "MediaFlange.UserButton"
        return bool(self.button(self.clock.now()))


def button_sensor(clock, arm) -> SocketSensor:
    s = SocketSensor.from_url("operator://none?window_s=0.5&poll_s=0.01&input=MediaFlange.UserButton",
                              clock=clock.now, sleep=clock.sleep, commander=arm)
    s.connect()
    return s


def test_a_press_of_the_controller_input_records_at_once():
    clock = SteppedClock()
    arm = ArmWithButton(clock, lambda t: np.full(7, 0.001), lambda t: 0.3 <= t < 0.5)
    cap = button_sensor(clock, arm).capture("socket 0", 2, 30.0)
    assert cap.trigger == "input" and 0.3 <= clock.t < 0.35


def test_a_button_held_from_before_confirms_only_when_pressed_again():
    clock = SteppedClock()
    pressed = lambda t: t < 0.2 or 0.6 <= t < 0.8  # still held from the last socket, then pressed anew
    cap = button_sensor(clock, ArmWithButton(clock, lambda t: np.zeros(7), pressed)).capture("socket 1", 2, 30.0)
    assert cap.trigger == "input" and 0.6 <= clock.t < 0.65
    clock = SteppedClock()
    stuck = ArmWithButton(clock, lambda t: np.zeros(7), lambda t: True)  # stuck: never released
    with pytest.raises(DeviceTimeoutError, match="not held in socket 1 within 2 s"):
        button_sensor(clock, stuck).capture("socket 1", 2, 2.0)


def test_an_input_needs_a_commander_that_reads_inputs():
    clock = SteppedClock()
    with pytest.raises(ValueError, match="input=MediaFlange.UserButton needs a commander that reads the controller's "
                                         "inputs .*confirm with Enter"):
        button_sensor(clock, ScriptedArm(clock, guided))
