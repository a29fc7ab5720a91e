"""``SunriseSession``: the fake Sunrise's FRI session state machine (see ``fake`` for the diagram).

It holds what the controller knows of the session: the state and how long it has been in it,
the message counters (ours and the client's last), the IDLE messages still to send after a
close, the interpolator's position (``ipo``, fixed when the overlay motion starts), drive and
safety states, and the controller clock (``sim_time``, s). Every method is called with the
fake's lock held; ``changed`` (a condition on that lock) is notified on every state change and
when the last closing IDLE message is sent.
"""

from __future__ import annotations

import logging
import threading

from drivers.kuka_fri.fake_servo import JointServo
from drivers.kuka_fri.fake_windows import AnswerWindows
from drivers.kuka_fri.messages import ConnectionQuality, DriveState, SafetyState, SessionState

log = logging.getLogger("remaster.fake.sunrise")


class SunriseSession:
    """The session of one fake controller (options as ``FakeSunrise``'s of the same names).

    servo: the joints (its set-point is held on IDLE, its position starts the overlay);
    windows: the answer-window record (streaks reset on every state change); stats: the fake's
    ``FakeSunriseStats`` (drops and violations are counted there); lock: the fake's lock.
    """

    def __init__(self, servo: JointServo, windows: AnswerWindows, stats, lock: threading.Lock, *,
                 auto_open: bool, idle_cycles: int, closing_idle_messages: int, ready_after: int,
                 commanding_wait_cycles: int, max_missed: int, abort_on_violation: bool, application: bool,
                 application_start_cycles: int) -> None:
        self.servo = servo
        self.windows = windows
        self.stats = stats
        self.changed = threading.Condition(lock)
        self.auto_open = auto_open
        self.idle_cycles = idle_cycles
        self.closing_idle_messages = closing_idle_messages
        self.ready_after = ready_after
        self.commanding_wait_cycles = commanding_wait_cycles
        self.max_missed = max_missed
        self.abort_on_violation = abort_on_violation
        self.application = application
        self.application_start_cycles = application_start_cycles
        self.state = SessionState.IDLE
        self.ipo = servo.q.copy()  # the interpolator's position: the application's motion, rad
        self.seq = 0  # our counter, next message
        self.client_seq = 0  # last counter the client sent
        self.cycles_in_state = 0
        self.idle_first_seq = 0  # first counter sent since the session went IDLE
        self.idle_to_send = 0  # IDLE messages still to send after the session was closed
        self.ended = False  # the robot application ended (stop, max_runtime_s): no re-opening
        self.first_active_command = True
        self.safety = SafetyState.NORMAL_OPERATION
        self.drives = DriveState.ACTIVE
        self.sim_time = 0.0  # controller clock, s

    def set_state(self, new: SessionState, why: str) -> None:
        if new != self.state:
            log.info("fake Sunrise: %s -> %s (%s)", self.state.name, new.name, why)
            self.state = new
            self.cycles_in_state = 0
            self.windows.consecutive_good = 0
            if new == SessionState.COMMANDING_WAIT:
                self.ipo = self.servo.setpoint.copy()  # the overlay motion holds where the robot is
            if new == SessionState.COMMANDING_ACTIVE:
                self.first_active_command = True
                self.windows.since_applied = 1
            if new == SessionState.IDLE:
                self.servo.hold_here()
                self.idle_first_seq = self.seq
            self.changed.notify_all()

    def open(self, why: str = "session opened") -> None:
        """IDLE → MONITORING_WAIT (no more closing IDLE messages)."""
        if self.state == SessionState.IDLE:
            self.idle_to_send = 0
            self.set_state(SessionState.MONITORING_WAIT, why)

    def close(self, why: str) -> None:
        """→ IDLE, with ``closing_idle_messages`` IDLE messages to send."""
        if self.state != SessionState.IDLE:
            self.set_state(SessionState.IDLE, why)
            self.idle_to_send = self.closing_idle_messages

    def drop(self, why: str) -> None:
        """A session drop: back to MONITORING_WAIT (counted)."""
        if self.state != SessionState.IDLE:
            self.stats.session_drops += 1
            self.set_state(SessionState.MONITORING_WAIT, why)

    def restart(self) -> None:
        """Controller restart: counters back at zero, IDLE without IDLE messages."""
        self.seq = 0
        self.client_seq = 0
        self.windows.forget()
        self.set_state(SessionState.IDLE, "controller restart")
        self.idle_to_send = 0

    def commanding(self) -> bool:
        return self.state in (SessionState.COMMANDING_WAIT, SessionState.COMMANDING_ACTIVE)

    def violation(self, text: str) -> None:
        """Record what the client did wrong; with ``abort_on_violation`` the motion ends."""
        log.warning("fake Sunrise: %s", text)
        self.stats.violations.append(text)
        if self.abort_on_violation and self.commanding():
            self.set_state(SessionState.MONITORING_READY, f"motion aborted: {text}")

    def powered(self) -> bool:
        return self.drives == DriveState.ACTIVE and self.safety == SafetyState.NORMAL_OPERATION

    def close_window(self) -> None:
        """End of a receive window: score it, walk the state machine."""
        w = self.windows
        if self.state == SessionState.IDLE:
            w.skip()
            return
        if w.close():
            self.stats.missed_windows += 1
        if w.consecutive_missed >= self.max_missed and self.state != SessionState.MONITORING_WAIT:
            self.drop(f"{w.consecutive_missed} answer windows missed in a row")
            return
        good = w.quality() >= ConnectionQuality.GOOD
        if self.state == SessionState.MONITORING_WAIT and good and w.consecutive_good >= self.ready_after:
            self.set_state(SessionState.MONITORING_READY, "connection quality good")
        elif (
            self.state == SessionState.COMMANDING_WAIT
            and good
            and w.consecutive_good >= self.commanding_wait_cycles
        ):
            self.set_state(SessionState.COMMANDING_ACTIVE, "client echoes the ipo position")

    def tick(self) -> None:
        """One controller cycle in the state: the session opens by itself (``auto_open``) and the
        robot application starts its overlay motion (``application``) when their time comes."""
        self.cycles_in_state += 1
        if (self.state == SessionState.IDLE and self.auto_open and not self.ended and not self.idle_to_send
                and self.cycles_in_state > self.idle_cycles):
            self.set_state(SessionState.MONITORING_WAIT, "session opened")
        if (self.application and self.state == SessionState.MONITORING_READY
                and self.cycles_in_state > self.application_start_cycles
                and self.powered()):
            self.set_state(SessionState.COMMANDING_WAIT, "robot application started its FRI overlay motion")

    def idle_message_due(self) -> bool:
        """In IDLE: whether a closing IDLE message is still to be sent (counted off here)."""
        if not self.idle_to_send:
            return False
        self.idle_to_send -= 1
        if not self.idle_to_send:
            self.changed.notify_all()
        return True

    def next_seq(self) -> None:
        self.seq = (self.seq + 1) & 0xFFFF_FFFF


__all__ = ["SunriseSession"]
