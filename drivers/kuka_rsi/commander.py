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

The commander holds the options and the ``JointCommander`` calls; ``drivers/kuka_rsi/link.py``
(``RsiLink``) holds the exchange process and what it reports, ``drivers/kuka_rsi/motion.py``
(``plan_move``) the checks against the verified state and the correction table of a move.

Faults end the motion with a clear error: no packet for ``timeout_cycles`` cycles
(``DeviceTimeoutError``), the controller's ``Delay`` growing by more than ``delay_limit`` within
``delay_window`` cycles or the RSI session restarting mid-motion (``DeviceFaultError``).
"""

from __future__ import annotations

import math
import time
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import DEFAULT_LIMIT_MARGIN_RAD, CommanderBase, check_timeout
from drivers.errors import DeviceTimeoutError, DriverError, LimitError, NotReadyError
from drivers.kuka_rsi.link import RsiLink
from drivers.kuka_rsi.motion import plan_move
from drivers.protocols import JointLimits, JointState, LinkStats
from drivers.trajectory import default_jerk

__all__ = ["RsiCommander", "LinkStats"]

DEFAULT_PORT = 49152


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
        self._link = RsiLink(name, self.log, n_axes=n, window=stats_window, rt_priority=self.rt_priority)

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
        return None if self._link.exchange is None else self._link.exchange.pid

    @property
    def _exchange(self):
        """The running ``ExchangeProcess`` (None before ``bind``), for its ``startup`` figures."""
        return self._link.exchange

    def bind(self) -> tuple[str, int]:
        """Open the UDP socket and start the exchange process answering on it (``connect`` does
        it too); returns the bound address, so a controller (or fake) can be pointed at it
        before ``connect`` waits. Blocks until the exchange process is ready (under a second on
        an idle machine)."""
        if self._link.exchange is not None:
            return self._link.address
        lim = self.limits
        options = dict(
            n_axes=lim.n_axes, dt=self.dt, timeout_cycles=self.timeout_cycles, delay_limit=self.delay_limit,
            delay_window=self.delay_window, sen_type=self.sen_type,
            lower_rad=np.asarray(lim.lower_rad, float), upper_rad=np.asarray(lim.upper_rad, float),
            max_velocity_rad_s=np.asarray(lim.max_velocity_rad_s, float),
            max_acceleration_rad_s2=np.asarray(lim.max_acceleration_rad_s2, float),
            max_jerk_rad_s3=self.max_jerk_rad_s3, window=self._W, orphan_hold_s=self.orphan_hold_s,
        )
        return self._link.start(self.host, self.port, options)

    def connect(self) -> None:
        """Listen, start the exchange process and wait for the controller's first packet.

        Raises DeviceTimeoutError when no packet comes within ``connect_timeout`` and LimitError
        when the controller's axis count differs from the robot model's.
        """
        host, port = self.bind()
        if not self._link.first.wait(self.connect_timeout):
            self.close()
            raise DeviceTimeoutError(
                f"{self.name}: no RSI packet within {self.connect_timeout:.3g} s on {host}:{port}; "
                "is the RSI program running and configured to send to this PC and port?"
            )
        if self._link.axis_error is not None:
            msg = self._link.axis_error
            self.close()
            raise LimitError(msg)
        snap = self._link.snapshot()
        self.log.info(
            "%s: RSI link up from the controller: %d axes, session reference %s deg; exchange process %s: %s",
            self.name,
            self.limits.n_axes,
            None if snap is None else np.round(snap["ref"], 3).tolist(),
            self._link.exchange.pid,
            self._link.exchange.realtime,
        )

    def close(self) -> None:
        """Stop any motion (within limits), then end the exchange process (it closes the socket)."""
        if self._link.exchange is None:
            return
        if self._link.busy() and self._link.fresh(self.max_state_age_s):
            try:
                self._link.stop_motion(timeout=2.0)
            except DriverError as exc:
                self.log.warning("%s: stopping on close failed: %s", self.name, exc)
        self._link.close()

    # -- state --------------------------------------------------------------------------------

    def joint_state(self) -> JointState:
        """Latest measured axes (AIPos then EIPos), radians. DeviceTimeoutError when stale."""
        snap = self._link.snapshot()
        if snap is None:
            raise DeviceTimeoutError(f"{self.name}: no packet from the controller yet (call connect())")
        host_time = float(snap["t_rx"][0])
        age = time.monotonic() - host_time
        if age > self.max_state_age_s:
            fault = f" ({self._link.fault})" if self._link.fault is not None else ""
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
        return self._link.link_stats()

    def latencies(self) -> np.ndarray:
        """Answer latencies (s) of the last cycles, oldest first, shape (min(packets, window),),
        measured in the exchange process (kernel arrival stamp to the answer's send)."""
        return self.answer_log()[2]

    def answer_log(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(packets, arrived, latency)``: packets answered so far and, for the last
        min(packets, stats_window) of them, oldest first, each shape (m,), the kernel's arrival
        stamp (wall-clock s, ``time.time`` scale) and the answer latency (s) — to place late
        answers in time (benches poll it to keep more than the ring holds)."""
        return self._link.answer_log()

    def ready(self) -> JointState:
        """The measured state when a move could start now: a fresh packet, the RSI session not
        ended with the Stop flag, no motion running; else NotReadyError saying why."""
        state = super().ready()
        snap = self._link.snapshot()
        if snap is not None and snap["session_ended"][0]:
            raise NotReadyError(f"{self.name}: the RSI session was ended with the Stop flag; restart the RSI program")
        if self._link.busy():
            raise NotReadyError(f"{self.name}: a motion is still running")
        return state

    # -- motion -------------------------------------------------------------------------------

    def _move_internal(self, start: JointState, target_rad: np.ndarray, speed: float, timeout: float) -> None:
        self._link.raise_fault()
        snap = self._link.snapshot()
        move = plan_move(snap, snap is not None and self._link.busy(), start.position_rad, target_rad, speed,
                         limits=self.limits, max_jerk_rad_s3=self.max_jerk_rad_s3,
                         max_deviation_rad=self.max_deviation_rad, dt=self.dt, timeout=timeout, name=self.name)
        self.log.info(
            "%s: moving to %s deg in %.3f s (%d cycles, speed %.2f)",
            self.name,
            np.round(np.degrees(target_rad), 3).tolist(),
            move.trajectory.duration,
            move.cycles,
            speed,
        )
        waiter = self._link.hand_over(move.rows, move.trajectory, move.session)
        if not waiter.done.wait(timeout):
            self._link.request("stop")
            waiter.done.wait(2.0)
            raise DeviceTimeoutError(f"{self.name}: move not completed within {timeout:.3g} s; stopped")
        if waiter.error is not None:
            self._link.reported(waiter.error)  # reported here, once
            raise waiter.error

    def stop(self, *, end_session: bool = True, timeout: float = 5.0) -> None:
        """Decelerate within limits (a jerk-limited stop planned from the current velocity and
        acceleration), then send the Stop flag (``end_session``) so the RSI program ends."""
        if self._link.exchange is None:
            return
        self._link.stop_motion(timeout)
        if end_session:
            self.log.info("%s: robot at rest; sending the Stop flag", self.name)
            if not self._link.end_session(max(min(timeout, 20 * self.dt), 0.5)):
                self.log.warning("%s: no controller packet to carry the Stop flag", self.name)
