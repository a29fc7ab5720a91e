"""``SessionView``: the main process's read-only view of the exchange process's ``FriClientSession``.

Same names as the session (``snapshot``, ``session_state``, ``held_position``,
``motion_active``, ``counters``), read from the exchange's shared memory through its
``FriLink``, plus ``begin_move`` (checked and planned here, streamed there) and
``request_stop``.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from drivers.kuka_fri import realtime
from drivers.kuka_fri.link import FriLink
from drivers.kuka_fri.messages import SessionState
from drivers.kuka_fri.session import Motion, SessionCounters, SessionSnapshot, plan_move
from drivers.protocols import JointLimits


class SessionView:
    """The session behind ``link``. limits: the model's, shape (7,) arrays; start_tolerance_rad:
    allowed gap between measured and held position when a move starts; expect_major: the FRI
    major version moves require (None: any)."""

    def __init__(self, link: FriLink, limits: JointLimits, *, start_tolerance_rad: float,
                 expect_major: Optional[int]) -> None:
        self._link = link
        self.limits = limits
        self.start_tolerance_rad = start_tolerance_rad
        self.expect_major = expect_major
        self._cached: Optional[SessionSnapshot] = None

    def snapshot(self) -> Optional[SessionSnapshot]:
        """The latest monitoring message as the exchange saw it (the same object until the next)."""
        st = self._link.read(realtime.SNAP + realtime.layout_arrays())
        if st is None:
            return self._cached
        c = self._cached
        tables = self._link.io_tables
        same = c is not None and c.host_time == st["host_time"][0] and c.sequence_counter == int(st["seq"][0])
        if same and (c.io or not int(st["n_io"][0]) or realtime.io_pending(st, tables)):
            return c  # (rebuilt when the names of its IO values have arrived since)
        self._cached = realtime.snapshot_from(st, tables)
        return self._cached

    def io_pending(self) -> bool:
        """The exchange shares IO values whose names have not reached this process yet."""
        st = self._link.read(realtime.SNAP)
        return st is not None and realtime.io_pending(st, self._link.io_tables)

    @property
    def session_state(self) -> Optional[SessionState]:
        snap = self.snapshot()
        return None if snap is None else snap.session_state

    def held_position(self) -> Optional[np.ndarray]:
        st = self._link.read(("has_hold", "hold"))
        return None if st is None or not st["has_hold"][0] else st["hold"].copy()

    def motion_active(self) -> bool:
        """A move is handed over and not reported done, or the exchange is still streaming one."""
        if self._link.active_motion() is not None:
            return True
        st = self._link.read(("busy",))
        return st is not None and bool(st["busy"][0])

    @property
    def counters(self) -> SessionCounters:
        st = self._link.read(realtime.COUNTERS)
        return SessionCounters() if st is None else realtime.counters_from(st)

    def begin_move(self, target_rad: np.ndarray, speed: float, name: str) -> Motion:
        """Check and plan a move here (LimitError: nothing moved), then hand it to the exchange,
        which starts it only if the session and the held position are still as checked."""
        st = self._link.read(realtime.SNAP + realtime.layout_arrays() + ("hold",))
        snap = None if st is None else realtime.snapshot_from(st)
        hold = None if st is None or not st["has_hold"][0] else st["hold"].copy()
        busy = self.motion_active()
        motion = plan_move(snap, hold, busy, target_rad, speed, limits=self.limits,
                           start_tolerance_rad=self.start_tolerance_rad, expect_major=self.expect_major, name=name)
        self._link.hand_over(motion, hold)
        return motion

    def request_stop(self) -> Optional[Motion]:
        """Ask the exchange to decelerate the current motion; returns it (None if idle)."""
        motion = self._link.active_motion()
        self._link.request_stop()
        return motion
