"""``AnswerHandler``: what the fake Sunrise does with each answer (``FRICommandMessage``) it gets.

In order: an answer may be lost (``loss_in``); its framing must match the FRI version (2.7
frames every datagram, 1.x/2.5 none) and it must decode, else it is counted malformed. In IDLE an
answer to a message of this IDLE spell is a violation, an older one is late. Otherwise its
reflected counter must have been sent (else a bad reflection) and belong to the current answer
window (else late); only the first answer of a window counts. In COMMANDING_WAIT it must echo
the interpolator's position (7 joints, within ``echo_tolerance_rad``); in COMMANDING_ACTIVE its
joint positions are the set-point, taken only when the drives are powered, the first within
``start_tolerance_rad`` of the interpolator's position, each within the limits' speed over the
windows since the last one taken (``fake_servo.set_point_violation``).
"""

from __future__ import annotations

import logging
from typing import Optional

import numpy as np

from drivers.errors import ProtocolError
from drivers.kuka_fri.fake_servo import N_JOINTS, set_point_violation
from drivers.kuka_fri.fake_session import SunriseSession
from drivers.kuka_fri.framing import unframe
from drivers.kuka_fri.messages import SessionState, decode_command
from drivers.protocols import JointLimits

log = logging.getLogger("remaster.fake.sunrise")


class AnswerHandler:
    """Checks and applies the client's answers to ``session`` (lock held by the caller).

    receive_period_s: the time one answer window spans (s); record_commands: keep every applied
    set-point in ``stats.commands``; rng: draws the answer losses; other options as
    ``FakeSunrise``'s of the same names.
    """

    def __init__(self, session: SunriseSession, *, fri_version: str, limits: Optional[JointLimits],
                 receive_period_s: float, start_tolerance_rad: float, echo_tolerance_rad: float,
                 speed_tolerance: float, loss_in: float, record_commands: bool, rng: np.random.Generator) -> None:
        self.session = session
        self.fri_version = fri_version
        self.limits = limits
        self.receive_period_s = receive_period_s
        self.start_tolerance_rad = start_tolerance_rad
        self.echo_tolerance_rad = echo_tolerance_rad
        self.speed_tolerance = speed_tolerance
        self.loss_in = loss_in
        self.record_commands = record_commands
        self.rng = rng

    def handle(self, data: bytes) -> None:
        """One datagram from the client (see the module docstring)."""
        s = self.session
        stats, windows = s.stats, s.windows
        if self.rng.random() < self.loss_in:
            return
        try:
            body, framed = unframe(data)
            if framed != (self.fri_version == "2.7"):
                raise ProtocolError(
                    "a 2.7-framed answer to an FRI {0} controller, which sends and reads bare messages".format(
                        self.fri_version) if framed else
                    "a bare answer to an FRI 2.7 controller: SDK 2.7 frames every datagram (length, message, CRC-32)")
            msg = decode_command(body)
        except ProtocolError as exc:
            stats.malformed_answers += 1
            log.warning("fake Sunrise: malformed answer (%d bytes): %s", len(data), exc)
            return
        stats.answers += 1
        r = msg.header.reflected_sequence_counter
        if s.state == SessionState.IDLE:
            if s.idle_first_seq <= r < s.seq:
                stats.answers_in_idle += 1
                stats.violations.append("client answered while the session is IDLE")
            else:  # in flight when the session went IDLE (or the controller restarted)
                stats.late_answers += 1
            return
        last_sent = s.seq - 1
        if r > last_sent:
            stats.bad_reflections += 1
            log.warning("fake Sunrise: answer reflects %d, never sent (last %d)", r, last_sent)
            return
        if r < windows.first_seq:
            stats.late_answers += 1
            return
        if windows.answered:
            return  # a second answer in one window: nothing more to apply
        windows.answered = True
        s.client_seq = msg.header.sequence_counter
        jp = None if msg.command_data is None else msg.command_data.joint_position
        if s.state == SessionState.COMMANDING_WAIT:
            if jp is None or len(jp) != N_JOINTS:
                stats.violations.append("COMMANDING_WAIT answer without 7 joint positions")
                windows.consecutive_good = -1
            elif np.max(np.abs(np.asarray(jp) - s.ipo)) > self.echo_tolerance_rad:
                stats.violations.append("COMMANDING_WAIT answer does not echo the ipo position")
                windows.consecutive_good = -1
        elif s.state == SessionState.COMMANDING_ACTIVE:
            self._apply_command(jp)

    def _apply_command(self, jp) -> None:
        s = self.session
        if jp is None or len(jp) != N_JOINTS:
            s.violation(f"command without {N_JOINTS} joint positions ({'none' if jp is None else len(jp)})")
            return
        if not s.powered():
            return  # brakes hold; the set-point is not taken
        cmd = np.asarray(jp, dtype=float)
        if s.first_active_command and np.all(np.isfinite(cmd)):
            s.first_active_command = False
            # The overlay starts at zero: the first set-point is the interpolator's position.
            # Not the measured one: a hand on the arm, or a servo still following it, is not the
            # client's to command away (it would be a jump when the hand lets go).
            jump = np.max(np.abs(cmd - s.ipo))
            if jump > self.start_tolerance_rad:
                s.violation(
                    f"first command is {jump:.4g} rad from the interpolator's position "
                    f"(allowed {self.start_tolerance_rad:.3g})"
                )
                return
        # The client advances one step per answer; a window whose answer was lost or late
        # leaves the robot a step behind, so the speed is judged over the windows since the
        # last set-point we took.
        dt = self.receive_period_s * s.windows.since_applied
        why = set_point_violation(cmd, s.servo.setpoint, dt, self.limits, self.speed_tolerance)
        if why is not None:
            s.violation(why)
            return
        s.servo.setpoint = cmd
        s.windows.since_applied = 0
        if self.record_commands:
            s.stats.commands.append((s.sim_time, cmd.copy()))
