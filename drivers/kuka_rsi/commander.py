"""``RsiCommander``: the PC side of KUKA RSI, a real-time answering process plus safe joint moves.

The controller sends ``<Rob>`` every interpolation cycle (4 or 12 ms) and the PC must answer each
packet, to its source address and echoing its IPOC, within the cycle. A process of its own does
only that (``drivers/kuka_rsi/realtime.py`` run by ``drivers/exchange.py``): receive, parse,
take the next row of a precomputed correction table, check it against the per-cycle limits,
format, send. Everything slow (planning, sampling, waiting, logging) happens here, in the
caller's process, before the motion is handed over; the GIL, the garbage collector and the load
of this process cannot delay an answer.

Corrections are ``RSI_ON(#ABSOLUTE)`` axis corrections ``AK``: the total offset from the start
position ``ASPos`` (degrees). The trajectory advances exactly one cycle per packet answered, so the
command stream obeys the limits cycle by cycle whatever the timing jitter or packet loss; each row
is additionally checked in the exchange process (position, velocity, acceleration per cycle) and
a violating row is clamped and the motion stopped.

Real-time notes: the exchange process asks for SCHED_FIFO and locked memory (a warning says how
to grant them when not permitted), warms every code path up and freezes its garbage collector
before the first packet; lateness is measured in that process, from the kernel's arrival stamp
to the answer's send. If this process dies, the exchange process stops a running motion within
the limits, holds, sends the Stop flag and exits.

Faults end the motion with a clear error: no packet for ``timeout_cycles`` cycles
(``DeviceTimeoutError``), the controller's ``Delay`` growing by more than ``delay_limit`` within
``delay_window`` cycles or the RSI session restarting mid-motion (``DeviceFaultError``).
"""

from __future__ import annotations

import itertools
import math
import socket
import threading
import time
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import DEFAULT_LIMIT_MARGIN_RAD, CommanderBase, check_timeout
from drivers.errors import ConnectionLostError, DeviceTimeoutError, DriverError, LimitError
from drivers.exchange import ExchangeProcess, ring_in_order
from drivers.kuka_rsi import realtime
from drivers.protocols import JointLimits, JointState, LinkStats
from drivers.trajectory import JointTrajectory, default_jerk, scaled_limits

__all__ = ["RsiCommander", "LinkStats"]

DEFAULT_PORT = 49152


class _Waiter:
    """The main process's side of one motion: set when the exchange process reports it done."""

    __slots__ = ("done", "error")

    def __init__(self) -> None:
        self.done = threading.Event()
        self.error: DriverError | None = None


