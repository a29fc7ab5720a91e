"""Device faults that pass are waited out (``acquire.run.suspenders.DeviceFaultSuspender`` and the
run's ``ConfigurationRunner``), on simulated time: no sleeping, no sockets.

A fault suspends the run with one line, the devices are probed until ready within the plan's
allowance for the device that faulted, then the configuration starts again at its move; a fault
that outlasts its allowance fails that configuration; a refusal for the target fails it at once.
"""

from __future__ import annotations

import logging
import re
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from acquire.run.procedure import ConfigurationRunner
from acquire.run.sequencer import SensorSpec, SequencingSettings
from acquire.run.suspenders import DeviceFaultSuspender, LostTargetSuspender, Probe
from drivers.errors import DeviceTimeoutError, LimitError, NotReadyError
from drivers.protocols import JointLimits, JointState, MarkerMeasurement, MarkerSample

from test_sequencer import ManualClock  # noqa: E402 - the sequencer tests' simulated clock (tests/acquire on sys.path)


def down_until(clock: ManualClock, t_back: float, what: str = "drives not ACTIVE"):
    """A probe check that raises NotReadyError until ``clock`` reaches ``t_back``."""
    def check() -> None:
        if clock.now() < t_back:
            raise NotReadyError(f"fri: {what}")
    return check


def suspender(clock: ManualClock, events: list, settle_after_s: float = 0.2) -> DeviceFaultSuspender:
    return DeviceFaultSuspender(clock=clock.now, sleep=clock.sleep, settle_after_s=settle_after_s,
                                event=lambda kind, **f: events.append((kind, f)))


def test_a_fault_that_passes_within_its_allowance_is_waited_out_and_verified_again():
    clock, events = ManualClock(), []
    probes = [Probe("fri", down_until(clock, 2.0), 30.0), Probe("mocap", lambda: None, 5.0)]
    rec = suspender(clock, events).recover("p1", "move: drives not ACTIVE", probes)
    assert rec.action == "resume"
    assert 2.2 <= clock.now() < 2.5  # back at 2 s, ready again 0.2 s later (the settle delay)
    assert [k for k, _ in events] == ["suspended", "resumed"]
    assert events[0][1]["device"] == "fri" and events[0][1]["allowance_s"] == 30.0  # the robot's allowance
    assert events[0][1]["not_ready"] == ["fri: drives not ACTIVE"]


def test_a_fault_that_outlasts_its_allowance_fails_and_says_how_long_it_waited():
    clock, events = ManualClock(), []
    probes = [Probe("mocap", down_until(clock, 100.0, "no frame"), 5.0)]
    rec = suspender(clock, events).recover("p1", "settle: no frame", probes)
    assert rec.action == "fail"
    assert 5.0 <= clock.now() < 5.2
    assert "allowed 5 s" in rec.reason and "no frame" in rec.reason
    assert [k for k, _ in events] == ["suspended"]


def test_the_allowance_runs_from_the_first_fault_at_the_configuration():
    clock, events = ManualClock(), []
    clock.t = 4.0  # a second fault at the same configuration, 4 s after the first
    rec = suspender(clock, events).recover("p1", "again", [Probe("fri", down_until(clock, 100.0), 5.0)], since=0.0)
    assert rec.action == "fail" and 5.0 <= clock.now() < 5.2


def test_a_device_that_drops_again_while_settling_is_waited_for_again():
    clock, events = ManualClock(), []
    flaps = iter([True, False, True, True, False, False, False])  # down, up, down (in the settle), … up

    def check() -> None:
        if next(flaps, False):
            raise NotReadyError("fri: session is MONITORING_WAIT")

    rec = suspender(clock, events).recover("p1", "session dropped", [Probe("fri", check, 10.0)])
    assert rec.action == "resume"
    assert [k for k, _ in events] == ["suspended", "resumed"]


