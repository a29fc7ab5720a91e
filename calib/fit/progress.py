"""What a long fit is doing, and about how long it will take: ``Progress``, told by the fit's stages
(cross-validation folds, the importance check, the random walk) and passed on to a sink — a
terminal line (``acquire fit``), the daemon's run status (``acquire.run.fitting``) — no more
often than ``every_s``.

The estimate of the time left is per stage: the stage's elapsed time over the fraction of its
work done (fold fits counted; the samplers say their own fraction). A stage of unknown length (the
random walk stops when its chains agree) gives its bound: the time to its most steps.
"""

from __future__ import annotations

import time
from typing import Callable

#: The sink: (what the fit is doing, seconds left in that stage or None).
Sink = Callable[[str, "float | None"], None]


class Progress:
    """Progress of one fit. ``sink(text, eta_s)``: where it goes; ``clock``: monotonic seconds
    (injected in tests); ``every_s``: the least interval between two lines given to the sink
    (a stage's first line always goes)."""

    def __init__(self, sink: Sink, *, clock: Callable[[], float] = time.monotonic, every_s: float = 0.5) -> None:
        self.sink, self.clock, self.every_s = sink, clock, float(every_s)
        self.t_stage = self.t_last = -float("inf")
        self.stage, self.total, self.done = "", 0, 0

    def begin(self, stage: str, total: int = 0) -> None:
        """Start ``stage`` of ``total`` counted steps (0: the stage gives its own fractions)."""
        self.stage, self.total, self.done = stage, int(total), 0
        self.t_stage = self.clock()
        self.t_last = -float("inf")

    def step(self, text: str) -> None:
        """One counted step of the stage begins: ``text`` says which."""
        self._emit(f"{text} [{self.done + 1}/{self.total}]" if self.total else text,
                   self.done / self.total if self.total else None)
        self.done += 1

    def note(self, text: str, fraction: float | None = None) -> None:
        """A line of the stage, with the fraction of it done where known (for the time left)."""
        self._emit(text, fraction)

    def __call__(self, text: str, fraction: float | None = None) -> None:
        """``note``: a sampler's line (``calib.fit.laplace_sampling``'s ``progress``)."""
        self.note(text, fraction)

    def _emit(self, text: str, fraction: float | None) -> None:
        now = self.clock()
        first = self.t_last < self.t_stage
        if not first and now - self.t_last < self.every_s:
            return
        self.t_last = now
        eta = None
        if fraction is not None and fraction > 0:
            eta = (now - self.t_stage) * (1.0 - fraction) / fraction
        self.sink(text, eta)

