"""``FriCommander``: the ``JointCommander`` for a KUKA LBR iiwa over FRI.

The controller (Sunrise) is the sender: it sends a monitoring message every send period to
this client's UDP port (30200 by default); the client answers to the sender's address. The
exchange runs in a process of its own (``drivers/kuka_fri/realtime.py`` run by
``drivers/exchange.py``: SCHED_FIFO and locked memory when permitted, its garbage collector
frozen) around ``FriClientSession``; nothing this process does (fitting, writing, the bus) can
delay an answer. ``move_to`` checks and plans here, hands the trajectory over and waits;
``session`` is a read-only view of the exchange's session (snapshot, held position,
counters). If this process dies, the exchange process stops a running motion within its
limits, holds, then stops answering (Sunrise ends commanding) and exits.

URL: ``fri://HOST:PORT?option=value&...`` where HOST:PORT is the local address to bind
(``0.0.0.0:30200`` on the cell PC, ``127.0.0.1:0`` in tests). Options:

- ``controller=IP``: accept monitoring messages only from this address (default: any).
- ``rt_priority=N``: SCHED_FIFO priority of the exchange process, 0 to not ask (default 50).
- ``timeout_ms=N``: silence after which a running motion fails with DeviceTimeoutError
  (default 100).
- ``max_speed=F``: highest speed fraction the plan allows, (0, 1] (default 1).
- ``start_tolerance_deg=F``: allowed gap between measured and held position when a move
  starts (default 2).
- ``max_state_age_ms=N``: a measured state older than this is stale (default 100).
- ``fri_version=V``: the controller's FRI version (``1.11``…``1.16``, ``2.5``, ``2.7``, or
  ``auto``, the default): moves are refused when the controller's messages are of the other
  major version. The layout is always read off the messages (``layout_of``).
- ``session_wait_s=F``: how long a move waits for a session that left COMMANDING_ACTIVE (a
  drop under load, the robot application restarting its overlay) to come back before it
  fails with a ``DeviceFaultError`` the run can wait out (default 10).
- ``name=S``: device name for logs (default ``fri``).

``digital_input(name)`` reads a BOOLEAN or DIGITAL controller IO that the robot application
shares over FRI (``readIORequest`` of the monitoring messages), e.g. a button on the media
flange that confirms a socket recording (``drivers.socket``).
"""

from __future__ import annotations

import math
import time
from typing import Callable, Optional
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import DEFAULT_LIMIT_MARGIN_RAD, Clock, CommanderBase
from drivers.errors import DeviceFaultError, DeviceTimeoutError, DriverError, NotReadyError
from drivers.kuka_fri.link import FriLink, enum_name
from drivers.kuka_fri.messages import IOType, SessionState
from drivers.kuka_fri.session import N_JOINTS, MotionStoppedError, SessionSnapshot, check_ready, joint_state_of
from drivers.kuka_fri.session_view import SessionView
from drivers.protocols import JointLimits, JointState, LinkStats

__all__ = ["FriCommander", "MotionStoppedError", "SessionView"]

DEFAULT_PORT = 30200
#: Seconds a move waits for COMMANDING_ACTIVE before the wait is worth a warning.
QUIET_SESSION_WAIT_S = 3.0
#: Longest wall time a stop is waited for (``FriCommander._await_end``), however late the controller.
STOP_WAIT_CAP_S = 30.0
STOP_NOT_OVER = "the stop has not ended yet; is the controller sending?"
_URL_OPTIONS = ("controller", "rt_priority", "timeout_ms", "max_speed", "start_tolerance_deg",
                "max_state_age_ms", "fri_version", "session_wait_s", "name")
#: FRI versions whose message tables the session knows (1.11–1.16 share 1.x's layout).
KNOWN_VERSIONS = ("1.11", "1.12", "1.13", "1.14", "1.15", "1.16", "2.5", "2.6", "2.7")


def _fri_major(value: str) -> Optional[int]:
    if value == "auto":
        return None
    if value not in KNOWN_VERSIONS:
        raise ValueError(f"known versions: auto, {', '.join(KNOWN_VERSIONS)}")
    return int(value.split(".")[0])


