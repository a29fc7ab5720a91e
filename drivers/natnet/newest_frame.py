"""The newest NatNet frame: ordering by frame number (late and duplicate frames dropped, a server
restart recognised), and handing each accepted frame to the reader once, with the silence limit."""

from __future__ import annotations

import threading
from collections.abc import Callable

from drivers.base import Clock
from drivers.errors import ConnectionLostError, DeviceTimeoutError
from drivers.natnet import codec
from drivers.natnet.settings import NatNetSettings


class NewestFrame:
    """Keeps only the newest frame (see NatNetSensor's "Ordering" and "Silence").

    ``offer`` (receiver thread) accepts a frame whose number is above the newest one; an older
    one is stale and dropped, unless the counter jumped back by more than
    ``settings.reorder_window`` frames or ``settings.restart_run`` older frames came in
    increasing order, or it is the first frame after ``rejoin()`` (a new SERVERINFO): then the
    server restarted, ordering starts over and ``offer`` says why. ``take`` (reader) waits for
    a frame not taken yet.

    Counters: ``frames_accepted``, ``frames_stale`` (dropped), ``restarts`` (recognised).
    """

    def __init__(self, settings: NatNetSettings, clock: Clock) -> None:
        self.settings = settings
        self.clock = clock
        self.frames_accepted = 0
        self.frames_stale = 0
        self.restarts = 0
        self._cond = threading.Condition()
        self._frame: codec.FrameOfData | None = None
        self._frame_host_time = 0.0
        self._seq = 0  # accepted frames so far; take() returns each at most once
        self._read_seq = 0
        self._newest: int | None = None  # newest accepted frame number
        self._old_run: list[int] = []
        self._rejoined = False
        self._last_rx = 0.0  # host time (s) of the last frame datagram (any)
        self._failure: BaseException | None = None

    @property
    def last_rx(self) -> float:
        """Host time (s) of the last frame datagram, or of the last ``heard``."""
        return self._last_rx

    def heard(self, host_time: float) -> None:
        """The server answered at ``host_time`` (s): the silence limit counts from here."""
        with self._cond:
            self._last_rx = host_time

    def rejoin(self) -> None:
        """The server re-announced itself: take its next frame whatever its number."""
        with self._cond:
            self._rejoined = True

    def fail(self, exc: BaseException) -> None:
        """The receiver stopped: ``take`` raises ConnectionLostError from ``exc``."""
        with self._cond:
            self._failure = exc
            self._cond.notify_all()

    def offer(self, frame: codec.FrameOfData, host_time: float) -> str | None:
        """Take ``frame`` (arrived at ``host_time``, s) if it is the newest; returns why the
        server is taken to have restarted (``restarts`` counted), else None."""
        n = frame.frame_number
        with self._cond:
            self._last_rx = host_time
            newest = self._newest
            reason = None
            if self._rejoined:  # first frame after a SERVERINFO: accept whatever its number
                self._rejoined = False
                if newest is not None and n <= newest:
                    reason = f"frame counter restarted at {n} (was {newest}) after a new SERVERINFO"
            elif newest is not None and n <= newest:
                run = self._old_run
                if run and n <= run[-1]:
                    run.clear()
                run.append(n)
                if newest - n <= self.settings.reorder_window and len(run) < self.settings.restart_run:
                    self.frames_stale += 1
                    return None
                reason = f"frame counter went back from {newest} to {n}"
            self._old_run.clear()
            self._newest = n
            self._frame = frame
            self._frame_host_time = host_time
            self._seq += 1
            self.frames_accepted += 1
            if reason is not None:
                self.restarts += 1
            self._cond.notify_all()
        return reason

    def take(self, timeout: float, why_silent: Callable[[], str]) -> tuple[codec.FrameOfData, float]:
        """The newest frame not taken yet and its host arrival time (s), waiting up to
        ``timeout`` s. DeviceTimeoutError as soon as no frame came for
        ``settings.silence_timeout_s`` (message ends with ``why_silent()``) or at the timeout;
        ConnectionLostError when the receiver stopped."""
        s = self.settings
        deadline = self.clock() + timeout
        with self._cond:
            while True:
                if self._failure is not None:
                    raise ConnectionLostError(f"{s.name}: receiver stopped: {self._failure}") from self._failure
                if self._seq > self._read_seq and self._frame is not None:
                    self._read_seq = self._seq
                    return self._frame, self._frame_host_time
                now = self.clock()
                silent = now - self._last_rx
                if silent >= s.silence_timeout_s:
                    raise DeviceTimeoutError(
                        f"{s.name}: no NatNet frame for {silent:.3f} s (silence limit "
                        f"{s.silence_timeout_s} s); " + why_silent()
                    )
                if now >= deadline:
                    raise DeviceTimeoutError(f"{s.name}: no new NatNet frame within {timeout:.3g} s")
                self._cond.wait(min(deadline, self._last_rx + s.silence_timeout_s) - now)
