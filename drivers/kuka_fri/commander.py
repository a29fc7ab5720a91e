"""``FriCommander``: the ``JointCommander`` for a KUKA LBR iiwa over FRI.

The controller (Sunrise) is the sender: it sends a monitoring message every send period to
this client's UDP port (30200 by default); the client answers to the sender's address. The
exchange runs in its own thread (``fri-rt``, SCHED_FIFO when permitted) around
``FriClientSession``; ``move_to`` only plans, hands the trajectory over and waits. Because a
Python thread holding the GIL keeps it up to the interpreter's switch interval (5 ms, a whole
FRI period), ``connect`` lowers that interval to 0.5 ms and ``close`` restores it.

URL: ``fri://HOST:PORT?option=value&...`` where HOST:PORT is the local address to bind
(``0.0.0.0:30200`` on the cell PC, ``127.0.0.1:0`` in tests). Options:

- ``controller=IP``: accept monitoring messages only from this address (default: any).
- ``rt_priority=N``: SCHED_FIFO priority of the exchange thread, 0 to not ask (default 50).
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
import os
import socket
import sys
import threading
import time
from typing import Callable, Optional
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import DEFAULT_LIMIT_MARGIN_RAD, Clock, CommanderBase
from drivers.errors import ConnectionLostError, DeviceFaultError, DeviceTimeoutError, DriverError, ProtocolError
from drivers.kuka_fri.messages import ConnectionQuality, IOType, SessionState, decode_monitoring, encode_command
from drivers.kuka_fri.session import (
    N_JOINTS,
    FriClientSession,
    MotionStoppedError,
    SessionSnapshot,
    joint_state_of,
)
from drivers.protocols import JointLimits, JointState, LinkStats

__all__ = ["FriCommander", "MotionStoppedError"]

DEFAULT_PORT = 30200
_URL_OPTIONS = ("controller", "rt_priority", "timeout_ms", "max_speed", "start_tolerance_deg",
                "max_state_age_ms", "fri_version", "session_wait_s", "name")
#: FRI versions whose message tables the session knows (1.11–1.16 share 1.x's layout).
KNOWN_VERSIONS = ("1.11", "1.12", "1.13", "1.14", "1.15", "1.16", "2.5", "2.6", "2.7")


def _enum_name(cls, value: int) -> str:
    try:
        return cls(value).name
    except ValueError:
        return str(value)


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
    switch_interval_s: interpreter thread switch interval while connected (None: leave it).
    clock / sleep: client time source and sleep (inject a ``SimClock``'s ``now``/``sleep``).
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
        switch_interval_s: Optional[float] = 0.0005,
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
        if switch_interval_s is not None and not switch_interval_s > 0:
            raise ValueError(f"switch_interval_s must be positive or None, got {switch_interval_s}")
        self.switch_interval_s = switch_interval_s
        self._saved_switch_interval: Optional[float] = None
        try:
            major = _fri_major(str(fri_version))
        except ValueError as exc:
            raise ValueError(f"fri_version {fri_version!r} is not known; {exc}") from None
        if not session_wait_s >= 0:
            raise ValueError(f"session_wait_s must be >= 0, got {session_wait_s}")
        self.fri_version = str(fri_version)
        self.session_wait_s = float(session_wait_s)
        self.session = FriClientSession(limits, start_tolerance_rad=start_tolerance_rad, expect_major=major,
                                        logger=self.log)
        # link statistics, written by the exchange thread only (a ring of the last _W cycles)
        self._W = 2000
        self._rx = np.zeros(self._W)
        self._lat = np.zeros(self._W)
        self._count = 0
        self._late = 0
        self._gaps = 0
        self._seen_seq: Optional[int] = None
        self.rt_scheduling: str = "not started"
        self.malformed_messages = 0
        self.foreign_datagrams = 0
        self._sock: Optional[socket.socket] = None
        self._thread: Optional[threading.Thread] = None
        self._running = threading.Event()
        self._last_warning = -math.inf

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
        if self._sock is None:
            raise RuntimeError(f"{self.name}: not connected")
        return self._sock.getsockname()

    def connect(self) -> None:
        """Bind the UDP port and start the exchange thread (answers start with the controller)."""
        if self._thread is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(self.bind)
        except OSError as exc:
            sock.close()
            raise ConnectionLostError(f"{self.name}: cannot bind UDP {self.bind[0]}:{self.bind[1]}: {exc}") from exc
        sock.settimeout(min(0.02, self.receive_timeout_s / 2))
        self._sock = sock
        self._running.set()
        self._shorten_switch_interval()
        self._thread = threading.Thread(target=self._rt_loop, name=f"{self.name}-rt", daemon=True)
        self._thread.start()
        self.log.info("FRI client listening on %s:%d", *self.address)

    def close(self) -> None:
        """Stop a running motion (decelerating), end the exchange thread and close the port."""
        if self._thread is None:
            return
        if self.session.motion_active():
            try:
                self.stop()
            except DeviceTimeoutError as exc:
                self.log.warning("stop on close did not finish: %s", exc)
        self._running.clear()
        self._thread.join(timeout=2.0)
        self._thread = None
        if self._saved_switch_interval is not None:
            if sys.getswitchinterval() == self.switch_interval_s:
                sys.setswitchinterval(self._saved_switch_interval)
            self._saved_switch_interval = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # ------------------------------------------------------------------ the exchange thread

    def _shorten_switch_interval(self) -> None:
        """A Python thread holding the GIL keeps it for up to ``sys.getswitchinterval()``
        (5 ms by default): a whole FRI period. While connected we lower it so the exchange
        thread gets the interpreter within ``switch_interval_s`` of its datagram."""
        if self.switch_interval_s is None or sys.getswitchinterval() <= self.switch_interval_s:
            return
        self._saved_switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(self.switch_interval_s)
        self.log.info(
            "thread switch interval lowered from %.1f ms to %.2f ms for the FRI exchange",
            self._saved_switch_interval * 1e3, self.switch_interval_s * 1e3,
        )

    def _set_realtime(self) -> None:
        if self.rt_priority == 0:
            self.rt_scheduling = "normal (rt_priority=0)"
            return
        if not hasattr(os, "sched_setscheduler"):
            self.rt_scheduling = "normal (no SCHED_FIFO on this platform)"
            self.log.warning("SCHED_FIFO is not available on this platform; FRI runs at normal priority")
            return
        try:  # pid 0: the calling thread on Linux
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
            self.rt_scheduling = f"SCHED_FIFO {self.rt_priority}"
            self.log.info("FRI exchange thread runs SCHED_FIFO priority %d", self.rt_priority)
        except PermissionError as exc:
            self.rt_scheduling = "normal (SCHED_FIFO not permitted)"
            self.log.warning(
                "SCHED_FIFO priority %d not permitted (%s): the FRI exchange runs at normal priority "
                "and may answer late under load. Grant it with LimitRTPRIO=%d in the systemd unit, "
                "an rtprio limit in /etc/security/limits.d, or CAP_SYS_NICE.",
                self.rt_priority, exc, self.rt_priority,
            )

    def _rt_loop(self) -> None:
        self._set_realtime()
        sock = self._sock
        assert sock is not None
        session = self.session
        while self._running.is_set():
            try:
                data, addr = sock.recvfrom(4096)
            except socket.timeout:
                session.check_silence(self.clock(), self.receive_timeout_s)
                continue
            except OSError as exc:
                if not self._running.is_set():
                    break
                self._warn(f"receive failed: {exc}")
                continue
            now = self.clock()
            if self.controller_host is not None and addr[0] != self.controller_host:
                self.foreign_datagrams += 1
                session.check_silence(now, self.receive_timeout_s)
                continue
            try:
                msg = decode_monitoring(data)
            except ProtocolError as exc:
                self.malformed_messages += 1
                self._warn(f"malformed monitoring message ({len(data)} bytes) from {addr[0]}:{addr[1]}: {exc}")
                session.check_silence(now, self.receive_timeout_s)
                continue
            self._count_cycle(msg.header.sequence_counter, now)
            try:
                reply = session.on_monitoring(msg, now)
            except Exception as exc:  # noqa: BLE001 - the exchange thread must survive a bug
                self.log.exception("FRI cycle failed; ending any motion")
                session.abort(DeviceFaultError(f"{self.name}: FRI cycle failed: {exc!r}"))
                continue
            if reply is not None:
                try:
                    sock.sendto(encode_command(reply), addr)
                except OSError as exc:
                    self._warn(f"send to {addr[0]}:{addr[1]} failed: {exc}")
                self._count_answer(now)

    def _count_cycle(self, seq: int, now: float) -> None:
        """Exchange thread: one monitoring message arrived at ``now``."""
        prev, self._seen_seq = self._seen_seq, seq
        if prev is not None and seq > prev + 1 and seq - prev < (1 << 31):
            self._gaps += seq - prev - 1
        i = self._count % self._W
        self._rx[i] = now
        self._lat[i] = 0.0
        self._count += 1

    def _count_answer(self, received: float) -> None:
        """Exchange thread: the answer to the message received at ``received`` is sent."""
        latency = self.clock() - received
        self._lat[(self._count - 1) % self._W] = latency
        snap = self.session.snapshot()
        if snap is not None and snap.receive_period_s and latency > snap.receive_period_s:
            self._late += 1

    def _warn(self, text: str) -> None:
        """Rate-limited warning: at most one per second from the exchange thread."""
        t = time.monotonic()
        if t - self._last_warning >= 1.0:
            self._last_warning = t
            self.log.warning("%s", text)

    def _ordered(self, ring: np.ndarray) -> np.ndarray:
        count = self._count
        if count <= self._W:
            return ring[:count].copy()
        i = count % self._W
        return np.concatenate([ring[i:], ring[:i]])

    def link_stats(self) -> LinkStats:
        """Timing of the last cycles (see ``LinkStats``). Costs O(window); not for the RT path."""
        rx, lat = self._ordered(self._rx), self._ordered(self._lat)
        n = lat.shape[0]
        per = np.diff(rx) if n > 1 else np.zeros(1)
        q = np.percentile(lat, [50, 99]) if n else np.zeros(2)
        snap = self.session.snapshot()
        notes = ["session: no monitoring message yet"] if snap is None else [
            f"session: {snap.session_state.name}, quality {_enum_name(ConnectionQuality, snap.quality)}, "
            f"{snap.layout}, receive period {(snap.receive_period_s or 0) * 1e3:.0f} ms",
        ]
        notes.append(f"exchange thread: {self.rt_scheduling}; foreign datagrams {self.foreign_datagrams}")
        return LinkStats(
            packets=self._count, window=n, period_mean_s=float(per.mean()), period_std_s=float(per.std()),
            period_max_s=float(per.max()), latency_p50_s=float(q[0]), latency_p99_s=float(q[1]),
            latency_max_s=float(lat.max()) if n else 0.0, late_answers=self._late, gaps=self._gaps,
            malformed=self.malformed_messages, restarts=self.session.counters.restarts,
            guard_clamps=self.session.counters.step_clamps, delay=None,
            realtime=self.rt_scheduling.startswith("SCHED_FIFO"), notes=tuple(notes),
        )

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
        for io in snap.io:
            if io.name != name:
                continue
            if io.type not in (IOType.BOOLEAN, IOType.DIGITAL):
                raise DriverError(f"{self.name}: controller IO {name!r} is {_enum_name(IOType, io.type)}; "
                                  "name a BOOLEAN or DIGITAL IO")
            return bool(io.digital_value)
        shared = ", ".join(repr(io.name) for io in snap.io) or "none"
        raise DriverError(f"{self.name}: the controller shares no IO named {name!r} over FRI (it shares: {shared}); "
                          "register it in the robot application's FRI configuration, or correct the name")

    def _wait_commanding(self) -> None:
        """A session that left COMMANDING_ACTIVE (a drop under load, a controller restart) comes
        back when the robot application starts its overlay again: wait up to ``session_wait_s``
        for it. DeviceFaultError (the run waits it out and retries) when it does not."""
        state = self.session.session_state
        if state == SessionState.COMMANDING_ACTIVE or state is None:
            return
        self.log.warning("%s: session is %s; waiting up to %.0f s for COMMANDING_ACTIVE",
                         self.name, state.name, self.session_wait_s)
        try:
            self.wait_session(SessionState.COMMANDING_ACTIVE, self.session_wait_s)
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
                motion.done.wait(self._stop_wait_s(motion))
                raise DeviceTimeoutError(
                    f"{self.name}: move not finished within {timeout:.3g} s "
                    f"(planned {motion.planned_s:.3g} s); stopped"
                )
        if motion.error is not None:
            raise motion.error

    def _stop_wait_s(self, motion) -> float:
        """Wall time to wait for a stop to finish: the worst stop time plus slack."""
        v, a, _ = motion.limits_scaled
        return float(np.max(v / a)) * 2.0 + 10 * motion.dt + 0.5

    def stop(self) -> None:
        """Decelerate the current motion within the limits and hold (no-op when idle).
        A ``move_to`` waiting on it raises ``MotionStoppedError``."""
        motion = self.session.request_stop()
        if motion is None:
            return
        if not motion.done.wait(self._stop_wait_s(motion)):
            raise DeviceTimeoutError(f"{self.name}: stop did not complete; is the controller sending?")

    def _sleep(self, dt: float) -> None:
        self._sleep_fn(dt)
