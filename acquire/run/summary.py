"""How a run ends (``RunSummary``), why it cannot start (``RunError``), and its states."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

#: Every state of a run, in the order a run normally passes them.
STATES = ("idle", "starting", "running", "paused", "suspended", "stopping", "finished", "aborted", "failed")
#: States a run does not leave.
TERMINAL = ("finished", "aborted", "failed")


class RunError(RuntimeError):
    """The run cannot start or go on (bad resume log, the cell not matching the plan, …)."""


@dataclass
class RunSummary:
    """How a run ended. Times in wall seconds; ``cell_seconds`` in the cell's clock (its
    description's ``clock``)."""

    run_id: str
    state: str
    log_path: Optional[Path]
    total: int
    done: int
    measured: int
    skipped: int
    failed: int
    reason: str = ""
    wall_seconds: float = 0.0
    cell_seconds: float = 0.0
    result_path: Optional[Path] = None
    report_path: Optional[Path] = None
    fit: Optional[dict] = None
    skipped_reasons: dict = field(default_factory=dict)
    adaptive: Optional[dict] = None  # an adaptive run: why it stopped, intervals vs configurations, time saved

    @property
    def exit_code(self) -> int:
        """0 finished; 1 failed; 130 aborted (as after Ctrl-C)."""
        return {"finished": 0, "aborted": 130}.get(self.state, 1)
