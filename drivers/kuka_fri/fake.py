"""``FakeSunrise``: a Sunrise controller's FRI side, over real UDP on 127.0.0.1.

It is the sender, as the real controller is: every ``send_period_ms`` (simulated time when a
``SimClock`` is given) it sends an ``FRIMonitoringMessage`` to the client address and collects
the ``FRICommandMessage`` answers that arrive before the next one. It walks the session state
machine, runs the commanded positions through a second-order servo, checks the client's
counters, timing, echo and step sizes, and exposes fault hooks for the failure paths:
``drop_next``, ``send_malformed`` (garbage, truncated, wrong_id, bad_crc), ``restart``,
``stop_sending`` / ``resume_sending``, ``drives_off``, ``drop_session``, ``hold_brakes``,
``inject_fault`` / ``clear_fault``; the robot application's own steps: ``open_session``,
``close_session``, ``start_commanding``, ``stop_commanding``, ``stop``.

Message layouts (``fri_version``: ``"1.15"``, ``"2.5"``, ``"2.7"``) are built in
``fake_monitoring``; in 2.7 every datagram, both ways, is framed with a length and a CRC-32
(``framing``), and an answer in the other framing is malformed, as it is to the SDK. The joints
are ``fake_servo.JointServo``; answer windows and quality are scored by
``fake_windows.AnswerWindows``; the session state machine below is ``fake_session.SunriseSession``
and what the controller does with each answer ``fake_answers.AnswerHandler``; the sending thread
is ``fake_sender.SendLoop``. This class holds the options, the cycle (servo, windows, the
message built) and the hooks tests pull.

Like a cabinet: nothing is sent until the robot application opens the FRI session (the first
message already says MONITORING_WAIT; an SDK example reading IDLE would quit); when the
application closes it (``close_session``, ``stop`` — Ctrl-C or the end of ``acquire sim`` —,
``max_runtime_s``) the controller sends ``closing_idle_messages`` IDLE messages, so a client
that blocks on receive (the SDK examples) sees IDLE and leaves; a ``restart`` goes silent.
Messages leave from the FRI port (the client's port, on ``controller_host``): the 1.15 SDK
example given a controller host ``connect()``s to host:port and takes nothing else. The
monitoring time stamp is the controller's clock: time of day, seconds and nanoseconds.

``ipoData.jointPosition`` is the interpolator's position, as the SDK documents it: the robot
application's motion (a position hold) under the FRI joint overlay, fixed when the overlay
motion starts. A client's command is the absolute joint set-point (ipo position + overlay);
FRI 1.x reports the last one applied as ``commandedJointPosition``.

``application=True`` runs the robot application the controller-side program we ship does
(``drivers/kuka_fri/controller/``): it opens the session, and whenever the session has been
MONITORING_READY for ``application_start_cycles`` messages it starts the overlay motion, again
after a drop. Any FRI client (ours, KUKA's SDK examples) can then be tried without code.

Session state machine (see ``PROTOCOL.md``)::

    IDLE (silent) --(open_session / auto after idle_cycles)--> MONITORING_WAIT
    MONITORING_WAIT --(ready_after consecutive answered windows, quality >= GOOD)--> MONITORING_READY
    MONITORING_READY --(start_commanding(): the robot application's FRI overlay motion)--> COMMANDING_WAIT
    COMMANDING_WAIT --(commanding_wait_cycles answers echoing the ipo position)--> COMMANDING_ACTIVE
    MONITORING_READY --(application mode: after application_start_cycles)--> COMMANDING_WAIT
    COMMANDING_* --(stop_commanding / violation / fault)--> MONITORING_READY
    any non-IDLE --(max_missed consecutive unanswered windows)--> MONITORING_WAIT
    any --(close_session / stop: closing_idle_messages IDLE messages; restart: silent)--> IDLE

Answer windows, late answers and connection quality: see ``fake_windows``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from drivers.kuka_fri.fake_answers import AnswerHandler
from drivers.kuka_fri.fake_monitoring import (
    MALFORMED_KINDS,
    ControllerView,
    malformed_datagram,
    monitoring_datagram,
    nominal_flange_pose,
)
from drivers.kuka_fri.fake_port import FriPort
from drivers.kuka_fri.fake_sender import SendLoop
from drivers.kuka_fri.fake_servo import N_JOINTS, JointServo
from drivers.kuka_fri.fake_session import SunriseSession
from drivers.kuka_fri.fake_windows import AnswerWindows
from drivers.kuka_fri.messages import ConnectionQuality, DriveState, SafetyState, SessionState
from drivers.protocols import JointLimits

log = logging.getLogger("remaster.fake.sunrise")

__all__ = ["FRI_VERSIONS", "MALFORMED_KINDS", "FakeSunrise", "FakeSunriseStats", "nominal_flange_pose"]

_LOOPBACK = {"127.0.0.1", "localhost", "::1"}
FRI_VERSIONS = ("1.15", "2.5", "2.7")


@dataclass
class FakeSunriseStats:
    """What the fake saw of the client. ``commands``: (controller time s, shape (7,) rad) of
    every set-point the fake applied in COMMANDING_ACTIVE, in order."""

    sent: int = 0
    answers: int = 0
    late_answers: int = 0
    missed_windows: int = 0
    bad_reflections: int = 0
    malformed_answers: int = 0
    answers_in_idle: int = 0
    session_drops: int = 0
    violations: list[str] = field(default_factory=list)
    commands: list[tuple[float, np.ndarray]] = field(default_factory=list)


class FakeSunrise:
    """A fake Sunrise FRI controller.

    client_address: (host, port) of the FRI client, loopback only.
    controller_host: loopback address the fake sends from, on the client's port (the FRI port,
        as Sunrise does), taken once a client holds its port; until then, and if it cannot be
        bound (a client holding the port on every address, as KUKA's SDK binds it), the fake
        sends from an ephemeral port on 127.0.0.1 (``fake_port.FriPort.claim``).
    idle_cycles: silent cycles before the session opens by itself (``auto_open``) at start and
        after a ``restart``.
    closing_idle_messages: IDLE messages sent when the application closes the session.
    ready_after / commanding_wait_cycles: consecutive answered windows needed to leave
        MONITORING_WAIT / COMMANDING_WAIT.
    limits: used to check what the client commands (per-cycle speed, position range) and,
        when ``abort_on_violation``, to end the motion as Sunrise does; None skips the checks.
    initial_position_rad: shape (7,); default the scene's pose or zeros.
    servo_frequency_hz, servo_damping: second-order servo from set-point to actual position.
    max_missed: consecutive missed windows that drop the session to MONITORING_WAIT.
    jitter_ms: each send is delayed by a uniform random 0..jitter_ms (simulated ms).
    loss_out / loss_in: probability that a monitoring message / an answer is lost.
    max_runtime_s: wall seconds after which the sending thread stops by itself.
    rt_priority: SCHED_FIFO priority of the sending thread when permitted (0: normal).
    fri_version: message layout, one of ``FRI_VERSIONS`` (see the module docstring).
    application: run the shipped robot application's behaviour (start the overlay motion by
        itself ``application_start_cycles`` messages after MONITORING_READY, again after drops).
    inputs: names of the BOOLEAN inputs the robot application shares over FRI (registered in
        its FRI configuration), e.g. ``MediaFlange.UserButton``; all released until
        ``set_input``. Every monitoring message carries them (``readIORequest``).
    record_commands: keep every applied set-point in ``stats.commands`` (for tests that judge
        the client's trajectory). A long-lived fake (the simulated cell of a daemon) passes
        False: the record grows by ~0.2 kB per set-point, without bound.
    """

    def __init__(
        self,
        client_address: tuple[str, int],
        *,
        limits: Optional[JointLimits] = None,
        send_period_ms: int = 5,
        receive_multiplier: int = 1,
        initial_position_rad: Optional[np.ndarray] = None,
        scene=None,
        clock=None,
        servo_frequency_hz: float = 6.0,
        servo_damping: float = 0.7,
        noise_rad: float = 0.0,
        seed: int = 0,
        auto_open: bool = True,
        idle_cycles: int = 0,
        closing_idle_messages: int = 5,
        controller_host: str = "127.0.0.2",
        ready_after: int = 10,
        commanding_wait_cycles: int = 10,
        max_missed: int = 20,
        quality_window: int = 50,
        start_tolerance_rad: float = 1e-3,
        echo_tolerance_rad: float = 1e-6,
        speed_tolerance: float = 1e-6,
        abort_on_violation: bool = True,
        jitter_ms: float = 0.0,
        loss_out: float = 0.0,
        loss_in: float = 0.0,
        max_runtime_s: float = 300.0,
        rt_priority: int = 0,
        fri_version: str = "1.15",
        application: bool = False,
        application_start_cycles: int = 20,
        inputs: tuple[str, ...] = (),
        record_commands: bool = True,
    ) -> None:
        host, port = client_address
        if fri_version not in FRI_VERSIONS:
            raise ValueError(f"fri_version must be one of {', '.join(FRI_VERSIONS)}, got {fri_version!r}")
        if host not in _LOOPBACK:
            raise ValueError(f"the fake Sunrise only talks to loopback, got client host {host!r}")
        if not (isinstance(send_period_ms, int) and 1 <= send_period_ms <= 100):
            raise ValueError(f"send_period_ms must be an integer in [1, 100], got {send_period_ms!r}")
        if not (isinstance(receive_multiplier, int) and 1 <= receive_multiplier <= 10):
            raise ValueError(f"receive_multiplier must be an integer in [1, 10], got {receive_multiplier!r}")
        for name, p in (("loss_out", loss_out), ("loss_in", loss_in)):
            if not 0 <= p < 1:
                raise ValueError(f"{name} must be a probability in [0, 1), got {p}")
        if limits is not None and limits.n_axes != N_JOINTS:
            raise ValueError(f"an LBR iiwa has {N_JOINTS} joints; limits have {limits.n_axes}")
        self.client_address = ("127.0.0.1" if host == "localhost" else host, int(port))
        self.limits = limits
        self.send_period_ms = send_period_ms
        self.receive_multiplier = receive_multiplier
        self.scene = scene
        self.clock = clock
        self.noise_rad = float(noise_rad)
        if controller_host not in _LOOPBACK and not controller_host.startswith("127."):
            raise ValueError(f"the fake Sunrise only sends from loopback, got controller_host {controller_host!r}")
        self.controller_host = controller_host
        self.jitter_ms = float(jitter_ms)
        self.loss_out = float(loss_out)
        self.max_runtime_s = float(max_runtime_s)
        self.rt_priority = int(rt_priority)
        self.fri_version = fri_version
        self._rng = np.random.default_rng(seed)

        if initial_position_rad is None:
            initial_position_rad = (
                np.asarray(scene.joint_positions(), dtype=float) if scene is not None else np.zeros(N_JOINTS)
            )
        self._servo = JointServo(initial_position_rad, servo_frequency_hz, servo_damping)
        self._windows = AnswerWindows(receive_multiplier, quality_window)
        for name in inputs:
            if not (isinstance(name, str) and 0 < len(name.encode("utf-8")) <= 63):
                raise ValueError(f"an FRI IO name is 1–63 bytes of UTF-8 (<IO group>.<IO>), got {name!r}")
        self._inputs = {name: False for name in inputs}  # shared BOOLEAN inputs: pressed or not

        self.stats = FakeSunriseStats()
        self._lock = threading.Lock()
        self._session = SunriseSession(
            self._servo, self._windows, self.stats, self._lock, auto_open=auto_open, idle_cycles=idle_cycles,
            closing_idle_messages=int(closing_idle_messages), ready_after=ready_after,
            commanding_wait_cycles=commanding_wait_cycles, max_missed=max_missed,
            abort_on_violation=abort_on_violation, application=bool(application),
            application_start_cycles=int(application_start_cycles))
        self._answers = AnswerHandler(
            self._session, fri_version=fri_version, limits=limits,
            receive_period_s=send_period_ms * receive_multiplier / 1000.0, start_tolerance_rad=start_tolerance_rad,
            echo_tolerance_rad=echo_tolerance_rad, speed_tolerance=speed_tolerance, loss_in=float(loss_in),
            record_commands=bool(record_commands), rng=self._rng)
        self._drop_next = 0
        self._malformed_next: list[str] = []
        self._sending = True
        self._port: Optional[FriPort] = None
        self._sender: Optional[SendLoop] = None

    # ------------------------------------------------------------------ public API

    @property
    def address(self) -> tuple[str, int]:
        """The fake's own (host, port): where the client's answers go."""
        if self._port is None:
            raise RuntimeError("FakeSunrise is not started")
        return self._port.address

    @property
    def overruns(self) -> int:
        """Send times the sending thread was descheduled past (it re-anchored)."""
        return 0 if self._sender is None else self._sender.overruns

    @property
    def loss_in(self) -> float:
        """Probability that an answer is lost (may be changed while running)."""
        return self._answers.loss_in

    @loss_in.setter
    def loss_in(self, p: float) -> None:
        self._answers.loss_in = float(p)

    @property
    def session_state(self) -> SessionState:
        with self._lock:
            return self._session.state

    @property
    def quality(self) -> ConnectionQuality:
        with self._lock:
            return self._windows.quality()

    def actual_position(self) -> np.ndarray:
        """The servo's actual joint positions, shape (7,), radians."""
        with self._lock:
            return self._servo.q.copy()

    def setpoint(self) -> np.ndarray:
        """The commanded position the servo holds (the client's last set-point), shape (7,), rad."""
        with self._lock:
            return self._servo.setpoint.copy()

    def hand_guide(self, displacement_rad: np.ndarray) -> None:
        """A person pushes the arm: the joint-impedance servo settles at set-point +
        ``displacement_rad`` (7,) instead of the set-point, and the monitoring messages say
        JOINT_IMPEDANCE_CONTROL_MODE (the robot application's hand-guiding mode, in which an iiwa
        yields to the hand). Zeros: the hand lets go and the arm springs back."""
        with self._lock:
            self._servo.push(displacement_rad)

    def release(self) -> None:
        """The hand lets go."""
        self.hand_guide(np.zeros(N_JOINTS))

    def set_input(self, name: str, value: bool) -> None:
        """Press (True) or release a shared BOOLEAN input (one of ``inputs``): the next
        monitoring messages carry the new value."""
        with self._lock:
            if name not in self._inputs:
                raise ValueError(f"the robot application shares no input {name!r} (it shares {sorted(self._inputs)})")
            self._inputs[name] = bool(value)

    def start(self) -> "FakeSunrise":
        """Bind the FRI port on ``controller_host`` (see the class docstring) and start."""
        if self._sender is not None:
            raise RuntimeError("FakeSunrise already started")
        self._port = FriPort(self.client_address, self.controller_host)
        self._port.claim(self._on_answer)
        self._sender = SendLoop(self._port, period_s=self._wall(self.send_period_ms / 1000.0),
                                max_runtime_s=self.max_runtime_s, rt_priority=self.rt_priority, cycle=self._tick,
                                on_answer=self._on_answer, end=self._end, closed=lambda: self._session.idle_to_send == 0,
                                stats=self.stats)
        self._sender.start()
        return self

    def stop(self, close_session: bool = True) -> None:
        """The robot application ends (idempotent): with ``close_session`` it closes the FRI
        session first, so the client reads IDLE (``closing_idle_messages`` of them), then the
        sending stops and the socket closes. ``close_session=False``: the controller just goes
        quiet (power cut, cable pulled)."""
        if self._sender is not None and self._sender.alive() and close_session:
            session = self._session
            with self._lock:
                session.ended = True
                session.close("robot application ended")
                if not self._sending:  # stop_sending(): a quiet controller says nothing more
                    session.idle_to_send = 0
                pending = session.idle_to_send
            wall = self._wall(self.send_period_ms / 1000.0) * (pending + 2) + 1.0
            with session.changed:
                session.changed.wait_for(lambda: session.idle_to_send == 0, wall)
        if self._sender is not None:
            self._sender.stop()
        if self._port is not None:
            self._port.close()

    def __enter__(self) -> "FakeSunrise":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait_state(self, state: SessionState, timeout: float) -> None:
        """Block until the session is in ``state``; TimeoutError after ``timeout`` wall s."""
        session = self._session
        with session.changed:
            if not session.changed.wait_for(lambda: session.state == state, timeout):
                raise TimeoutError(
                    f"fake Sunrise: session is {session.state.name}, not {state.name}, after {timeout} s"
                )

    def open_session(self) -> None:
        """The robot application opens its FRI session: IDLE → MONITORING_WAIT."""
        with self._lock:
            self._session.open()

    def close_session(self) -> None:
        """The robot application closes its FRI session: ``closing_idle_messages`` IDLE
        messages, then silence until the session opens again (``open_session``)."""
        with self._lock:
            self._session.close("session closed")

    def start_commanding(self) -> None:
        """The robot application starts a motion with a joint-position FRI overlay."""
        with self._lock:
            if self._session.state != SessionState.MONITORING_READY:
                raise RuntimeError(
                    f"start_commanding needs MONITORING_READY, the session is {self._session.state.name}"
                )
            self._session.set_state(SessionState.COMMANDING_WAIT, "application started an FRI motion")

    def stop_commanding(self) -> None:
        """The robot application ends its FRI motion."""
        with self._lock:
            if self._session.commanding():
                self._session.set_state(SessionState.MONITORING_READY, "application ended the FRI motion")

    # fault hooks ------------------------------------------------------

    def drop_next(self, n: int = 1) -> None:
        """Lose the next ``n`` monitoring messages (their counters are used up)."""
        with self._lock:
            self._drop_next += n

    def send_malformed(self, n: int = 1, kind: str = "garbage") -> None:
        """Replace the next ``n`` monitoring messages by bad bytes: ``garbage`` (random bytes),
        ``truncated`` (a valid message cut short), ``wrong_id`` (a command identifier) or
        ``bad_crc`` (an FRI 2.7 frame whose CRC-32 does not match the message)."""
        if kind not in MALFORMED_KINDS:
            raise ValueError(f"kind must be one of {', '.join(MALFORMED_KINDS)}, got {kind!r}")
        with self._lock:
            self._malformed_next.extend([kind] * n)

    def restart(self) -> None:
        """Controller restart: it goes silent (no IDLE message: the application is gone) for
        ``idle_cycles`` cycles, then the application opens the session again (``auto_open``)
        with the counters back at zero."""
        with self._lock:
            self._session.restart()

    def stop_sending(self) -> None:
        with self._lock:
            self._sending = False

    def resume_sending(self) -> None:
        with self._lock:
            self._sending = True

    def inject_fault(self, kind: str) -> None:
        """``drives_off`` (drive states OFF, brakes hold), ``safety_stop`` (safety stop level 1,
        brakes hold) or ``session_drop`` (the session falls back to MONITORING_WAIT)."""
        with self._lock:
            if kind == "drives_off":
                self._session.drives = DriveState.OFF
            elif kind == "safety_stop":
                self._session.safety = SafetyState.SAFETY_STOP_LEVEL_1
            elif kind == "session_drop":
                self._session.drop("injected session drop")
            else:
                raise ValueError(f"kind must be drives_off, safety_stop or session_drop, got {kind!r}")
            self._servo.halt()

    def drives_off(self) -> None:
        """Drives off (brakes hold); the monitoring messages say so. Same as ``inject_fault``."""
        self.inject_fault("drives_off")

    def drop_session(self) -> None:
        """The session falls back to MONITORING_WAIT (as after a connection-quality drop)."""
        self.inject_fault("session_drop")

    def hold_brakes(self, held: bool = True) -> None:
        """The joints stay where they are (a brake that does not release, a seized gear) while
        the controller reports everything normal and keeps taking the client's set-points."""
        with self._lock:
            self._servo.brakes_held = bool(held)
            self._servo.halt()

    def clear_fault(self) -> None:
        with self._lock:
            self._session.drives = DriveState.ACTIVE
            self._session.safety = SafetyState.NORMAL_OPERATION
            self._servo.hold_here()

    # ------------------------------------------------------------------ internals (lock held)

    def _build(self) -> bytes:
        servo = self._servo
        noise = self._rng.normal(0.0, self.noise_rad, N_JOINTS) if self.noise_rad else 0.0
        session = self._session
        return monitoring_datagram(self.fri_version, ControllerView(
            seq=session.seq, client_seq=session.client_seq, measured=servo.q + noise,
            setpoint=servo.setpoint, ipo=session.ipo, state=session.state, quality=self._windows.quality(),
            send_period_ms=self.send_period_ms, receive_multiplier=self.receive_multiplier,
            safety=session.safety, drives=session.drives, compliant=servo.compliant, inputs=dict(self._inputs)))

    def _cycle(self) -> Optional[bytes]:
        """One controller cycle (lock held): servo, window scoring, next message bytes."""
        session = self._session
        dt = self.send_period_ms / 1000.0
        session.sim_time += dt
        self._servo.step(dt, session.powered())
        if self.scene is not None:
            self.scene.set_joint_positions(self._servo.q.copy())
        if self._windows.message_due():
            session.close_window()
            self._windows.open(session.seq)
        session.tick()
        if not self._sending:
            return None
        if session.state == SessionState.IDLE and not session.idle_message_due():
            return None  # no session: the controller sends nothing
        data = self._build()
        if self._malformed_next:
            data = malformed_datagram(self._malformed_next.pop(0), data, self.fri_version, session.seq,
                                      session.client_seq, self._rng)
        session.next_seq()
        self.stats.sent += 1
        if self._drop_next > 0:
            self._drop_next -= 1
            return None
        if self.loss_out and self._rng.random() < self.loss_out:
            return None
        return data

    def _wall(self, sim_s: float) -> float:
        return self.clock.wall_duration(sim_s) if self.clock is not None else sim_s

    def _tick(self) -> tuple[Optional[bytes], float]:
        """The sending thread's cycle: (message or None, wall seconds of jitter before it)."""
        with self._lock:
            data = self._cycle()
            jitter = self._rng.uniform(0.0, self.jitter_ms / 1000.0) if self.jitter_ms else 0.0
        return data, (self._wall(jitter) if jitter else 0.0)

    def _end(self, why: str) -> None:
        """The robot application ends by itself: it closes the session first, never to reopen it."""
        with self._lock:
            self._session.ended = True
            self._session.close(why)

    def _on_answer(self, data: bytes) -> None:
        with self._lock:
            self._answers.handle(data)
