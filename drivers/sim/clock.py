"""Simulated time that can run faster than real time.

``SimClock(time_scale=10)`` advances ten simulated seconds per wall second. Fakes and the
sequencer's cell-time estimates read ``now()``; waits go through ``sleep(sim_seconds)``.
"""

from __future__ import annotations

import threading
import time


class SimClock:
    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0:
            raise ValueError(f"time_scale must be positive, got {time_scale}")
        self.time_scale = float(time_scale)
        self._wall0 = time.monotonic()
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        # picklable (an exchange process reads the same clock: the monotonic clock is system-wide)
        return {"time_scale": self.time_scale, "_wall0": self._wall0}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Simulated seconds since the clock was made."""
        return (time.monotonic() - self._wall0) * self.time_scale

    def wall_duration(self, sim_seconds: float) -> float:
        """Wall seconds that ``sim_seconds`` of simulated time take."""
        return sim_seconds / self.time_scale

    def sleep(self, sim_seconds: float) -> None:
        time.sleep(max(0.0, sim_seconds) / self.time_scale)
