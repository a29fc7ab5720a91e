"""Rate-limited log lines for what clients send: a flood of bad requests cannot flood the log.

``Throttle.admit(source)`` answers whether one more line about ``source`` may be written, with
token buckets per source (``burst`` lines, then one every ``1/per_s`` seconds) and one over all
sources (a client that changes its source id each time is still bounded). A refused line is
counted; the next admitted line for that source reports how many were suppressed, and ``drain()``
what is still owed when the server closes. Sources are forgotten (oldest first) beyond ``max_sources``.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable


@dataclass
class _Bucket:
    tokens: float
    t: float
    suppressed: int = 0


class Throttle:
    """Token buckets per source and overall (thread-safe). Rates in lines per second."""

    def __init__(self, *, burst: int = 20, per_s: float = 0.2, total_burst: int = 60, total_per_s: float = 1.0,
                 max_sources: int = 1024, clock: Callable[[], float] = time.monotonic) -> None:
        self.burst, self.per_s = burst, per_s
        self.total_burst, self.total_per_s = total_burst, total_per_s
        self.max_sources = max_sources
        self._clock = clock
        self._sources: OrderedDict[str, _Bucket] = OrderedDict()
        self._total = _Bucket(float(total_burst), clock())
        self._lock = threading.Lock()
        #: Lines refused so far (all sources).
        self.suppressed_total = 0

    @staticmethod
    def _refill(b: _Bucket, now: float, burst: int, rate: float) -> None:
        b.tokens = min(float(burst), b.tokens + (now - b.t) * rate)
        b.t = now

    def admit(self, source: str) -> int | None:
        """None when this line must be dropped; otherwise how many lines of ``source`` were
        dropped since its last admitted one."""
        now = self._clock()
        with self._lock:
            b = self._sources.get(source)
            if b is None:
                b = self._sources[source] = _Bucket(float(self.burst), now)
                while len(self._sources) > self.max_sources:
                    self._sources.popitem(last=False)
            else:
                self._sources.move_to_end(source)
            self._refill(b, now, self.burst, self.per_s)
            self._refill(self._total, now, self.total_burst, self.total_per_s)
            if b.tokens < 1 or self._total.tokens < 1:
                b.suppressed += 1
                self.suppressed_total += 1
                return None
            b.tokens -= 1
            self._total.tokens -= 1
            n, b.suppressed = b.suppressed, 0
            return n

    def drain(self) -> dict[str, int]:
        """The sources with lines dropped since their last admitted one, and how many (then
        zeroed): what a closing server still owes its log."""
        with self._lock:
            owed = {src: b.suppressed for src, b in self._sources.items() if b.suppressed}
            for src in owed:
                self._sources[src].suppressed = 0
            return owed


def clip(text: object, limit: int = 200) -> str:
    """``str(text)`` on one line, at most ``limit`` characters (what a client sent is not trusted)."""
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 1] + "…"