class RsiCommander(CommanderBase):
    """Joint commander over KUKA RSI. See the module docstring.

    limits: the robot model's limits; its axis count must equal the controller's (A1..A6 plus
    external E1..Em). host, port: where to listen for the controller (``0.0.0.0:49152``).
    cycle_ms: 4 (``#IPO_FAST``) or 12 (``#IPO``). timeout_cycles: silence that ends a motion.
    delay_limit / delay_window: tolerated growth of the controller's late count. rt_priority:
    SCHED_FIFO priority for the exchange process (0: don't try). max_deviation_rad: largest
    allowed difference between the measured and the commanded position when a move starts.
    stats_window: cycles kept in the latency ring. orphan_hold_s: how long the exchange process
    holds the stopped robot after this process died before it sends the Stop flag.
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
        orphan_hold_s: float = 0.5,
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
        v = np.asarray(limits.max_velocity_rad_s, dtype=float)
        a = np.asarray(limits.max_acceleration_rad_s2, dtype=float)
        self.max_jerk_rad_s3 = default_jerk(v, a) if max_jerk_rad_s3 is None else np.asarray(max_jerk_rad_s3, float)
        if not (isinstance(stats_window, int) and stats_window >= 2):
            raise ValueError(f"stats_window must be an integer >= 2, got {stats_window!r}")
        self._W = stats_window
        self.orphan_hold_s = float(orphan_hold_s)
        self._sock: socket.socket | None = None  # bound here, owned by the exchange process once started
        self._address: tuple[str, int] | None = None
        self._exchange: ExchangeProcess | None = None
        self._first = threading.Event()
        self._stop_sent = threading.Event()
        self._axis_error: str | None = None
        self._fault: DriverError | None = None
        self._waiters: dict[int, _Waiter] = {}
        self._ids = itertools.count(1)
        self._active: int | None = None  # id of the motion handed over and not reported done
        self._lock = threading.Lock()
        self._final_stats: LinkStats | None = None  # the figures of the last exchange, after close

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

    @property
    def exchange_pid(self) -> int | None:
        """Process id of the exchange process (None before ``bind``): for ``chrt -p``, ``top``."""
        return None if self._exchange is None else self._exchange.pid

    def bind(self) -> tuple[str, int]:
        """Open the UDP socket and start the exchange process answering on it (``connect`` does
        it too); returns the bound address, so a controller (or fake) can be pointed at it
        before ``connect`` waits. Blocks until the exchange process is ready (under a second on
        an idle machine)."""
        if self._exchange is None:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind((self.host, self.port))
            except OSError as exc:
                sock.close()
                raise ConnectionLostError(f"{self.name}: cannot listen on {self.host}:{self.port}: {exc}") from exc
            self._address = sock.getsockname()
            self._first.clear()
            self._axis_error = None
            self._final_stats = None
            lim = self.limits
            options = dict(
                n_axes=lim.n_axes, dt=self.dt, timeout_cycles=self.timeout_cycles, delay_limit=self.delay_limit,
                delay_window=self.delay_window, sen_type=self.sen_type,
                lower_rad=np.asarray(lim.lower_rad, float), upper_rad=np.asarray(lim.upper_rad, float),
                max_velocity_rad_s=np.asarray(lim.max_velocity_rad_s, float),
                max_acceleration_rad_s2=np.asarray(lim.max_acceleration_rad_s2, float),
                max_jerk_rad_s3=self.max_jerk_rad_s3, window=self._W, orphan_hold_s=self.orphan_hold_s,
            )
            ex = ExchangeProcess(self.name, realtime.layout(lim.n_axes, self._W), realtime.RsiLoop, options,
                                 self._on_event, rt_priority=self.rt_priority, log=self.log)
            self._exchange = ex
            try:
                ex.start(sock)
            except RuntimeError as exc:
                self._exchange = None
                raise ConnectionLostError(str(exc)) from exc
        return self._address

    def _on_event(self, event: tuple) -> None:
        """Reader thread: one event from the exchange process (see ``realtime``)."""
        kind = event[0]
        if kind == "first":
            self._first.set()
        elif kind == "axis_error":
            self._axis_error = event[1]
            self._first.set()
        elif kind == "done":
            with self._lock:
                w = self._waiters.pop(event[1], None)
                if self._active == event[1]:
                    self._active = None
            if w is not None:
                w.error = event[2]
                w.done.set()
        elif kind == "fault":
            self._fault = event[1]
        elif kind == "stop_sent":
            self._stop_sent.set()
        elif kind == "crashed":
            err = ConnectionLostError(f"{self.name}: the RSI exchange process failed: {event[1]}")
            self._fault = err
            with self._lock:
                waiters, self._waiters, self._active = list(self._waiters.values()), {}, None
            for w in waiters:
                w.error = err
                w.done.set()

    def connect(self) -> None:
        """Listen, start the exchange process and wait for the controller's first packet.

        Raises DeviceTimeoutError when no packet comes within ``connect_timeout`` and LimitError
        when the controller's axis count differs from the robot model's.
        """
        host, port = self.bind()
        if not self._first.wait(self.connect_timeout):
            self.close()
            raise DeviceTimeoutError(
                f"{self.name}: no RSI packet within {self.connect_timeout:.3g} s on {host}:{port}; "
                "is the RSI program running and configured to send to this PC and port?"
            )
        if self._axis_error is not None:
            msg = self._axis_error
            self.close()
            raise LimitError(msg)
        snap = self._snapshot()
        self.log.info(
            "%s: RSI link up from the controller: %d axes, session reference %s deg; exchange process %s: %s",
            self.name,
            self.limits.n_axes,
            None if snap is None else np.round(snap["ref"], 3).tolist(),
            self._exchange.pid,
            self._exchange.realtime,
        )

    def close(self) -> None:
        """Stop any motion (within limits), then end the exchange process (it closes the socket)."""
        if self._exchange is None:
            return
        if self._busy() and self._fresh():
            try:
                self._stop_motion(timeout=2.0)
            except DriverError as exc:
                self.log.warning("%s: stopping on close failed: %s", self.name, exc)
        self._final_stats = self.link_stats()
        self._exchange.close()
        self._exchange = None

    # -- state --------------------------------------------------------------------------------

    def _snapshot(self, *extra: str) -> dict | None:
        """The latest packet's state from the exchange process (None before the first)."""
        ex = self._exchange
        state = None if ex is None else ex.state
        if state is None:
            return None
        try:
            st = state.read(realtime.SCALARS + ("actual", "cmd", "ref") + extra)
        except ConnectionError:  # closed meanwhile by another thread
            return None
        if not st["has_state"][0]:
            return None
        return st

    def _busy(self) -> bool:
        snap = self._snapshot()
        return self._active is not None or (snap is not None and bool(snap["busy"][0]))

    def _fresh(self) -> bool:
        snap = self._snapshot()
        return snap is not None and time.monotonic() - snap["t_rx"][0] <= self.max_state_age_s

    def joint_state(self) -> JointState:
        """Latest measured axes (AIPos then EIPos), radians. DeviceTimeoutError when stale."""
        snap = self._snapshot()
        if snap is None:
            raise DeviceTimeoutError(f"{self.name}: no packet from the controller yet (call connect())")
        host_time = float(snap["t_rx"][0])
        age = time.monotonic() - host_time
        if age > self.max_state_age_s:
            fault = f" ({self._fault})" if self._fault is not None else ""
            raise DeviceTimeoutError(
                f"{self.name}: last controller packet is {age * 1e3:.0f} ms old "
                f"(allowed {self.max_state_age_s * 1e3:.0f} ms){fault}"
            )
        return JointState(
            position_rad=np.radians(snap["actual"]),
            device_time=int(snap["ipoc"][0]) * 1e-3,
            host_time=host_time,
            commanded_rad=np.radians(snap["ref"] + snap["cmd"]),
        )

    def link_stats(self) -> LinkStats:
        """Timing of the last cycles, as measured by the exchange process (see ``LinkStats``).
        Costs O(window); not for a tight loop."""
        ex = self._exchange
        if ex is None and self._final_stats is not None:
            return self._final_stats
        try:
            snap = None if ex is None or ex.state is None else ex.state.read(realtime.SCALARS + ("lat", "rx"))
        except ConnectionError:  # closed meanwhile by another thread
            snap = None
            if self._final_stats is not None:
                return self._final_stats
        if snap is None:
            count, lat, rx = 0, np.zeros(0), np.zeros(0)
            snap = dict.fromkeys(realtime.SCALARS, np.zeros(1))
        else:
            count = int(snap["count"][0])
            lat, rx = ring_in_order(snap["lat"], count), ring_in_order(snap["rx"], count)
        n = lat.shape[0]
        per = np.diff(rx) if n > 1 else np.zeros(1)
        q = np.percentile(lat, [50, 99]) if n else np.zeros(2)
        delay = int(snap["delay"][0]) if snap["has_delay"][0] else None
        return LinkStats(
            packets=count,
            window=n,
            period_mean_s=float(per.mean()),
            period_std_s=float(per.std()),
            period_max_s=float(per.max()),
            latency_p50_s=float(q[0]),
            latency_p99_s=float(q[1]),
            latency_max_s=float(lat.max()) if n else 0.0,
            late_answers=int(snap["late"][0]),
            gaps=int(snap["gaps"][0]),
            malformed=int(snap["malformed"][0]),
            restarts=int(snap["restarts"][0]),
            guard_clamps=int(snap["clamps"][0]),
            delay=delay,
            realtime=ex is not None and ex.realtime.startswith("SCHED_FIFO"),
            notes=(f"controller Delay {delay}", f"exchange process: {ex.realtime if ex else 'not running'}"),
        )

    def latencies(self) -> np.ndarray:
        """Answer latencies (s) of the last cycles, oldest first, shape (min(packets, window),),
        measured in the exchange process (kernel arrival stamp to the answer's send)."""
        return self.answer_log()[2]

    def answer_log(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(packets, arrived, latency)``: packets answered so far and, for the last
        min(packets, stats_window) of them, oldest first, each shape (m,), the kernel's arrival
        stamp (wall-clock s, ``time.time`` scale) and the answer latency (s) — to place late
        answers in time (benches poll it to keep more than the ring holds)."""
        ex = self._exchange
        try:
            snap = None if ex is None or ex.state is None else ex.state.read(("count", "lat", "rx"))
        except ConnectionError:  # closed meanwhile by another thread
            snap = None
        if snap is None:
            return 0, np.zeros(0), np.zeros(0)
        count = int(snap["count"][0])
        return count, ring_in_order(snap["rx"], count), ring_in_order(snap["lat"], count)

    # -- motion -------------------------------------------------------------------------------

    def _raise_fault(self) -> None:
        fault, self._fault = self._fault, None
        if fault is not None:
            raise fault

    def _move_internal(self, start: JointState, target_rad: np.ndarray, speed: float, timeout: float) -> None:
        self._raise_fault()
        snap = self._snapshot()
        if snap is None:
            raise DeviceTimeoutError(f"{self.name}: no packet from the controller yet (call connect())")
        if snap["session_ended"][0]:
            raise LimitError(f"{self.name}: the RSI session was ended with the Stop flag; restart the RSI program")
        if self._busy():
            raise LimitError(f"{self.name}: a motion is already running")
        ref = snap["ref"]
        commanded = np.radians(ref + snap["cmd"])
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
        self.log.info(
            "%s: moving to %s deg in %.3f s (%d cycles, speed %.2f)",
            self.name,
            np.round(np.degrees(target_rad), 3).tolist(),
            traj.duration,
            m,
            speed,
        )
        motion_id = next(self._ids)
        waiter = _Waiter()
        with self._lock:
            self._waiters[motion_id] = waiter
            self._active = motion_id
        try:
            self._exchange.request("move", motion_id, rows, traj, int(snap["session"][0]))
        except ConnectionError as exc:
            with self._lock:
                self._waiters.pop(motion_id, None)
                self._active = None
            raise ConnectionLostError(str(exc)) from exc
        if not waiter.done.wait(timeout):
            self._request("stop")
            waiter.done.wait(2.0)
            raise DeviceTimeoutError(f"{self.name}: move not completed within {timeout:.3g} s; stopped")
        if waiter.error is not None:
            if self._fault is waiter.error:
                self._fault = None  # reported here, once
            raise waiter.error

    def _request(self, *msg) -> None:
        try:
            self._exchange.request(*msg)
        except (ConnectionError, AttributeError) as exc:
            raise ConnectionLostError(f"{self.name}: the RSI exchange process is not running ({exc})") from exc

    def stop(self, *, end_session: bool = True, timeout: float = 5.0) -> None:
        """Decelerate within limits (a jerk-limited stop planned from the current velocity and
        acceleration), then send the Stop flag (``end_session``) so the RSI program ends."""
        if self._exchange is None:
            return
        self._stop_motion(timeout)
        if end_session:
            self._stop_sent.clear()
            self.log.info("%s: robot at rest; sending the Stop flag", self.name)
            self._request("end_session")
            if not self._stop_sent.wait(max(min(timeout, 20 * self.dt), 0.5)):
                self.log.warning("%s: no controller packet to carry the Stop flag", self.name)

    def _stop_motion(self, timeout: float) -> None:
        """Ask the exchange process to stop the current motion and wait until it is at rest."""
        with self._lock:
            active = self._active
            waiter = None if active is None else self._waiters.get(active)
        self._request("stop")
        deadline = time.monotonic() + timeout
        if waiter is not None:
            waiter.done.wait(timeout)
        # an aborted motion reports done at once and then stops: wait for the stop's end too
        while self._busy() and time.monotonic() < deadline:
            time.sleep(0.01)
        if self._busy():
            raise DeviceTimeoutError(f"{self.name}: stop not completed within {timeout:.3g} s (no packets?)")
