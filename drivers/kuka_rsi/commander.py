"""``RsiCommander``: the PC side of KUKA RSI, a real-time answering thread plus safe joint moves.

The controller sends ``<Rob>`` every interpolation cycle (4 or 12 ms) and the PC must answer each
packet, to its source address and echoing its IPOC, within the cycle. One thread does only that:
receive, parse (regex), take the next row of a precomputed correction table, check it against the
per-cycle limits, format (``%`` template), send. Everything slow (planning, sampling, waiting,
logging) happens in the caller's thread before the motion is handed over.

Corrections are ``RSI_ON(#ABSOLUTE)`` axis corrections ``AK``: the total offset from the start
position ``ASPos`` (degrees). The trajectory advances exactly one cycle per packet answered, so the
command stream obeys the limits cycle by cycle whatever the timing jitter or packet loss; each row
is additionally checked (position, velocity, acceleration per cycle) and a violating row is
clamped and the motion stopped.

Real-time notes: the thread asks for SCHED_FIFO (logs a clear warning when not permitted),
the interpreter's switch interval is lowered so it gets the GIL within ~0.2 ms, every code path
is warmed up before the first packet, and lateness is measured from the kernel's arrival stamp.
What a thread cannot fix in CPython is another thread of the same process holding the GIL while
the OS has preempted it (a saturated host): expect rare late answers there (see
``tests/bench/bench_rsi.py``); an isolated core or a separate exchange process removes them.

Faults end the motion with a clear error: no packet for ``timeout_cycles`` cycles
(``DeviceTimeoutError``), the controller's ``Delay`` growing by more than ``delay_limit`` within
``delay_window`` cycles or the RSI session restarting mid-motion (``DeviceFaultError``).
"""

from __future__ import annotations

import math
import os
import socket
import sys
import threading
import time
from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import DEFAULT_LIMIT_MARGIN_RAD, CommanderBase, check_timeout
from drivers.errors import (
    ConnectionLostError,
    DeviceFaultError,
    DeviceTimeoutError,
    DriverError,
    LimitError,
    ProtocolError,
)
from drivers.kuka_rsi.codec import SenFormatter, parse_rob
from drivers.kuka_rsi.udp import enable_rx_timestamps, recv_stamped
from drivers.protocols import JointLimits, JointState, LinkStats
from drivers.trajectory import JointTrajectory, default_jerk, scaled_limits

__all__ = ["RsiCommander", "LinkStats"]

DEFAULT_PORT = 49152
#: Relative slack of the per-cycle guard: a row may exceed a limit by this fraction only
#: (covers the rounding of the 7-decimal wire format, never a real excess).
GUARD_SLACK = 1e-6


class _Motion:
    """A precomputed correction table handed to the real-time thread.

    rows_deg: shape (m, n), AK/EK values for the next m cycles, degrees. ``traj`` is sampled at
    ``(k + 1 + t_offset_cycles) · dt`` for row k (used to plan a stop from the current state).
    """

    __slots__ = ("rows_deg", "k", "traj", "session", "done", "error", "is_stop", "ref_rad")

    def __init__(self, rows_deg, traj, session, ref_rad, is_stop=False) -> None:
        self.rows_deg = rows_deg
        self.k = 0
        self.traj = traj
        self.session = session
        self.ref_rad = ref_rad
        self.done = threading.Event()
        self.error: DriverError | None = None
        self.is_stop = is_stop


