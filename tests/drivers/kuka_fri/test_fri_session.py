"""The client's cyclic core, fed message by message (no sockets): what it answers in each
session state, what it refuses, and — as a property over random targets, limits, multipliers,
lost messages and stops — that no command it sends exceeds position, speed or acceleration
limits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fri_helpers import assert_commands_within_limits, iiwa14_limits
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.errors import DeviceFaultError, DeviceTimeoutError, LimitError, NotReadyError
from drivers.kuka_fri.messages import (
    COMMAND_MESSAGE_ID,
    MONITORING_MESSAGE_ID,
    ConnectionInfo,
    ConnectionQuality,
    DriveState,
    FRIMonitoringMessage,
    IpoData,
    MessageHeader,
    MonitorData,
    RobotInfo,
    SafetyState,
    SessionState,
    decode_command,
    decode_monitoring,
    encode_command,
)
from drivers.kuka_fri.session import FriClientSession, MotionStoppedError
from drivers.protocols import JointLimits


class Controller:
    """Builds the monitoring messages a controller would send; ``measured`` follows the last
    command exactly (an ideal servo) unless a test sets it."""

    def __init__(self, q0, period_ms=5, multiplier=1, state=SessionState.COMMANDING_ACTIVE):
        self.seq = 0
        self.state = state
        self.period_ms = period_ms
        self.multiplier = multiplier
        self.measured = np.asarray(q0, dtype=float)
        self.commanded = self.measured.copy()
        self.ipo = self.measured.copy()
        self.drives = DriveState.ACTIVE
        self.safety = SafetyState.NORMAL_OPERATION
        self.n = 7
        self.t = 0.0

    def message(self) -> FRIMonitoringMessage:
        msg = FRIMonitoringMessage(
            MessageHeader(MONITORING_MESSAGE_ID, self.seq, 0),
            RobotInfo(self.n, self.safety, (self.drives,) * self.n),
            MonitorData(tuple(self.measured[: self.n]), None, tuple(self.commanded[: self.n])),
            ConnectionInfo(self.state, ConnectionQuality.EXCELLENT, self.period_ms, self.multiplier),
            IpoData(tuple(self.ipo[: self.n])),
        )
        self.seq += 1
        self.t += self.period_ms / 1000
        return msg

    def exchange(self, session: FriClientSession, lose: bool = False):
        """One cycle through the real codec; returns the decoded answer (or None)."""
        msg = self.message()
        if lose:
            return None
        answer = session.on_monitoring(decode_monitoring(msg.encode()), self.t)
        if answer is None:
            return None
        decoded = decode_command(encode_command(answer))
        if self.state == SessionState.COMMANDING_ACTIVE:
            self.commanded = np.asarray(decoded.command_data.joint_position)
            self.measured = self.commanded.copy()
        return decoded


@pytest.fixture
def session(limits) -> FriClientSession:
    return FriClientSession(limits)


Q0 = np.radians([10.0, -20.0, 5.0, 40.0, 0.0, 30.0, -15.0])


def test_idle_gets_no_answer_and_monitoring_echoes_the_commanded_position(session):
    ctl = Controller(Q0, state=SessionState.IDLE)
    assert ctl.exchange(session) is None
    ctl.state = SessionState.MONITORING_WAIT
    ctl.commanded = Q0 + 0.01
    ans = ctl.exchange(session)
    assert ans.header.message_identifier == COMMAND_MESSAGE_ID
    assert ans.header.reflected_sequence_counter == 1
    np.testing.assert_array_equal(ans.command_data.joint_position, Q0 + 0.01)
    ctl.state = SessionState.COMMANDING_WAIT
    ctl.ipo = Q0 + 0.02
    np.testing.assert_array_equal(ctl.exchange(session).command_data.joint_position, Q0 + 0.02)


def test_commanding_starts_from_the_measured_position_and_counters_advance(session):
    ctl = Controller(Q0, multiplier=1)
    ctl.commanded = Q0 + 0.005  # the controller's set-point lags: we still start from measured
    answers = [ctl.exchange(session) for _ in range(3)]
    np.testing.assert_array_equal(answers[0].command_data.joint_position, Q0)
    assert [a.header.sequence_counter for a in answers] == [0, 1, 2]
    assert [a.header.reflected_sequence_counter for a in answers] == [0, 1, 2]


def test_every_receive_multiplier_th_message_is_answered(session):
    ctl = Controller(Q0, multiplier=3, state=SessionState.MONITORING_READY)
    got = [ctl.exchange(session) for _ in range(9)]
    assert [a is not None for a in got] == [False, False, True] * 3
    assert [a.header.reflected_sequence_counter for a in got if a] == [2, 5, 8]


def _active(session, ctl, cycles=2):
    for _ in range(cycles):
        ctl.exchange(session)


@pytest.mark.parametrize(
    "breaker, message, passes",
    [
        (lambda c: setattr(c, "state", SessionState.MONITORING_READY), "session is MONITORING_READY", True),
        (lambda c: setattr(c, "drives", DriveState.OFF), "drives not ACTIVE", True),
        (lambda c: setattr(c, "safety", SafetyState.SAFETY_STOP_LEVEL_1), "SAFETY_STOP_LEVEL_1", True),
        (lambda c: setattr(c, "n", 6), "reports 6 joints", False),
    ],
)
def test_moves_are_refused_before_anything_moves(session, breaker, message, passes):
    """A refusal for a state that may clear by itself (the drives come back, the application
    restarts its overlay) is a NotReadyError, which a run waits out; a wrong robot is not."""
    ctl = Controller(Q0)
    _active(session, ctl)
    breaker(ctl)
    ctl.message()  # the bad message
    session.on_monitoring(decode_monitoring(ctl.message().encode()), ctl.t)
    with pytest.raises(LimitError, match=message) as refused:
        session.begin_move(Q0 + 0.1, 1.0, "fri")
    assert isinstance(refused.value, NotReadyError) == passes
    assert not session.motion_active()


def test_a_move_while_the_last_one_is_still_ending_is_refused_as_not_ready(session):
    """Seen with the cell's allowances at 1500 ms on a busy host: a move that timed out while the
    controller was silent was still ending when the next one came; its refusal ("a move is
    already in progress") failed three configurations in a row. It is NotReadyError now: the run
    waits for the last move to end, then moves."""
    ctl = Controller(Q0)
    _active(session, ctl)
    session.begin_move(Q0 + 0.1, 0.5, "fri")
    with pytest.raises(NotReadyError, match="a move is already in progress"):
        session.begin_move(Q0 + 0.2, 0.5, "fri")


def test_a_move_is_refused_when_the_robot_is_far_from_the_held_command(session):
    ctl = Controller(Q0)
    _active(session, ctl)
    ctl.measured = Q0 + math.radians(3.0)
    session.on_monitoring(ctl.message(), ctl.t)
    with pytest.raises(LimitError, match="measured position is 3.000° from the commanded one"):
        session.begin_move(Q0 + 0.1, 1.0, "fri")


def test_a_move_reaches_its_target_and_then_holds(session, limits):
    ctl = Controller(Q0)
    _active(session, ctl)
    target = Q0 + np.radians([20, -10, 5, 0, 30, -5, 60])
    motion = session.begin_move(target, 0.5, "fri")
    sent = []
    while not motion.done.is_set():
        sent.append(ctl.exchange(session).command_data.joint_position)
        assert len(sent) < 5000
    assert motion.error is None
    np.testing.assert_allclose(sent[-1], target, atol=1e-12)
    assert len(sent) == math.ceil(motion.trajectory.duration / 0.005)
    for _ in range(3):
        np.testing.assert_array_equal(ctl.exchange(session).command_data.joint_position, target)
    assert_commands_within_limits([Q0] + sent, limits, 0.005, speed=0.5)


@pytest.mark.parametrize(
    "fault, error, message",
    [
        (lambda c: setattr(c, "state", SessionState.MONITORING_WAIT), DeviceFaultError, "left COMMANDING_ACTIVE"),
        (lambda c: setattr(c, "drives", DriveState.TRANSITIONING), DeviceFaultError, "TRANSITIONING"),
        (lambda c: setattr(c, "safety", SafetyState.SAFETY_STOP_LEVEL_0), DeviceFaultError, "SAFETY_STOP_LEVEL_0"),
        (lambda c: setattr(c, "seq", 0), DeviceFaultError, "controller restarted"),
    ],
)
def test_a_fault_mid_motion_ends_it_with_a_clear_error(session, fault, error, message):
    ctl = Controller(Q0)
    _active(session, ctl)
    motion = session.begin_move(Q0 + 0.5, 1.0, "fri")
    _active(session, ctl, 20)
    fault(ctl)
    ctl.exchange(session)
    assert motion.done.is_set()
    assert isinstance(motion.error, error)
    assert message in str(motion.error)
    assert not session.motion_active()


def test_silence_mid_motion_is_a_timeout(session):
    ctl = Controller(Q0)
    _active(session, ctl)
    motion = session.begin_move(Q0 + 0.5, 1.0, "fri")
    _active(session, ctl, 5)
    session.check_silence(ctl.t + 0.05, 0.1)
    assert not motion.done.is_set()
    session.check_silence(ctl.t + 0.15, 0.1)
    assert isinstance(motion.error, DeviceTimeoutError)
    assert "no monitoring message for 150 ms" in str(motion.error)


def test_stop_decelerates_within_limits_and_short_of_the_target(session, limits):
    ctl = Controller(Q0)
    _active(session, ctl)
    target = Q0 + np.radians([60, 40, -50, 30, 90, -60, 120])
    motion = session.begin_move(target, 1.0, "fri")
    sent = [Q0]
    for _ in range(60):
        sent.append(ctl.exchange(session).command_data.joint_position)
    session.request_stop()
    while not motion.done.is_set():
        sent.append(ctl.exchange(session).command_data.joint_position)
    assert isinstance(motion.error, MotionStoppedError)
    q = np.asarray(sent)
    assert np.all(np.abs(q[-1] - target) > np.radians(1))
    assert_commands_within_limits(q, limits, 0.005)
    for _ in range(2):  # then it holds where it stopped
        np.testing.assert_array_equal(ctl.exchange(session).command_data.joint_position, q[-1])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    v_scale=st.floats(0.5, 1.5),
    accel_factor=st.floats(2.0, 10.0),
    speed=st.floats(0.3, 1.0),
    period_ms=st.sampled_from([2, 4, 5, 10]),
    multiplier=st.integers(1, 3),
    loss=st.floats(0.0, 0.2),
    stop_at=st.none() | st.integers(1, 400),
)
def test_no_sent_command_exceeds_the_limits(seed, v_scale, accel_factor, speed, period_ms, multiplier, loss, stop_at):
    """Random starts, targets and limits, lost monitoring messages (the jitter a UDP link adds: the
    answer phase shifts, some cycles are skipped), an optional stop: every command the client
    sends, decoded from its bytes, stays within position, speed and acceleration limits."""
    rng = np.random.default_rng(seed)
    base = iiwa14_limits(accel_factor)
    limits = JointLimits(base.lower_rad, base.upper_rad, base.max_velocity_rad_s * v_scale,
                         base.max_acceleration_rad_s2 * v_scale)
    session = FriClientSession(limits)
    margin = math.radians(0.5)
    lo, hi = limits.lower_rad + margin, limits.upper_rad - margin
    q0 = rng.uniform(lo, hi)
    ctl = Controller(q0, period_ms=period_ms, multiplier=multiplier)
    sent = []
    while not sent:
        ans = ctl.exchange(session)
        if ans:
            sent.append(np.asarray(ans.command_data.joint_position))
    for _ in range(2):  # moves of up to ±15° per axis, kept inside the limits
        target = np.clip(sent[-1] + rng.uniform(-1, 1, 7) * math.radians(15), lo, hi)
        motion = session.begin_move(target, speed, "fri")
        cycles = 0
        while not motion.done.is_set():
            ans = ctl.exchange(session, lose=rng.random() < loss)
            if ans is not None:
                sent.append(np.asarray(ans.command_data.joint_position))
                cycles += 1
                if stop_at is not None and cycles == stop_at:
                    session.request_stop()
            assert cycles < 200_000
        if stop_at is None:
            np.testing.assert_allclose(sent[-1], target, atol=1e-9)
    dt = period_ms * multiplier / 1000
    assert_commands_within_limits(sent, limits, dt, speed=speed, rtol=1e-6)
    assert session.counters.step_clamps == 0
