"""The fake Sunrise's answer handling without UDP: ``AnswerHandler`` on a ``SunriseSession``.

Answers are built with the protobuf runtime from the SDK's field tables (``fri_proto``), not
with our encoder.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from fri_helpers import iiwa14_limits
from fri_proto import messages

from drivers.kuka_fri.fake import FakeSunriseStats
from drivers.kuka_fri.fake_answers import AnswerHandler
from drivers.kuka_fri.fake_servo import JointServo
from drivers.kuka_fri.fake_session import SunriseSession
from drivers.kuka_fri.fake_windows import AnswerWindows
from drivers.kuka_fri.messages import SessionState

PERIOD_S = 0.005
Q0 = np.array([0.1, 0.2, -0.1, -1.2, 0.0, 0.6, 0.3])


def _active(record_commands: bool = True) -> tuple[SunriseSession, AnswerHandler]:
    """A session in COMMANDING_ACTIVE with message 4 sent and its window open; its lock is held
    for the rest of the test, as the fake holds it around every call."""
    windows = AnswerWindows(1, 50)
    lock = threading.Lock()
    lock.acquire()
    session = SunriseSession(JointServo(Q0, 6.0, 0.7), windows, FakeSunriseStats(), lock,
                             auto_open=False, idle_cycles=0, closing_idle_messages=5, ready_after=10,
                             commanding_wait_cycles=10, max_missed=20, abort_on_violation=True,
                             application=False, application_start_cycles=20)
    session.open()
    session.set_state(SessionState.COMMANDING_WAIT, "test")  # the overlay holds Q0
    session.set_state(SessionState.COMMANDING_ACTIVE, "test")
    session.seq = 5
    windows.open(4)
    handler = AnswerHandler(session, fri_version="1.15", limits=iiwa14_limits(), receive_period_s=PERIOD_S,
                            start_tolerance_rad=1e-3, echo_tolerance_rad=1e-6, speed_tolerance=1e-6,
                            loss_in=0.0, record_commands=record_commands, rng=np.random.default_rng(0))
    return session, handler


def _answer(reflected: int, q) -> bytes:
    _, command = messages("1.15")
    m = command()
    m.header.messageIdentifier = 0x34001
    m.header.sequenceCounter = 7
    m.header.reflectedSequenceCounter = reflected
    m.commandData.jointPosition.value.extend(list(q))
    return m.SerializeToString()


@pytest.mark.parametrize("record", [True, False])
def test_a_set_point_within_the_speed_limit_is_applied_and_recorded_when_asked(record):
    session, handler = _active(record)
    q = Q0 + 1e-4
    handler.handle(_answer(4, q))
    np.testing.assert_allclose(session.servo.setpoint, q)
    assert session.client_seq == 7 and session.state == SessionState.COMMANDING_ACTIVE
    assert len(session.stats.commands) == (1 if record else 0) and session.stats.violations == []


def test_a_set_point_faster_than_the_limits_ends_the_motion_and_is_not_taken():
    session, handler = _active()
    handler.handle(_answer(4, Q0 + 1e-4))  # the first, at the interpolator's position
    handler.handle(_answer(4, Q0))  # a second answer in the same window: ignored
    session.close_window()  # the window of message 4 ends answered; message 5 opens the next
    session.windows.open(5)
    session.seq = 6
    jump = Q0 + 1e-4 + np.array([0, 0, 0, 0, 0, 0, 0.5])  # 0.5 rad in 5 ms on A7
    handler.handle(_answer(5, jump))
    np.testing.assert_allclose(session.servo.setpoint, Q0 + 1e-4)
    assert session.state == SessionState.MONITORING_READY
    assert "A7" in session.stats.violations[-1]


def test_answers_that_reflect_an_unsent_or_an_old_message_are_counted_not_applied():
    session, handler = _active()
    handler.handle(_answer(9, Q0))  # never sent
    handler.handle(_answer(2, Q0))  # before the window
    assert (session.stats.bad_reflections, session.stats.late_answers) == (1, 1)
    np.testing.assert_allclose(session.servo.setpoint, Q0)
    handler.handle(b"\x00\x01garbage")
    assert session.stats.malformed_answers == 1