def test_a_fault_already_over_at_the_first_probe_is_a_retry_without_a_suspension():
    clock, events = ManualClock(), []
    rec = suspender(clock, events).recover("p1", "one late packet", [Probe("fri", lambda: None, 10.0)])
    assert rec.action == "retry" and events == [] and clock.now() == 0.0


def test_skip_policy_waits_its_lost_target_wait_for_a_target_that_comes_back_by_itself():
    """The bundled plans say ``on_lost_target: skip`` with ``lost_target_wait_s: 5``: someone
    walking through a motion-capture bar's view for 2 s does not skip the configuration."""
    clock, events = ManualClock(), []

    class Mocap:
        name = "mocap"

        def read(self, timeout):
            seen = clock.now() >= 2.0
            return [MarkerSample("sir", np.zeros(3) if seen else np.full(3, np.nan), clock.now(), clock.now(),
                                 visible=seen)]

    def skipper(wait_s: float) -> LostTargetSuspender:
        return LostTargetSuspender("skip", wait_s=wait_s, predictor=None, clock=clock.now, sleep=clock.sleep,
                                   event=lambda kind, **f: events.append((kind, f)), settle_after_s=0.0)

    assert skipper(5.0).recover(Mocap(), "sir", "p1", np.zeros(7), "not visible").action == "resume"
    assert 2.0 <= clock.now() < 2.2
    clock.t = 0.0
    rec = skipper(1.0).recover(Mocap(), "sir", "p2", np.zeros(7), "not visible")
    assert rec.action == "skip" and "not back within 1 s" in rec.reason
    clock.t = 0.0
    assert skipper(0.0).recover(Mocap(), "sir", "p3", np.zeros(7), "not visible").action == "skip"
    assert clock.now() == 0.0  # lost_target_wait_s 0: skipped at once


# ------------------------------------------------------------------ the run's per-configuration logic
N = 7
LIMITS = JointLimits(lower_rad=np.full(N, -3.0), upper_rad=np.full(N, 3.0), max_velocity_rad_s=np.ones(N),
                     max_acceleration_rad_s2=np.ones(N))


class StubCommander:
    """A commander on simulated time whose drives are off from ``off[0]`` to ``off[1]`` s: moves
    are refused (NotReadyError) meanwhile, as the FRI commander refuses them."""

    name = "fri"
    limits = LIMITS

    def __init__(self, clock: ManualClock, off=(0.0, 0.0)) -> None:
        self.clock, self.off, self.q, self.moves = clock, off, np.zeros(N), []

    def _drives_off(self) -> bool:
        return self.off[0] <= self.clock.now() < self.off[1]

    def joint_state(self) -> JointState:
        return JointState(self.q.copy(), self.clock.now(), self.clock.now())

    def ready(self) -> JointState:
        if self._drives_off():
            raise NotReadyError("fri: drives not ACTIVE on axes [1, 2, 3, 4, 5, 6, 7]")
        return self.joint_state()

    def move_to(self, target, speed, timeout) -> None:
        if np.any(np.abs(target) > 3.0):
            raise LimitError("fri: target outside joint limits")
        self.ready()
        self.moves.append(self.clock.now())
        self.clock.sleep(1.0)
        self.q = np.asarray(target, float)

    def wait_settled(self, tolerance_rad, window_s, timeout) -> JointState:
        self.clock.sleep(window_s)
        return self.joint_state()

    def stop(self) -> None:
        pass


class StubSensor:
    """A marker sensor on simulated time that stalls (DeviceTimeoutError) from ``stall[0]`` to ``stall[1]`` s."""

    name = "mocap"

    def __init__(self, clock: ManualClock, stall=(0.0, 0.0)) -> None:
        self.clock, self.stall = clock, stall

    def read(self, timeout):
        if self.stall[0] <= self.clock.now() < self.stall[1]:
            self.clock.sleep(min(timeout, 0.5))
            raise DeviceTimeoutError("mocap: no frame")
        self.clock.sleep(0.01)
        t = self.clock.now()
        return [MarkerSample("sir", np.array([1.0, 2.0, 3.0]), t, t)]

    def measure(self, marker, n, timeout):
        self.read(timeout)
        return MarkerMeasurement(marker, np.array([1.0, 2.0, 3.0]), np.zeros(3), n, self.clock.now(), self.clock.now())


