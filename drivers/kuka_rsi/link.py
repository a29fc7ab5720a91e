"""``RsiLink``: an RSI commander's exchange process and what it reports.

The UDP socket is bound here and handed to the exchange process (``drivers/exchange.py``
running ``realtime.RsiLoop``), which answers every controller packet. This side keeps what the
process reports back: the first packet (or the controller's axis-count mismatch), motions done,
faults, the Stop flag sent; it reads the latest packet's state and the timing rings from shared
memory, hands planned motions over and asks for stops.
"""

from __future__ import annotations

import itertools
import logging
import socket
import threading
import time

import numpy as np

from drivers.errors import ConnectionLostError, DeviceTimeoutError, DriverError
from drivers.exchange import ExchangeProcess, answer_log, read_state, ring_timing
from drivers.kuka_rsi import realtime
from drivers.protocols import LinkStats


class MotionWaiter:
    """The main process's side of one motion: set when the exchange process reports it done."""

    __slots__ = ("done", "error")

    def __init__(self) -> None:
        self.done = threading.Event()
        self.error: DriverError | None = None


class RsiLink:
    """The exchange process of commander ``name`` (see the module docstring).

    n_axes: axes of the robot model; window: cycles kept in the latency ring; rt_priority:
    SCHED_FIFO priority asked for (0: don't). ``start`` takes the loop's keyword options
    (``realtime.RsiLoop``).
    """

    def __init__(self, name: str, log: logging.Logger, *, n_axes: int, window: int, rt_priority: int) -> None:
        self.name = name
        self.log = log
        self.n_axes = n_axes
        self.window = window
        self.rt_priority = rt_priority
        self.exchange: ExchangeProcess | None = None
        self.address: tuple[str, int] | None = None
        self.axis_error: str | None = None
        #: the last fault the exchange reported and nobody raised yet
        self.fault: DriverError | None = None
        self.first = threading.Event()
        self._stop_sent = threading.Event()
        self._waiters: dict[int, MotionWaiter] = {}
        self._ids = itertools.count(1)
        self._active: int | None = None  # id of the motion handed over and not reported done
        self._lock = threading.Lock()
        self._final_stats: LinkStats | None = None  # the figures of the last exchange, after close

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self, host: str, port: int, options: dict) -> tuple[str, int]:
        """Bind UDP ``host:port`` and start the exchange process on it (no-op when running);
        returns the bound address. ConnectionLostError when either fails."""
        if self.exchange is None:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind((host, port))
            except OSError as exc:
                sock.close()
                raise ConnectionLostError(f"{self.name}: cannot listen on {host}:{port}: {exc}") from exc
            self.address = sock.getsockname()
            self.first.clear()
            self.axis_error = None
            self._final_stats = None
            ex = ExchangeProcess(self.name, realtime.layout(self.n_axes, self.window), realtime.RsiLoop, options,
                                 self._on_event, rt_priority=self.rt_priority, log=self.log)
            self.exchange = ex
            try:
                ex.start(sock)
            except RuntimeError as exc:
                self.exchange = None
                raise ConnectionLostError(str(exc)) from exc
        return self.address

    def close(self) -> None:
        """Keep the last figures and end the exchange process (it closes the socket)."""
        self._final_stats = self.link_stats()
        self.exchange.close()
        self.exchange = None

    def _on_event(self, event: tuple) -> None:
        """Reader thread: one event from the exchange process (see ``realtime``)."""
        kind = event[0]
        if kind == "first":
            self.first.set()
        elif kind == "axis_error":
            self.axis_error = event[1]
            self.first.set()
        elif kind == "done":
            with self._lock:
                w = self._waiters.pop(event[1], None)
                if self._active == event[1]:
                    self._active = None
            if w is not None:
                w.error = event[2]
                w.done.set()
        elif kind == "fault":
            self.fault = event[1]
        elif kind == "stop_sent":
            self._stop_sent.set()
        elif kind == "crashed":
            err = ConnectionLostError(f"{self.name}: the RSI exchange process failed: {event[1]}")
            self.fault = err
            with self._lock:
                waiters, self._waiters, self._active = list(self._waiters.values()), {}, None
            for w in waiters:
                w.error = err
                w.done.set()

    # -- state --------------------------------------------------------------------------------

    def snapshot(self, *extra: str) -> dict | None:
        """The latest packet's state from the exchange process (None before the first)."""
        st = read_state(self.exchange, realtime.SCALARS + ("actual", "cmd", "ref") + extra)
        if st is None or not st["has_state"][0]:
            return None
        return st

    def busy(self) -> bool:
        """A motion is handed over and not reported done, or the exchange is still running one."""
        snap = self.snapshot()
        return self._active is not None or (snap is not None and bool(snap["busy"][0]))

    def fresh(self, max_age_s: float) -> bool:
        """The latest packet arrived at most ``max_age_s`` ago."""
        snap = self.snapshot()
        return snap is not None and time.monotonic() - snap["t_rx"][0] <= max_age_s

    def raise_fault(self) -> None:
        """Raise (once) the fault the exchange reported, if any."""
        fault, self.fault = self.fault, None
        if fault is not None:
            raise fault

    def link_stats(self) -> LinkStats:
        """Timing of the last cycles, as measured by the exchange process (see ``LinkStats``)."""
        ex = self.exchange
        snap = read_state(ex, realtime.SCALARS + ("lat", "rx"))
        if snap is None and self._final_stats is not None:
            return self._final_stats
        if snap is None:
            timing = ring_timing(0, np.zeros(0), np.zeros(0))
            snap = dict.fromkeys(realtime.SCALARS, np.zeros(1))
        else:
            timing = ring_timing(int(snap["count"][0]), snap["rx"], snap["lat"])
        delay = int(snap["delay"][0]) if snap["has_delay"][0] else None
        return LinkStats(
            **timing,
            late_answers=int(snap["late"][0]),
            gaps=int(snap["gaps"][0]),
            malformed=int(snap["malformed"][0]),
            restarts=int(snap["restarts"][0]),
            guard_clamps=int(snap["clamps"][0]),
            delay=delay,
            realtime=ex is not None and ex.realtime.startswith("SCHED_FIFO"),
            notes=(f"controller Delay {delay}", f"exchange process: {ex.realtime if ex else 'not running'}"),
        )

    def answer_log(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(packets, arrived, latency)``: see ``RsiCommander.answer_log``."""
        return answer_log(self.exchange)

    # -- motion -------------------------------------------------------------------------------

    def hand_over(self, rows: np.ndarray, trajectory, session: int) -> MotionWaiter:
        """Give the exchange the correction rows (shape (m, n_axes), degrees from the session
        reference) of a checked, planned motion for session ``session``; its waiter is set when
        the exchange reports the motion done (or refused)."""
        motion_id = next(self._ids)
        waiter = MotionWaiter()
        with self._lock:
            self._waiters[motion_id] = waiter
            self._active = motion_id
        try:
            self.exchange.request("move", motion_id, rows, trajectory, session)
        except ConnectionError as exc:
            with self._lock:
                self._waiters.pop(motion_id, None)
                self._active = None
            raise ConnectionLostError(str(exc)) from exc
        return waiter

    def reported(self, error: DriverError) -> None:
        """``error`` (a motion's) has been raised to the caller: do not raise it again as a fault."""
        if self.fault is error:
            self.fault = None

    def request(self, *msg) -> None:
        try:
            self.exchange.request(*msg)
        except (ConnectionError, AttributeError) as exc:
            raise ConnectionLostError(f"{self.name}: the RSI exchange process is not running ({exc})") from exc

    def stop_motion(self, timeout: float) -> None:
        """Ask the exchange process to stop the current motion and wait until it is at rest."""
        with self._lock:
            active = self._active
            waiter = None if active is None else self._waiters.get(active)
        self.request("stop")
        deadline = time.monotonic() + timeout
        if waiter is not None:
            waiter.done.wait(timeout)
        # an aborted motion reports done at once and then stops: wait for the stop's end too
        while self.busy() and time.monotonic() < deadline:
            time.sleep(0.01)
        if self.busy():
            raise DeviceTimeoutError(f"{self.name}: stop not completed within {timeout:.3g} s (no packets?)")

    def end_session(self, wait_s: float) -> bool:
        """Send the Stop flag with the next answer; whether a packet carried it within ``wait_s``."""
        self._stop_sent.clear()
        self.request("end_session")
        return self._stop_sent.wait(wait_s)
