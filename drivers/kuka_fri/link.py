"""``FriLink``: an FRI commander's exchange process and what it reports.

The UDP port is bound here and handed to the exchange process (``drivers/exchange.py`` running
``realtime.FriLoop`` around ``FriClientSession``). This side keeps what the process reports
back (motions done, the names of the IOs the controller shares, a crash), reads its state and
timing rings from shared memory, hands checked motions over and asks for stops.
"""

from __future__ import annotations

import itertools
import logging
import socket
import threading
from typing import Optional

import numpy as np

from drivers.errors import ConnectionLostError
from drivers.exchange import ExchangeProcess, answer_log, read_state, ring_timing
from drivers.kuka_fri import realtime
from drivers.kuka_fri.messages import ConnectionQuality
from drivers.kuka_fri.session import Motion, SessionSnapshot
from drivers.protocols import LinkStats


def enum_name(cls, value: int) -> str:
    """``cls(value).name``, or the number when ``cls`` has no such member."""
    try:
        return cls(value).name
    except ValueError:
        return str(value)


class FriLink:
    """The exchange process of commander ``name`` (see the module docstring).

    window: cycles kept in the latency ring; rt_priority: SCHED_FIFO priority asked for (0:
    don't). ``io_tables``: generation → the shared IOs' (name, type, direction), the newest two.
    """

    def __init__(self, name: str, log: logging.Logger, *, window: int, rt_priority: int) -> None:
        self.name = name
        self.log = log
        self.window = window
        self.rt_priority = rt_priority
        self.exchange: Optional[ExchangeProcess] = None
        self.address: Optional[tuple[str, int]] = None
        self.io_tables: dict[int, tuple] = {}
        self._lock = threading.Lock()
        self._motions: dict[int, Motion] = {}  # handed to the exchange, not reported done
        self._ids = itertools.count(1)
        self._final_stats: Optional[LinkStats] = None
        self._last_scheduling = "not started"

    @property
    def scheduling(self) -> str:
        """How the exchange process is (or last was) scheduled (``SCHED_FIFO 50, memory locked``, …)."""
        return self._last_scheduling if self.exchange is None else self.exchange.realtime

    def start(self, bind: tuple[str, int], options: dict) -> None:
        """Bind UDP ``bind`` and start the exchange process on it; ConnectionLostError when either fails."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(bind)
        except OSError as exc:
            sock.close()
            raise ConnectionLostError(f"{self.name}: cannot bind UDP {bind[0]}:{bind[1]}: {exc}") from exc
        self.address = sock.getsockname()
        ex = ExchangeProcess(self.name, realtime.layout(self.window), realtime.FriLoop, options, self._on_event,
                             rt_priority=self.rt_priority, log=self.log)
        try:
            ex.start(sock)
        except RuntimeError as exc:
            raise ConnectionLostError(str(exc)) from exc
        self.exchange = ex
        self._final_stats = None

    def close(self, stats: LinkStats) -> None:
        """Keep ``stats`` (the last figures), end the exchange process (it closes the port) and
        fail the motions still waiting."""
        self._final_stats = stats
        self._last_scheduling = self.exchange.realtime
        self.exchange.close()
        self.exchange = None
        self._fail_all(ConnectionLostError(f"{self.name}: closed"))

    def _fail_all(self, err: ConnectionLostError) -> None:
        with self._lock:
            left, self._motions = list(self._motions.values()), {}
        for m in left:
            m.error = err
            m.done.set()

    def _on_event(self, event: tuple) -> None:
        """Reader thread: one event from the exchange process (see ``realtime``)."""
        kind = event[0]
        if kind == "done":
            with self._lock:
                m = self._motions.pop(event[1], None)
            if m is not None:
                m.error = event[2]
                m.done.set()
        elif kind == "io_table":
            gen, table = event[1], event[2]
            self.io_tables = {g: t for g, t in self.io_tables.items() if g >= gen - 1} | {gen: table}
        elif kind == "crashed":
            self._fail_all(ConnectionLostError(f"{self.name}: the FRI exchange process failed: {event[1]}"))

    def read(self, names) -> Optional[dict]:
        """The exchange's shared arrays ``names`` (copies); None when it is not running."""
        return read_state(self.exchange, names)

    def link_stats(self, snap: Optional[SessionSnapshot]) -> LinkStats:
        """Timing of the last cycles, measured in the exchange process; ``snap`` (the latest
        monitoring message) gives the session line of the notes."""
        st = self.read(realtime.LINK + realtime.COUNTERS + ("lat", "rx"))
        if st is None:
            if self._final_stats is not None:
                return self._final_stats
            st = {k: np.zeros(max(1, self.window)) for k in realtime.LINK + realtime.COUNTERS + ("lat", "rx")}
        notes = ["session: no monitoring message yet"] if snap is None else [
            f"session: {snap.session_state.name}, quality {enum_name(ConnectionQuality, snap.quality)}, "
            f"{snap.layout}, receive period {(snap.receive_period_s or 0) * 1e3:.0f} ms",
        ]
        notes.append(f"exchange process: {self.scheduling}; foreign datagrams {int(st['foreign'][0])}")
        return LinkStats(
            **ring_timing(int(st["count"][0]), st["rx"], st["lat"]), late_answers=int(st["late"][0]),
            gaps=int(st["gaps"][0]), malformed=int(st["malformed"][0]), restarts=int(st["restarts"][0]),
            guard_clamps=int(st["step_clamps"][0]), delay=None,
            realtime=self.scheduling.startswith("SCHED_FIFO"), notes=tuple(notes),
        )

    def answer_log(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(messages, arrived, latency)``: see ``FriCommander.answer_log``."""
        return answer_log(self.exchange)

    def hand_over(self, motion: Motion, hold: np.ndarray) -> None:
        """Send a checked, planned motion to the exchange process; its ``done`` is set when the
        exchange reports it ended (or refused it)."""
        motion_id = next(self._ids)
        with self._lock:
            self._motions[motion_id] = motion
        try:
            self.exchange.request("move", motion_id, motion.trajectory, motion.dt, motion.max_step_rad,
                                  motion.limits_scaled, motion.planned_s, hold)
        except (ConnectionError, AttributeError) as exc:
            with self._lock:
                self._motions.pop(motion_id, None)
            raise ConnectionLostError(f"{self.name}: the FRI exchange process is not running ({exc})") from exc

    def active_motion(self) -> Optional[Motion]:
        with self._lock:
            return next(iter(self._motions.values()), None)

    def request_stop(self) -> None:
        """Ask the exchange to decelerate the current motion (nothing when it is not running)."""
        ex = self.exchange
        if ex is not None:
            try:
                ex.request("stop")
            except ConnectionError:
                pass
