"""``CellDescription``: what a run needs to know about the cell it measures in.

A run is handed one and opens every device through it; it cannot tell (and does not ask)
whether the devices behind the URLs are real or simulated. A real cell's description is the
plan's own URLs and the host's clock (``acquire.cell.plan_cell``); a simulated cell
(``drivers.sim.running.SimulatedCell``) starts its fake devices and describes them the same
way — its timing allowances travel in the commander URL's query, as an integrator would write
them for a slow controller.

Units: clock and sleep in the cell's seconds (wall seconds on a real cell); ``time_scale`` in
cell seconds per wall second.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable


@dataclass(frozen=True)
class CellDescription:
    """Device URLs and time source of one cell.

    commander_url: where the run's commander listens (its driver parses the query, e.g.
    ``fri://127.0.0.1:30200?timeout_ms=300``). sensor_urls: plan sensor name → that sensor's
    URL. clock / sleep: the cell's time (seconds) for every device and the sequencer.
    time_scale: cell seconds per wall second (1 for a real cell; the ETA before the first
    configuration uses it). metadata: what the cell says about itself, written as text into the
    run log's metadata (e.g. ``{"cell_source": "plan"}``). notes: one line per device, for a
    person (logged at INFO when the run opens its devices).
    """

    commander_url: str
    sensor_urls: dict[str, str] = field(default_factory=dict)
    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    time_scale: float = 1.0
    metadata: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.commander_url:
            raise ValueError("a cell description needs the commander's URL (given none)")
        if not self.time_scale > 0:
            raise ValueError(f"time_scale must be positive (cell seconds per wall second), given {self.time_scale!r}")

    def sensor_url(self, name: str) -> str:
        """The URL of the plan sensor ``name``; KeyError naming the sensors the cell has."""
        try:
            return self.sensor_urls[name]
        except KeyError:
            raise KeyError(f"the cell has no device for sensor {name!r}; it has {sorted(self.sensor_urls)}") from None
