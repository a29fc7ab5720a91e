"""Everything a run tells the world: events and records into its log, the same on the Zenoh bus,
status to the progress display. Nothing here may stop a run: a failing log write is logged, a
failing bus publish is ignored (DEBUG)."""

from __future__ import annotations

import logging
import math
from typing import Callable, Optional

import numpy as np

log = logging.getLogger(__name__)


class RunPublisher:
    """The run's outputs. ``runlog``: the open ``acquire.record.recorder.RunLog`` (None before it is
    created and after it is closed); ``bus``: an ``acquire.live.bus.Bus`` or None; ``on_progress``:
    called with every status dict (the terminal's progress bar)."""

    def __init__(self, cell_id: str, bus=None, on_progress: Optional[Callable[[dict], None]] = None) -> None:
        self.cell_id = cell_id
        self.bus = bus
        self.on_progress = on_progress
        self.run_id = ""
        self.runlog = None
        self.bus_released = False

    def _publish(self, *parts_and_payload) -> None:
        *parts, payload = parts_and_payload
        if self.bus is None:
            return
        try:
            from acquire.live.bus import key

            # The bus's own key when it serves this cell: it carries the cell's site, if any.
            k = self.bus.key(*parts) if self.bus.cell == self.cell_id else key(self.cell_id, *parts)
            self.bus.publish(k, payload)
        except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
            log.debug("bus publish failed: %s", exc)

    def event(self, kind: str, **fields) -> None:
        """One event into the log (``RunLog.event``) and on ``remaster/<cell>/run/<id>/event``."""
        fields = {k: v for k, v in fields.items() if v is not None}
        if self.runlog is not None:
            try:
                self.runlog.event(kind, **fields)
            except (OSError, ValueError, RuntimeError) as exc:
                log.warning("could not log event %s: %s", kind, exc)
        if self.run_id:
            self._publish("run", self.run_id, "event", {"kind": kind, **fields})

    def progress(self, status: dict) -> None:
        """A status dict to the display and on ``remaster/<cell>/run/<id>/status`` (what
        ``acquire watch`` shows)."""
        if self.on_progress is not None:
            try:
                self.on_progress(status)
            except (OSError, ValueError) as exc:  # a closed terminal must not stop the run
                log.debug("progress display: %s", exc)
        if self.run_id and not self.bus_released:
            self._publish("run", self.run_id, "status", status)

    def reading(self, sensor: str, samples: list) -> None:
        """One sensor reading (settle window) to the log's marker stream and the bus."""
        if not samples:
            return
        positions = {s.marker: (s.position_mm if s.visible else None) for s in samples}
        device_time = samples[-1].device_time
        device_time = float(device_time) if math.isfinite(device_time) else None
        if self.runlog is not None:
            try:
                self.runlog.record_markers(sensor, positions, device_time=device_time)
            except (OSError, ValueError, RuntimeError) as exc:
                log.debug("marker frame not logged: %s", exc)
        self._publish(sensor, "markers", {
            "device_time": device_time,
            "markers": [{"name": m, "position_mm": None if p is None else np.asarray(p).tolist()}
                        for m, p in positions.items()]})

    def sample(self, record: dict) -> None:
        """One measured configuration: a sample record in the log and on the bus. Errors of
        the log (``OSError``, the recorder's storage errors) reach the caller: a sample that
        was not written is not measured."""
        if self.runlog is not None:
            self.runlog.sample(record)
        if self.run_id:
            self._publish("run", self.run_id, "sample", record)

    def release_bus(self) -> None:
        """Undeclare the run's own publishers (once): a long-lived daemon bus must not keep them."""
        if self.bus is None or not self.run_id or self.bus_released:
            return
        self.bus_released = True
        from acquire.live.bus import key

        try:
            same = self.bus.cell == self.cell_id
            self.bus.release(self.bus.key("run", self.run_id) if same else key(self.cell_id, "run", self.run_id))
        except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
            log.debug("releasing the run's publishers: %s", exc)

    def close_log(self) -> None:
        if self.runlog is not None:
            try:
                self.runlog.close()
            except (OSError, ValueError, RuntimeError) as exc:
                log.error("closing the run log: %s", exc)
            self.runlog = None