def runner(clock, commander, sensor, *, robot_wait=30.0, sensor_wait=30.0):
    events, records = [], []
    settings = SequencingSettings(speed=0.5, settle_window_s=0.1, settle_tolerance_rad=1e-3, sensor_stable_mm=0.05,
                                  samples=3, move_timeout_s=10.0, measure_timeout_s=5.0, retries=1,
                                  robot_fault_wait_s=robot_wait, sensor_fault_wait_s=sensor_wait)
    state = SimpleNamespace(aborting=threading.Event(), lock=threading.Lock(), skip_reasons={}, states=[])
    state.set = lambda s, reason="": state.states.append(s)
    pub = SimpleNamespace(event=lambda kind, **f: events.append((kind, f)), reading=None, sample=records.append,
                          runlog=None)
    lp = SimpleNamespace(plan=SimpleNamespace(sequencing=SimpleNamespace(on_lost_target="wait", lost_target_wait_s=5)))
    predictor = SimpleNamespace(add=lambda *a: None)
    r = ConfigurationRunner(lp, state, pub, commander, [SensorSpec(sensor, ["sir"])], settings, clock=clock.now,
                            sleep=clock.sleep, predictor=predictor)
    return r, events, records, state


def cfg(q=0.1, cid="p1"):
    return SimpleNamespace(config_id=cid, q_rad=np.full(N, q), pose="p", branch=0)


def test_drives_off_for_a_while_suspends_the_run_then_moves_again_once_they_are_back(caplog):
    clock = ManualClock()
    cmd = StubCommander(clock, off=(0.0, 3.0))
    r, events, records, state = runner(clock, cmd, StubSensor(clock))
    with caplog.at_level(logging.WARNING):
        assert r.measure(cfg()) == "measured"
    assert len(records) == 1 and cmd.moves and cmd.moves[0] >= 3.0  # moved only once the drives were back
    assert state.states == ["suspended", "running"]
    suspended = [f for k, f in events if k == "suspended"]
    assert len(suspended) == 1 and "drives not ACTIVE" in suspended[0]["reason"]
    lines = [r.getMessage() for r in caplog.records if "suspended at p1" in r.getMessage()]
    assert len(lines) == 1 and lines[0].endswith("— waiting up to 30 s for fri")
    assert lines[0].count("drives not ACTIVE") == 1  # the reason once


def test_a_sensor_stall_during_settling_is_waited_out_within_the_sensor_allowance():
    clock = ManualClock()
    r, events, records, _ = runner(clock, StubCommander(clock), StubSensor(clock, stall=(1.0, 4.0)))
    assert r.measure(cfg()) == "measured" and len(records) == 1
    (s,) = [f for k, f in events if k == "suspended"]
    assert s["device"] == "mocap" and s["reason"].startswith("settle: ")


def test_drives_off_longer_than_the_allowance_fails_only_that_configuration():
    clock = ManualClock()
    cmd = StubCommander(clock, off=(0.0, 8.0))
    r, events, records, _ = runner(clock, cmd, StubSensor(clock), robot_wait=5.0)
    assert r.measure(cfg(cid="p1")) == "failed"
    (failed,) = [f for k, f in events if k == "failed"]
    assert "allowed 5 s" in failed["reason"] and "drives not ACTIVE" in failed["reason"]
    assert cmd.moves == []  # nothing moved while the drives were off
    assert r.measure(cfg(0.2, cid="p2")) == "measured"  # the next one waits from its own first fault


def test_a_target_outside_the_limits_fails_at_once_without_a_wait():
    clock = ManualClock()
    r, events, _, state = runner(clock, StubCommander(clock), StubSensor(clock))
    assert r.measure(cfg(5.0)) == "failed"
    assert clock.now() == 0.0 and state.states == []
    (failed,) = [f for k, f in events if k == "failed"]
    assert failed["reason"].startswith("move refused: ")