class RsiCommander(CommanderBase):
    """Joint commander over KUKA RSI. See the module docstring.

    limits: the robot model's limits; its axis count must equal the controller's (A1..A6 plus
    external E1..Em). host, port: where to listen for the controller (``0.0.0.0:49152``).
    cycle_ms: 4 (``#IPO_FAST``) or 12 (``#IPO``). timeout_cycles: silence that ends a motion.
    delay_limit / delay_window: tolerated growth of the controller's late count. rt_priority:
    SCHED_FIFO priority for the exchange thread (0: don't try). switch_interval_s: the
    interpreter's thread switch interval is lowered to this (process-wide) so the exchange thread
    gets the GIL quickly (None: leave it). max_deviation_rad: largest
    allowed difference between the measured and the commanded position when a move starts.
    """

    def __init__(
        self,
        limits: JointLimits,
        *,
        host: str = "0.0.0.0",
        port: int = DEFAULT_PORT,
        cycle_ms: int = 4,
        name: str = "rsi",
        max_speed: float = 1.0,
        timeout_cycles: int = 25,
        delay_limit: int = 20,
        delay_window: int = 250,
        connect_timeout: float = 5.0,
        sen_type: str = "ImFree",
        rt_priority: int = 50,
        max_deviation_rad: float = math.radians(2.0),
        max_jerk_rad_s3=None,
        limit_margin_rad: float = DEFAULT_LIMIT_MARGIN_RAD,
        max_state_age_s: float = 0.1,
        stats_window: int = 1 << 16,
        switch_interval_s: float | None = 2e-4,
    ) -> None:
        super().__init__(
            name, limits, max_speed=max_speed, limit_margin_rad=limit_margin_rad, max_state_age_s=max_state_age_s
        )
        if cycle_ms not in (4, 12):
            raise ValueError(f"cycle_ms must be 4 (#IPO_FAST) or 12 (#IPO), got {cycle_ms!r}")
        if not (isinstance(timeout_cycles, int) and timeout_cycles >= 2):
            raise ValueError(f"timeout_cycles must be an integer >= 2, got {timeout_cycles!r}")
        if delay_limit < 1 or delay_window < 1:
            raise ValueError(f"delay_limit and delay_window must be >= 1, got {delay_limit}, {delay_window}")
        n = limits.n_axes
        if not 1 <= n <= 12:
            raise LimitError(f"{name}: RSI carries 1..12 axes (A1..A6, E1..E6), the robot model has {n}")
        self.host, self.port = host, int(port)
        self.cycle_ms = cycle_ms
        self.dt = cycle_ms / 1000.0
        self.timeout_cycles = timeout_cycles
        self.delay_limit, self.delay_window = int(delay_limit), int(delay_window)
        self.connect_timeout = check_timeout(connect_timeout)
        self.sen_type = sen_type
        self.rt_priority = int(rt_priority)
        self.max_deviation_rad = float(max_deviation_rad)
        self.switch_interval_s = switch_interval_s
        v = np.asarray(limits.max_velocity_rad_s, dtype=float)
        a = np.asarray(limits.max_acceleration_rad_s2, dtype=float)
        self.max_jerk_rad_s3 = default_jerk(v, a) if max_jerk_rad_s3 is None else np.asarray(max_jerk_rad_s3, float)
        # per-cycle guard, degrees per cycle
        self._g_step = np.degrees(v) * self.dt * (1 + GUARD_SLACK) + 1e-7
        self._g_acc = np.degrees(a) * self.dt**2 * (1 + GUARD_SLACK) + 2e-7
        self._lo_deg = np.degrees(np.asarray(limits.lower_rad, dtype=float))
        self._hi_deg = np.degrees(np.asarray(limits.upper_rad, dtype=float))
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._first = threading.Event()
        # state owned by the real-time thread (read by others as whole-object snapshots)
        self._latest = None  # (host_time, ipoc, actual_deg tuple, command_deg array, ref_deg array)
        self._hold = np.zeros(n)  # AK in force, degrees
        self._prev = np.zeros(n)  # previous two answers, for the acceleration guard
        self._prev2 = np.zeros(n)
        self._ref_deg: np.ndarray | None = None  # ASPos of this session
        self._session = 0
        self._n_robot = 0
        self._n_ext = 0
        self._formatter: SenFormatter | None = None
        self._motion: _Motion | None = None
        self._pending: _Motion | None = None
        self._stop_req = False
        self._stop_flag = False
        self._stop_sent = threading.Event()
        self._session_ended = False
        self._fault: DriverError | None = None
        self._rt_ok = False
        self._axis_error: str | None = None
        # statistics (preallocated rings)
        self._W = int(stats_window)
        self._lat = np.zeros(self._W)
        self._rx = np.zeros(self._W)
        self._count = 0
        self._late = 0
        self._gaps = 0
        self._malformed = 0
        self._restarts = 0
        self._clamps = 0
        self._delay_ring = np.zeros(self.delay_window, dtype=np.int64)
        self._delay_n = 0
        self._last_delay: int | None = None
        self._ipoc_step: int | None = None

    # -- construction from a URL --------------------------------------------------------------

    _URL_OPTIONS = {
        "cycle_ms": int,
        "timeout_cycles": int,
        "delay_limit": int,
        "delay_window": int,
        "connect_timeout": float,
        "sen_type": str,
        "rt_priority": int,
        "max_speed": float,
        "max_state_age_s": float,
        "name": str,
    }

    @classmethod
    def from_url(cls, url: str, *, limits: JointLimits, **overrides) -> "RsiCommander":
        """``rsi://HOST:PORT?cycle_ms=4&timeout_cycles=25&…`` (options: see ``_URL_OPTIONS``)."""
        parts = urlsplit(url)
        if parts.scheme != "rsi":
            raise ValueError(f"RSI commander URL must start with rsi://, got {url!r}")
        try:
            port = parts.port or DEFAULT_PORT
        except ValueError as exc:
            raise ValueError(f"bad port in {url!r}: {exc}") from exc
        kwargs: dict = {"host": parts.hostname or "0.0.0.0", "port": port}
        for key, value in parse_qsl(parts.query, keep_blank_values=True):
            if key not in cls._URL_OPTIONS:
                raise ValueError(
                    f"unknown option {key!r} in {url!r}; allowed: {', '.join(sorted(cls._URL_OPTIONS))}"
                )
            try:
                kwargs[key] = cls._URL_OPTIONS[key](value)
            except ValueError as exc:
                raise ValueError(f"option {key}={value!r} in {url!r}: {exc}") from exc
        kwargs.update(overrides)
        return cls(limits, **kwargs)

    # -- lifecycle ----------------------------------------------------------------------------

    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port); binds first if needed."""
        return self.bind()

    def bind(self) -> tuple[str, int]:
        """Open the UDP socket and start answering (``connect`` does it too); returns the bound
        address, so a controller (or fake) can be pointed at it before ``connect`` waits."""
        if self._sock is None:
            if self._thread is None:
                self._warm_up()  # before listening: no packet waits for it
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind((self.host, self.port))
            except OSError as exc:
                sock.close()
                raise ConnectionLostError(f"{self.name}: cannot listen on {self.host}:{self.port}: {exc}") from exc
            sock.settimeout(self.dt)
            self._sock = sock
        if self._thread is None:
            if self.switch_interval_s is not None and sys.getswitchinterval() > self.switch_interval_s:
                # A thread waking on a packet waits for the GIL up to the switch interval (5 ms by
                # default, longer than a 4 ms cycle): shorten it for the whole process.
                self.log.info(
                    "%s: interpreter switch interval %.1f ms -> %.2f ms for the real-time thread",
                    self.name,
                    sys.getswitchinterval() * 1e3,
                    self.switch_interval_s * 1e3,
                )
                sys.setswitchinterval(self.switch_interval_s)
            self._running.set()
            self._thread = threading.Thread(target=self._rt_main, name=f"{self.name}-rt", daemon=True)
            self._thread.start()
        return self._sock.getsockname()

    def _warm_up(self) -> None:
        """Run every code path of a cycle and of a move once before the exchange starts, so
        lazy imports and first-call costs (which hold the interpreter lock) happen now."""
        n = self.limits.n_axes
        f = SenFormatter(min(n, 6), max(n - 6, 0), self.sen_type)
        probe = (
            '<Rob Type="KUKA"><AIPos A1="0.0"/><ASPos A1="0.0"/><Delay D="0"/><IPOC>1</IPOC></Rob>'
        ).encode()
        parse_rob(probe)
        f.format(np.zeros(n), False, 1)
        v, a, j = scaled_limits(self.limits.max_velocity_rad_s, self.limits.max_acceleration_rad_s2, 0.5, self.max_jerk_rad_s3)
        lo = np.asarray(self.limits.lower_rad, dtype=float)
        traj = JointTrajectory.plan(lo, lo + 1e-3, v, a, j)
        traj.sample(np.arange(3) * self.dt)
        JointTrajectory.stop(lo, v * 0.5, a * 0.0, v, a, j).sample(0.0)
        np.percentile(np.zeros(4), [50, 99])

    def connect(self) -> None:
        """Listen, start the exchange thread and wait for the controller's first packet.

        Raises DeviceTimeoutError when no packet comes within ``connect_timeout`` and LimitError
        when the controller's axis count differs from the robot model's.
        """
        self.bind()
        if not self._first.wait(self.connect_timeout):
            host, port = self.bind()
            self.close()
            raise DeviceTimeoutError(
                f"{self.name}: no RSI packet within {self.connect_timeout:.3g} s on {host}:{port}; "
                "is the RSI program running and configured to send to this PC and port?"
            )
        if self._axis_error is not None:
            msg = self._axis_error
            self.close()
            raise LimitError(msg)
        st = self.link_stats()
        self.log.info(
            "%s: RSI link up from the controller: %d axes, session reference %s deg%s",
            self.name,
            self.limits.n_axes,
            np.round(self._ref_deg, 3).tolist() if self._ref_deg is not None else None,
            "" if st.realtime else " (no real-time priority)",
        )

    def close(self) -> None:
        """Stop any motion (within limits), then end the thread and close the socket."""
        if self._thread is not None and self._motion is not None and self._fresh():
            try:
                self._stop_motion(timeout=2.0)
            except DriverError as exc:
                self.log.warning("%s: stopping on close failed: %s", self.name, exc)
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # -- state --------------------------------------------------------------------------------

    def _fresh(self) -> bool:
        snap = self._latest
        return snap is not None and time.monotonic() - snap[0] <= self.max_state_age_s

    def joint_state(self) -> JointState:
        """Latest measured axes (AIPos then EIPos), radians. DeviceTimeoutError when stale."""
        snap = self._latest
        if snap is None:
            raise DeviceTimeoutError(f"{self.name}: no packet from the controller yet (call connect())")
        host_time, ipoc, actual, cmd, ref = snap
        age = time.monotonic() - host_time
        if age > self.max_state_age_s:
            fault = f" ({self._fault})" if self._fault is not None else ""
            raise DeviceTimeoutError(
                f"{self.name}: last controller packet is {age * 1e3:.0f} ms old "
                f"(allowed {self.max_state_age_s * 1e3:.0f} ms){fault}"
            )
        return JointState(
            position_rad=np.radians(np.asarray(actual, dtype=float)),
            device_time=ipoc * 1e-3,
            host_time=host_time,
            commanded_rad=np.radians(ref + cmd),
        )

    def link_stats(self) -> LinkStats:
        """Timing of the last cycles (see ``LinkStats``). Costs O(window); not for the RT path."""
        lat = self.latencies()
        rx = self._ordered(self._rx)
        n = lat.shape[0]
        per = np.diff(rx) if n > 1 else np.zeros(1)
        q = np.percentile(lat, [50, 99]) if n else np.zeros(2)
        return LinkStats(
            packets=self._count,
            window=n,
            period_mean_s=float(per.mean()),
            period_std_s=float(per.std()),
            period_max_s=float(per.max()),
            latency_p50_s=float(q[0]),
            latency_p99_s=float(q[1]),
            latency_max_s=float(lat.max()) if n else 0.0,
            late_answers=self._late,
            gaps=self._gaps,
            malformed=self._malformed,
            restarts=self._restarts,
            guard_clamps=self._clamps,
            delay=self._last_delay,
            realtime=self._rt_ok,
            notes=(f"controller Delay {self._last_delay}",),
        )

    def _ordered(self, ring: np.ndarray) -> np.ndarray:
        count = self._count
        if count <= self._W:
            return ring[:count].copy()
        i = count % self._W
        return np.concatenate([ring[i:], ring[:i]])

    def latencies(self) -> np.ndarray:
        """Answer latencies (s) of the last cycles, oldest first, shape (min(packets, window),)."""
        return self._ordered(self._lat)

    # -- motion -------------------------------------------------------------------------------

    def _raise_fault(self) -> None:
        fault, self._fault = self._fault, None
        if fault is not None:
            raise fault

    def _move_internal(self, start: JointState, target_rad: np.ndarray, speed: float, timeout: float) -> None:
        self._raise_fault()
        if self._session_ended:
            raise LimitError(f"{self.name}: the RSI session was ended with the Stop flag; restart the RSI program")
        if self._motion is not None or self._pending is not None:
            raise LimitError(f"{self.name}: a motion is already running")
        snap = self._latest
        _, _, actual, cmd, ref = snap
        commanded = np.radians(ref + cmd)
        deviation = np.abs(start.position_rad - commanded)
        if np.max(deviation) > self.max_deviation_rad:
            i = int(np.argmax(deviation))
            raise LimitError(
                f"{self.name}: measured and commanded positions disagree by {math.degrees(deviation[i]):.3f}° "
                f"on axis {i + 1} (allowed {math.degrees(self.max_deviation_rad):.3f}°); wait until settled"
            )
        v, a, j = scaled_limits(
            self.limits.max_velocity_rad_s, self.limits.max_acceleration_rad_s2, speed, self.max_jerk_rad_s3
        )
        traj = JointTrajectory.plan(commanded, target_rad, v, a, j)
        m = max(1, math.ceil(traj.duration / self.dt - 1e-9))
        wall = m * self.dt
        if wall + 10 * self.dt > timeout:
            raise LimitError(
                f"{self.name}: the move takes {wall:.3f} s at speed {speed}, longer than the timeout {timeout:.3f} s"
            )
        pos, _, _ = traj.sample(self.dt * np.arange(1, m + 1))
        pos[-1] = target_rad
        rows = np.degrees(pos) - ref
        motion = _Motion(rows, traj, self._session, ref)
        self.log.info(
            "%s: moving to %s deg in %.3f s (%d cycles, speed %.2f)",
            self.name,
            np.round(np.degrees(target_rad), 3).tolist(),
            traj.duration,
            m,
            speed,
        )
        self._pending = motion
        if not motion.done.wait(timeout):
            self._pending = None  # never adopted: nothing to stop
            self._stop_req = True
            motion.done.wait(2.0)
            raise DeviceTimeoutError(f"{self.name}: move not completed within {timeout:.3g} s; stopped")
        if motion.error is not None:
            if self._fault is motion.error:
                self._fault = None  # reported here, once
            raise motion.error

    def stop(self, *, end_session: bool = True, timeout: float = 5.0) -> None:
        """Decelerate within limits (a jerk-limited stop planned from the current velocity and
        acceleration), then send the Stop flag (``end_session``) so the RSI program ends."""
        if self._thread is None:
            return
        self._stop_motion(timeout)
        if end_session:
            self._stop_sent.clear()
            self._stop_flag = True
            self.log.info("%s: robot at rest; sending the Stop flag", self.name)
            if not self._stop_sent.wait(min(timeout, 20 * self.dt)):
                self.log.warning("%s: no controller packet to carry the Stop flag", self.name)

    def _stop_motion(self, timeout: float) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.done.set()  # a move that had not started yet ends without moving
        motion = self._motion
        if motion is None:
            return
        self._stop_req = True
        deadline = time.monotonic() + timeout
        while self._motion is not None and time.monotonic() < deadline:
            m = self._motion
            if m is not None:
                m.done.wait(0.05)
        if self._motion is not None:
            raise DeviceTimeoutError(f"{self.name}: stop not completed within {timeout:.3g} s (no packets?)")

    # -- the real-time thread -----------------------------------------------------------------

    def _set_realtime(self) -> None:
        if self.rt_priority <= 0:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
            self._rt_ok = True
            self.log.info("%s: exchange thread runs SCHED_FIFO priority %d", self.name, self.rt_priority)
        except (PermissionError, OSError, AttributeError) as exc:
            self.log.warning(
                "%s: cannot give the RSI exchange thread SCHED_FIFO priority %d (%s); it runs with normal "
                "priority and may answer late under load. Grant CAP_SYS_NICE and an RLIMIT_RTPRIO "
                "(systemd: AmbientCapabilities=CAP_SYS_NICE, LimitRTPRIO=%d) to fix.",
                self.name,
                self.rt_priority,
                exc,
                self.rt_priority,
            )

    def _rt_main(self) -> None:
        self._set_realtime()
        self._drain()
        try:
            self._rt_loop()
        except OSError as exc:
            if self._running.is_set():
                self.log.error("%s: RSI socket failed: %s", self.name, exc)
                self._abort(ConnectionLostError(f"{self.name}: RSI socket failed: {exc}"))

    def _drain(self) -> None:
        """Discard packets queued before the thread ran: their cycle is over, answering them
        now would only be late; the next packet starts the exchange."""
        sock = self._sock
        sock.setblocking(False)
        try:
            while True:
                sock.recvfrom(4096)
        except (BlockingIOError, InterruptedError):
            pass
        finally:
            sock.settimeout(self.dt)

    def _abort(self, error: DriverError) -> None:
        """Record a fault; a running motion ends with it and is turned into a stop."""
        if self._fault is None:
            self._fault = error
        m = self._motion
        if m is not None and m.error is None:
            m.error = error
            self._stop_req = True  # the motion becomes a stop; its waiter is told now
            m.done.set()
        p = self._pending
        if p is not None:
            p.error = error
            p.done.set()
            self._pending = None

    def _start_session(self, rob, actual) -> None:
        """First packet of an RSI session: reference = ASPos (or AIPos), hold = current offset."""
        n = len(actual)
        if n != self.limits.n_axes:
            self._axis_error = (
                f"{self.name}: the controller reports {len(rob.axis_actual_deg)} robot axes and "
                f"{len(rob.external_actual_deg)} external axes, the robot model has {self.limits.n_axes}"
            )
            return
        self._axis_error = None
        if rob.axis_setpoint_deg is not None and (
            rob.external_setpoint_deg is not None or not rob.external_actual_deg
        ):
            ref = np.asarray(rob.axis_setpoint_deg + (rob.external_setpoint_deg or ()), dtype=float)
        else:
            ref = np.asarray(actual, dtype=float)
        self._n_robot, self._n_ext = len(rob.axis_actual_deg), len(rob.external_actual_deg)
        self._formatter = SenFormatter(self._n_robot, self._n_ext, self.sen_type)
        self._ref_deg = ref
        hold = np.asarray(actual, dtype=float) - ref  # keep the robot where it is
        self._hold = hold
        self._prev = hold.copy()
        self._prev2 = hold.copy()
        self._session += 1
        self._stop_flag = False
        self._session_ended = False
        self._delay_n = 0

    def _rt_loop(self) -> None:  # noqa: C901 - one flat real-time loop on purpose
        sock = self._sock
        stamped = enable_rx_timestamps(sock)
        silence_limit = self.timeout_cycles * self.dt
        last_rx = time.monotonic()
        last_ipoc = -1
        step_deg, acc_deg = self._g_step, self._g_acc
        W = self._W
        while self._running.is_set():
            try:
                data, addr, arrived = recv_stamped(sock, 4096, stamped)
            except TimeoutError:
                if self._latest is not None and time.monotonic() - last_rx > silence_limit:
                    if self._motion is not None or self._pending is not None:
                        self._abort(
                            DeviceTimeoutError(
                                f"{self.name}: no packet from the controller for "
                                f"{(time.monotonic() - last_rx) * 1e3:.0f} ms (limit {self.timeout_cycles} "
                                f"cycles); the controller stopped RSI (last Delay {self._last_delay})"
                            )
                        )
                continue
            t_rx = time.monotonic()
            try:
                rob = parse_rob(data)
            except ProtocolError:
                self._malformed += 1
                continue
            actual = rob.axis_actual_deg + rob.external_actual_deg
            ipoc = rob.ipoc
            # -- session bookkeeping: first packet, restart, gaps
            restarted = False
            if self._ref_deg is None:
                self._start_session(rob, actual)
                if self._axis_error is not None:
                    self._first.set()
                    continue
            else:
                new_ref = rob.axis_setpoint_deg
                if ipoc == last_ipoc and len(actual) == len(self._ref_deg):
                    # the controller repeated a packet (it got no answer): same answer again,
                    # the trajectory does not advance
                    sock.sendto(self._formatter.format(self._prev, self._stop_flag, ipoc), addr)
                    self._latest = (t_rx, ipoc, actual, self._prev, self._ref_deg)
                    continue
                if (
                    ipoc < last_ipoc
                    or len(actual) != len(self._ref_deg)
                    or (new_ref is not None and any(abs(x - y) > 1e-6 for x, y in zip(new_ref, self._ref_deg)))
                ):
                    restarted = True
            if restarted:
                self._restarts += 1
                if self._motion is not None:
                    err = DeviceFaultError(
                        f"{self.name}: the controller restarted RSI during a motion (IPOC {last_ipoc} → {ipoc}); "
                        "motion abandoned, corrections reset"
                    )
                    m = self._motion
                    m.error = err
                    self._motion = None
                    m.done.set()
                    self._fault = err
                self._start_session(rob, actual)
                self._ipoc_step = None
                if self._axis_error is not None:
                    self._abort(LimitError(self._axis_error))
                    continue
            elif last_ipoc >= 0:
                diff = ipoc - last_ipoc
                if self._ipoc_step is None or diff < self._ipoc_step:
                    self._ipoc_step = diff
                elif diff > self._ipoc_step:
                    self._gaps += diff // self._ipoc_step - 1
            last_ipoc = ipoc
            last_rx = t_rx
            # -- controller-reported lateness
            if rob.delay is not None:
                ring = self._delay_ring
                i = self._delay_n % self.delay_window
                past = ring[i] if self._delay_n >= self.delay_window else ring[0]
                ring[i] = rob.delay
                self._delay_n += 1
                self._last_delay = rob.delay
                if rob.delay - past > self.delay_limit and self._fault is None:
                    self._abort(
                        DeviceFaultError(
                            f"{self.name}: the controller counted {rob.delay - past} late answers in the last "
                            f"{min(self._delay_n, self.delay_window)} cycles (Delay D={rob.delay}, "
                            f"limit {self.delay_limit}); motion stopped"
                        )
                    )
            # -- next command
            m = self._motion
            if m is None and self._pending is not None:
                p = self._pending
                self._pending = None
                if p.session != self._session:
                    p.error = DeviceFaultError(f"{self.name}: RSI restarted before the motion began; re-plan")
                    p.done.set()
                elif not self._stop_req:
                    self._motion = m = p
            if m is not None and self._stop_req and not m.is_stop:
                m = self._plan_stop(m)
            if self._stop_req and m is None:
                self._stop_req = False
            if m is not None:
                cmd = m.rows_deg[m.k]
                m.k += 1
            else:
                cmd = self._hold
            # -- per-cycle guard: position, velocity and acceleration per cycle
            prev = self._prev
            d1 = cmd - prev
            d2 = d1 - (prev - self._prev2)
            pos = self._ref_deg + cmd
            if (np.abs(d1) > step_deg).any() or (np.abs(d2) > acc_deg).any() or (pos < self._lo_deg).any() or (
                pos > self._hi_deg
            ).any():
                cmd = self._clamp(cmd)
                self._clamps += 1
                if m is not None and m.error is None:
                    m.traj = None  # the stream left the plan: stop from what was actually sent
                    self._abort(
                        LimitError(f"{self.name}: a command exceeded the per-cycle limits; clamped and stopped")
                    )
            stop_flag = self._stop_flag
            reply = self._formatter.format(cmd, stop_flag, ipoc)
            sock.sendto(reply, addr)
            t_tx = time.time()
            if stop_flag:
                self._session_ended = True
                self._stop_sent.set()
            # -- bookkeeping after the answer is out
            self._prev2 = prev
            self._prev = cmd
            self._hold = cmd
            if m is not None and m.k >= len(m.rows_deg):
                self._motion = None
                if m.is_stop:
                    self._stop_req = False
                m.done.set()
            c = self._count % W
            self._lat[c] = t_tx - arrived
            self._rx[c] = arrived
            self._count += 1
            if t_tx - arrived > self.dt:
                self._late += 1
            self._latest = (t_rx, ipoc, actual, cmd, self._ref_deg)
            if not self._first.is_set():
                self._first.set()

    def _plan_stop(self, m: _Motion) -> _Motion:
        """Replace motion ``m`` by a stop planned from the state of its last answered row."""
        dt = self.dt
        if m.traj is not None and m.k > 0:
            p, v, a = m.traj.sample(m.k * dt)
        else:  # emergency: state from the last answers
            p = np.radians(self._ref_deg + self._prev)
            v = np.radians(self._prev - self._prev2) / dt
            a = np.zeros_like(v)
        vmax = np.asarray(self.limits.max_velocity_rad_s, dtype=float)
        amax = np.asarray(self.limits.max_acceleration_rad_s2, dtype=float)
        stop = JointTrajectory.stop(p, v, a, vmax, amax, np.maximum(self.max_jerk_rad_s3, 1e-9))
        n_rows = max(1, math.ceil(stop.duration / dt - 1e-9))
        pos, _, _ = stop.sample(dt * np.arange(1, n_rows + 1))
        rows = np.degrees(pos) - self._ref_deg
        s = _Motion(rows, stop, m.session, m.ref_rad, is_stop=True)
        s.done = m.done  # whoever waits for the move sees the end of the stop
        s.error = m.error
        self._motion = s
        return s

    def _clamp(self, cmd: np.ndarray) -> np.ndarray:
        """The closest command to ``cmd`` that keeps velocity and acceleration per cycle in limits."""
        prev, prev2 = self._prev, self._prev2
        v_prev = prev - prev2
        lo = np.maximum(-self._g_step, v_prev - self._g_acc) * (1 - 2 * GUARD_SLACK)
        hi = np.minimum(self._g_step, v_prev + self._g_acc) * (1 - 2 * GUARD_SLACK)
        return prev + np.clip(cmd - prev, np.minimum(lo, hi), np.maximum(lo, hi))