class FriCommander(CommanderBase):
    """Joint-position commander over FRI for a 7-axis LBR iiwa.

    Sunrise grades the connection itself (quality from the answer windows, a session drop after
    too many misses, which a run waits out): our own late-answer count is a figure for people
    (``link_stats``), not a health verdict (``controller_stops_on_late_answers``).

    limits: the model's limits, shape (7,) arrays (radians, rad/s, rad/s²).
    bind: local (host, port) to receive monitoring messages on; port 0 picks a free one.
    controller_host: accept datagrams only from this IP (None: any sender).
    receive_timeout_s: silence (client clock) after which a running motion fails.
    clock / sleep: client time source and sleep (inject a ``SimClock``'s ``now``/``sleep``);
    the clock must be picklable (the exchange process reads it too).
    orphan_hold_s: how long the exchange process holds the stopped robot after this process
    died before it stops answering.
    """

    controller_stops_on_late_answers = False

    def __init__(
        self,
        limits: JointLimits,
        *,
        bind: tuple[str, int] = ("0.0.0.0", DEFAULT_PORT),
        controller_host: Optional[str] = None,
        name: str = "fri",
        rt_priority: int = 50,
        receive_timeout_s: float = 0.1,
        start_tolerance_rad: float = math.radians(2.0),
        max_speed: float = 1.0,
        max_state_age_s: float = 0.1,
        limit_margin_rad: float = DEFAULT_LIMIT_MARGIN_RAD,
        fri_version: str = "auto",
        session_wait_s: float = 10.0,
        orphan_hold_s: float = 0.5,
        clock: Clock = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if limits.n_axes != N_JOINTS:
            raise ValueError(f"{name}: an LBR iiwa has {N_JOINTS} axes; the model limits have {limits.n_axes}")
        super().__init__(
            name, limits, max_speed=max_speed, limit_margin_rad=limit_margin_rad,
            max_state_age_s=max_state_age_s, clock=clock,
        )
        if not (isinstance(rt_priority, int) and 0 <= rt_priority <= 99):
            raise ValueError(f"rt_priority must be an integer in [0, 99], got {rt_priority!r}")
        if not receive_timeout_s > 0:
            raise ValueError(f"receive_timeout_s must be positive, got {receive_timeout_s}")
        self.bind = (bind[0], int(bind[1]))
        self.controller_host = controller_host
        self.rt_priority = rt_priority
        self.receive_timeout_s = float(receive_timeout_s)
        self._sleep_fn = sleep
        try:
            major = _fri_major(str(fri_version))
        except ValueError as exc:
            raise ValueError(f"fri_version {fri_version!r} is not known; {exc}") from None
        if not session_wait_s >= 0:
            raise ValueError(f"session_wait_s must be >= 0, got {session_wait_s}")
        self.fri_version = str(fri_version)
        self.session_wait_s = float(session_wait_s)
        self.orphan_hold_s = float(orphan_hold_s)
        self._W = 1 << 16  # cycles in the latency ring
        self._link = FriLink(self.name, self.log, window=self._W, rt_priority=rt_priority)
        self.session = SessionView(self._link, self.limits, start_tolerance_rad=float(start_tolerance_rad),
                                   expect_major=major)

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_url(cls, url: str, *, limits: JointLimits, **kwargs) -> "FriCommander":
        """Build from ``fri://HOST:PORT?options`` (see the module docstring)."""
        parts = urlsplit(url)
        if parts.scheme != "fri":
            raise ValueError(f"FRI URL must start with fri://, got {url!r}")
        try:
            port = parts.port
        except ValueError as exc:
            raise ValueError(f"bad port in FRI URL {url!r}: {exc}") from exc
        host = parts.hostname or "0.0.0.0"
        opts = dict(parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False))
        unknown = sorted(set(opts) - set(_URL_OPTIONS))
        if unknown:
            raise ValueError(f"unknown FRI URL option(s) {unknown}; allowed: {', '.join(_URL_OPTIONS)}")
        conv = {
            "controller": ("controller_host", str),
            "rt_priority": ("rt_priority", int),
            "timeout_ms": ("receive_timeout_s", lambda v: float(v) / 1000.0),
            "max_speed": ("max_speed", float),
            "start_tolerance_deg": ("start_tolerance_rad", lambda v: math.radians(float(v))),
            "max_state_age_ms": ("max_state_age_s", lambda v: float(v) / 1000.0),
            "fri_version": ("fri_version", str),
            "session_wait_s": ("session_wait_s", float),
            "name": ("name", str),
        }
        args = {}
        for key, raw in opts.items():
            arg, fn = conv[key]
            try:
                args[arg] = fn(raw)
            except ValueError as exc:
                raise ValueError(f"FRI URL option {key}={raw!r} is not valid: {exc}") from exc
        args.update(kwargs)
        return cls(limits, bind=(host, DEFAULT_PORT if port is None else port), **args)

    # ------------------------------------------------------------------ lifecycle

    @property
    def address(self) -> tuple[str, int]:
        """The bound local (host, port); the controller sends here."""
        if self._link.exchange is None:
            raise RuntimeError(f"{self.name}: not connected")
        return self._link.address

    @property
    def exchange_pid(self) -> Optional[int]:
        """Process id of the exchange process (None when not connected)."""
        return None if self._link.exchange is None else self._link.exchange.pid

    @property
    def rt_scheduling(self) -> str:
        """How the exchange process is (or last was) scheduled (``SCHED_FIFO 50, memory locked``, …)."""
        return self._link.scheduling

    def connect(self) -> None:
        """Bind the UDP port and start the exchange process (answers start with the controller)."""
        if self._link.exchange is not None:
            return
        options = dict(
            limits=self.limits, start_tolerance_rad=self.session.start_tolerance_rad,
            expect_major=self.session.expect_major, controller_host=self.controller_host,
            receive_timeout_s=self.receive_timeout_s, clock=self.clock, window=self._W,
            orphan_hold_s=self.orphan_hold_s,
        )
        self._link.start(self.bind, options)
        ex = self._link.exchange
        self.log.info("FRI client listening on %s:%d; exchange process %s: %s", *self._link.address, ex.pid,
                      ex.realtime)

    def close(self) -> None:
        """Stop a running motion (decelerating), end the exchange process (it closes the port)."""
        if self._link.exchange is None:
            return
        if self.session.motion_active():
            try:
                self.stop()
            except DeviceTimeoutError as exc:
                self.log.warning("stop on close did not finish: %s", exc)
        self._link.close(self.link_stats())

    def link_stats(self) -> LinkStats:
        """Timing of the last cycles, measured in the exchange process (see ``LinkStats``).
        Costs O(window); not for a tight loop."""
        return self._link.link_stats(self.session.snapshot())

    def latencies(self) -> np.ndarray:
        """Answer latencies (s) of the last cycles, oldest first, shape (min(packets, window),),
        measured in the exchange process (kernel arrival stamp to the answer's send; 0 for a
        message that needed no answer)."""
        return self.answer_log()[2]

    def answer_log(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(messages, arrived, latency)``: monitoring messages so far and, for the last
        min(messages, window) of them, oldest first, each shape (m,), the arrival time on the
        commander's ``clock`` (s; ``time.monotonic`` by default) and the answer latency (s; 0 for
        a message that needed no answer) — to place late answers in time (benches poll it)."""
        return self._link.answer_log()

    @property
    def malformed_messages(self) -> int:
        st = self._link.read(("malformed",))
        return 0 if st is None else int(st["malformed"][0])

    @property
    def foreign_datagrams(self) -> int:
        st = self._link.read(("foreign",))
        return 0 if st is None else int(st["foreign"][0])

    # ------------------------------------------------------------------ JointCommander

    @property
    def session_state(self) -> Optional[SessionState]:
        """The session state of the latest monitoring message (None before the first)."""
        return self.session.session_state

    def wait_session(self, state: SessionState, timeout: float) -> None:
        """Wait until the controller reports ``state``; DeviceTimeoutError after ``timeout``."""
        deadline = self.clock() + timeout
        while self.session.session_state != state:
            if self.clock() > deadline:
                raise DeviceTimeoutError(
                    f"{self.name}: session is {getattr(self.session.session_state, 'name', None)}, "
                    f"not {state.name}, after {timeout} s"
                )
            self._sleep(0.005)

    def _fresh_snapshot(self) -> SessionSnapshot:
        """The latest monitoring message's snapshot; DeviceTimeoutError if none or stale."""
        snap: Optional[SessionSnapshot] = self.session.snapshot()
        if snap is None:
            raise DeviceTimeoutError(f"{self.name}: no monitoring message received yet")
        age = self.clock() - snap.host_time
        if age > self.max_state_age_s:
            raise DeviceTimeoutError(
                f"{self.name}: last monitoring message is {age * 1e3:.0f} ms old "
                f"(allowed {self.max_state_age_s * 1e3:.0f} ms); is the controller sending?"
            )
        return snap

    def joint_state(self) -> JointState:
        """Latest measured joint positions, shape (7,), radians; DeviceTimeoutError if stale."""
        snap = self._fresh_snapshot()
        if snap.measured_rad is None:
            raise DeviceTimeoutError(f"{self.name}: controller sends no measured joint position")
        return joint_state_of(snap)

    def digital_input(self, name: str) -> bool:
        """Whether the controller IO ``name`` (a BOOLEAN or DIGITAL IO the robot application shares
        over FRI, e.g. ``MediaFlange.UserButton``) is set in the latest monitoring message.
        DeviceTimeoutError if that message is stale; DriverError if the IO is not shared or analog."""
        snap = self._fresh_snapshot()
        deadline = time.monotonic() + 1.0
        while not snap.io and self.session.io_pending() and time.monotonic() < deadline:
            time.sleep(0.005)  # the IO names of a new table are on their way from the exchange
            snap = self._fresh_snapshot()
        for io in snap.io:
            if io.name != name:
                continue
            if io.type not in (IOType.BOOLEAN, IOType.DIGITAL):
                raise DriverError(f"{self.name}: controller IO {name!r} is {enum_name(IOType, io.type)}; "
                                  "name a BOOLEAN or DIGITAL IO")
            return bool(io.digital_value)
        shared = ", ".join(repr(io.name) for io in snap.io) or "none"
        raise DriverError(f"{self.name}: the controller shares no IO named {name!r} over FRI (it shares: {shared}); "
                          "register it in the robot application's FRI configuration, or correct the name")

    def ready(self) -> JointState:
        """The measured state when a move could start now: a fresh state, the session
        COMMANDING_ACTIVE with drives ACTIVE and normal safety, a command held, no move still
        ending (``plan_move``'s checks without a target); else NotReadyError saying why."""
        state = super().ready()
        snap = self.session.snapshot()
        if snap is None:
            raise NotReadyError(f"{self.name}: no monitoring message received yet; is the controller sending?")
        check_ready(snap, self.limits, self.session.expect_major, self.name)
        if self.session.motion_active():
            raise NotReadyError(f"{self.name}: the last move is still ending")
        if self.session.held_position() is None:
            raise NotReadyError(f"{self.name}: no command held yet in COMMANDING_ACTIVE")
        return state

    def _wait_commanding(self) -> None:
        """A session that left COMMANDING_ACTIVE (a drop under load, a controller restart) comes
        back when the robot application starts its overlay again: wait up to ``session_wait_s``
        for it. DeviceFaultError (the run waits it out and retries) when it does not."""
        state = self.session.session_state
        if state == SessionState.COMMANDING_ACTIVE or state is None:
            return
        # A healthy start passes through MONITORING_READY and COMMANDING_WAIT within a second or
        # two: that is news, not a warning. Only a wait that runs long is.
        self.log.info("%s: session is %s; waiting up to %.0f s for COMMANDING_ACTIVE",
                      self.name, state.name, self.session_wait_s)
        quiet = min(QUIET_SESSION_WAIT_S, self.session_wait_s)
        try:
            self.wait_session(SessionState.COMMANDING_ACTIVE, quiet)
        except DeviceTimeoutError:
            now = self.session.session_state
            self.log.warning("%s: session still %s after %.0f s; waiting up to %.0f s more for COMMANDING_ACTIVE "
                             "(is the robot application's FRI overlay motion running?)",
                             self.name, getattr(now, "name", None), quiet, self.session_wait_s - quiet)
        try:
            self.wait_session(SessionState.COMMANDING_ACTIVE, self.session_wait_s - quiet)
        except DeviceTimeoutError as exc:
            raise DeviceFaultError(
                f"{exc}; start the FRI joint-position overlay in the robot application "
                "(drivers/kuka_fri/controller/) and resume"
            ) from exc
        self._sleep(2 * (self.session.snapshot().receive_period_s or 0.01))  # one held command first

    def _move_internal(self, start: JointState, target_rad: np.ndarray, speed: float, timeout: float) -> None:
        self._wait_commanding()
        motion = self.session.begin_move(target_rad, speed, self.name)
        self.log.info(
            "move to %s deg at speed %.3g: %.3f s", np.round(np.degrees(target_rad), 3).tolist(),
            speed, motion.planned_s,
        )
        deadline = self.clock() + timeout
        while not motion.done.wait(0.005):
            if self.clock() > deadline:
                self.session.request_stop()
                how = "stopped"
                if not self._await_end(motion):
                    how = STOP_NOT_OVER
                elif motion.error is not None and not isinstance(motion.error, MotionStoppedError):
                    how = f"ended: {motion.error}"  # (a fault ended it first)
                raise DeviceTimeoutError(
                    f"{self.name}: move not finished within {timeout:.3g} s "
                    f"(planned {motion.planned_s:.3g} s); {how}"
                )
        if motion.error is not None:
            raise motion.error

    def _await_end(self, motion) -> bool:
        """Wait until the exchange reports ``motion`` ended after a stop was asked for; False
        when it still runs. A stop advances one step per monitoring message, so the wait is
        counted in the controller's cycles, not in wall time: a controller whose messages come
        late (a starved one) stops late but stops, and a move reported over *is* over (the next
        one is not refused as "already in progress"). The worst stop, ``2 v/a + 0.5 s`` of the
        controller's time plus 10 cycles, bounds the cycles; a silence bounds the wait too: past
        ``receive_timeout_s`` the exchange ends the motion itself, and one second of wall time
        more without that means the exchange is not working. ``STOP_WAIT_CAP_S`` of wall time
        caps it all (a caller, an operator's abort, gets its answer; the stop goes on)."""
        v, a, _ = motion.limits_scaled
        cycles = math.ceil((2.0 * float(np.max(v / a)) + 0.5) / motion.dt) + 10
        first = self.session.counters.received
        cap = time.monotonic() + STOP_WAIT_CAP_S
        silent_since: Optional[float] = None
        while not motion.done.wait(0.005):
            if self.session.counters.received - first > cycles or time.monotonic() > cap:
                return False
            snap = self.session.snapshot()
            if snap is not None and self.clock() - snap.host_time <= self.receive_timeout_s:
                silent_since = None
            elif silent_since is None:
                silent_since = time.monotonic()
            elif time.monotonic() - silent_since > 1.0:
                return False
        deadline = time.monotonic() + 1.0  # the exchange publishes the end right before it reports it
        while self.session.motion_active() and time.monotonic() < deadline:
            time.sleep(0.002)
        return True

    def stop(self) -> None:
        """Decelerate the current motion within the limits and hold (no-op when idle); returns
        once the robot stopped (``_await_end``). A ``move_to`` waiting on it raises
        ``MotionStoppedError``."""
        motion = self.session.request_stop()
        if motion is not None and not self._await_end(motion):
            raise DeviceTimeoutError(f"{self.name}: {STOP_NOT_OVER}")

    def _sleep(self, dt: float) -> None:
        self._sleep_fn(dt)