@pytest.mark.parametrize("field", ["robot_fault_wait_s", "sensor_fault_wait_s"])
def test_a_plan_with_a_negative_fault_allowance_is_refused_naming_file_line_and_field(tmp_path, field):
    from acquire.plan.schema import ConfigError, load_plan

    from run_helpers import small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest

    plan = small_plan(tmp_path, sequencing={field: -1})
    with pytest.raises(ConfigError) as err:
        load_plan(plan)
    text = str(err.value)
    assert f"sequencing.{field}" in text and "plan.yaml:" in text and "greater than or equal to 0" in text


class FlakyCommander(StubCommander):
    """Its first ``n_bad`` moves end with the controller silent for a moment (over before anyone
    looks: ``ready()`` passes at once), as a starved controller on a loaded host does."""

    def __init__(self, clock: ManualClock, n_bad: int) -> None:
        super().__init__(clock)
        self.n_bad, self.tries = n_bad, 0

    def move_to(self, target, speed, timeout) -> None:
        self.tries += 1
        if self.tries <= self.n_bad:
            self.clock.sleep(1.0)
            raise DeviceTimeoutError("fri: controller stopped sending: no monitoring message for 914 ms")
        super().move_to(target, speed, timeout)


def test_faults_that_pass_at_once_are_retried_within_the_allowance_then_fail_the_configuration():
    clock = ManualClock()
    cmd = FlakyCommander(clock, n_bad=4)  # more than retries (1), within the allowance (10 s)
    r, events, records, state = runner(clock, cmd, StubSensor(clock), robot_wait=10.0, sensor_wait=5.0)
    assert r.measure(cfg()) == "measured" and len(records) == 1
    assert [k for k, _ in events].count("retry") == 4 and state.states == []  # nothing to wait for: no suspension
    clock.t = 0.0
    cmd = FlakyCommander(clock, n_bad=1000)
    r, events, _, _ = runner(clock, cmd, StubSensor(clock), robot_wait=10.0, sensor_wait=5.0)
    assert r.measure(cfg()) == "failed"
    (failed,) = [f for k, f in events if k == "failed"]
    assert re.match(r"move failed 1[01] times in 10\.\d s: fri: controller stopped sending", failed["reason"])
    assert 10.0 <= clock.now() < 12.5  # the first fault came 1 s in; retried for the 10 s allowance


def test_the_run_controller_logs_a_foreseen_failure_for_the_console_to_show_in_one_line(tmp_path, caplog):
    from acquire.plan.schema import load_plan
    from acquire.run import RunController
    from acquire.run.summary import RunError

    from run_helpers import small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest

    rc = RunController(load_plan(small_plan(tmp_path)), fit=False)

    def three_in_a_row():
        raise RunError("3 configurations failed in a row (last: move refused); the cell is not usable")

    rc._run = three_in_a_row
    with caplog.at_level(logging.ERROR, logger="acquire.run"):
        rc.start()
        summary = rc.wait(30)
    assert summary.state == "failed" and "3 configurations failed in a row" in summary.reason
    (rec,) = [r for r in caplog.records if r.name == "acquire.run" and r.levelno == logging.ERROR]
    assert rec.getMessage().startswith("run ") and "failed: 3 configurations failed in a row" in rec.getMessage()
    assert rec.exc_info is not None and getattr(rec, "foreseen", False)  # traceback for the text log only


def test_an_abort_during_the_wait_ends_it_at_once():
    clock, events = ManualClock(), []
    aborting = []
    sus = DeviceFaultSuspender(clock=clock.now, sleep=lambda dt: (clock.sleep(dt), aborting.append(clock.now() > 1.0)),
                               event=lambda kind, **f: events.append(kind), stopping=lambda: any(aborting))
    rec = sus.recover("p1", "drives off", [Probe("fri", down_until(clock, 100.0), 30.0)])
    assert rec.action == "abort" and 1.0 < clock.now() < 1.2
