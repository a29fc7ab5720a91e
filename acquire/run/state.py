"""A run's state machine and its counters, behind one lock; the control surface's events.

States: idle → starting → running ⇄ paused / suspended → stopping → finished | aborted |
failed (``summary.STATES``). ``RunState`` holds the state, the reason, the counts
(total / done / measured / skipped / failed), the configuration being measured, the remaining
cell-time estimates (for the ETA) and the two events the control surface sets: ``aborting``
(abort asked) and ``unpaused`` (cleared by a pause). Every change goes through ``set`` so the
publisher (``RunPublisher``) sees it as an event and a status.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Optional

from acquire.run.summary import TERMINAL, RunSummary

log = logging.getLogger(__name__)


class RunState:
    """Thread-safe state and counters of one run. ``publisher``: its ``RunPublisher``;
    ``time_scale``: cell seconds per wall second (the ETA before any configuration is done)."""

    def __init__(self, publisher, time_scale: float = 1.0) -> None:
        self.pub = publisher
        self.lock = threading.RLock()
        self.state = "idle"
        self.reason = ""
        self.run_id = ""
        self.log_path: Optional[Path] = None
        self.total = self.done = self.measured = self.skipped = self.failed = 0
        self.current: Optional[str] = None
        self.remaining_est: list[float] = []
        self.est_done = 0.0
        self.loop_wall0: Optional[float] = None
        self.wall0 = time.monotonic()
        self.time_scale = float(time_scale)
        self.skip_reasons: dict[str, str] = {}
        #: The end-of-run fit while it runs: {"doing": what, "eta_s": seconds left in that stage or None}.
        self.fit: Optional[dict] = None
        self.aborting = threading.Event()
        self.unpaused = threading.Event()
        self.unpaused.set()

    # ------------------------------------------------------------------ reading
    def status(self) -> dict:
        with self.lock:
            return {
                "state": self.state, "run_id": self.run_id, "done": self.done, "total": self.total,
                "measured": self.measured, "failed": self.failed, "skipped": self.skipped, "eta_s": self.eta(),
                "current": self.current, "log": str(self.log_path) if self.log_path else None, "reason": self.reason,
                "fit": self.fit,
            }

    def eta(self) -> float | None:
        """Wall seconds left: the remaining estimated cell time, scaled by how the configurations
        done so far compared with their estimates (before any, by the cell's time scale)."""
        if not self.remaining_est:
            return 0.0 if self.total else None
        remaining = float(sum(self.remaining_est))
        if self.est_done > 0 and self.loop_wall0 is not None:
            return remaining * (time.monotonic() - self.loop_wall0) / self.est_done
        return remaining / self.time_scale

    def summary(self) -> RunSummary:
        with self.lock:
            return RunSummary(
                run_id=self.run_id, state=self.state, log_path=self.log_path, total=self.total, done=self.done,
                measured=self.measured, skipped=self.skipped, failed=self.failed, reason=self.reason,
                wall_seconds=time.monotonic() - self.wall0, skipped_reasons=dict(self.skip_reasons),
            )

    # ------------------------------------------------------------------ changing
    def progress(self) -> None:
        self.pub.progress(self.status())

    def fitting(self, doing: str, eta_s: float | None) -> None:
        """The end-of-run fit's progress (``calib.fit.progress.Progress``'s sink): a status."""
        with self.lock:
            self.fit = {"doing": doing, "eta_s": eta_s}
        self.progress()

    def set(self, state: str, reason: str = "") -> None:
        """Enter ``state`` (with ``reason``): logged, an event ``state``, a status."""
        with self.lock:
            if state == self.state:
                return
            self.state = state
            if reason or state == "running":
                self.reason = reason
        log.info("run %s: %s%s", self.run_id, state, f" ({reason})" if reason else "")
        self.pub.event("state", state=state, reason=reason)
        self.progress()

    def fail(self, reason: str) -> None:
        with self.lock:
            self.reason = reason
        self.set("failed", reason)

    def request_pause(self) -> bool:
        """Clear ``unpaused`` if the run can pause now; True if it did."""
        with self.lock:
            if self.state in ("running", "starting", "suspended"):
                self.unpaused.clear()
                return True
        return False

    def request_abort(self, reason: str) -> bool:
        """Mark the run aborting (once); True if this call did."""
        with self.lock:
            if self.state in TERMINAL or self.aborting.is_set():
                return False
            self.reason = reason
            self.aborting.set()
            self.unpaused.set()
            if self.state != "idle":
                self.set("stopping")
        return True

    def checkpoint(self) -> bool:
        """Between configurations: honour pause and abort. False to stop the loop."""
        if not self.unpaused.is_set() and not self.aborting.is_set():
            self.set("paused")
            self.unpaused.wait()
            if not self.aborting.is_set():
                self.set("running")
        return not self.aborting.is_set()

    def begin(self, config_id: str) -> None:
        with self.lock:
            self.current = config_id
        self.progress()

    def count(self, config_id: str, outcome: str, reason: str | None = None) -> None:
        """One configuration ended with ``outcome`` (measured | skipped | failed)."""
        with self.lock:
            self.done += 1
            if self.remaining_est:
                self.est_done += self.remaining_est.pop(0)
            if outcome in ("measured", "skipped", "failed"):
                setattr(self, outcome, getattr(self, outcome) + 1)
            self.current = None
        self.progress()
