"""What ``acquire watch`` knows about a cell, built from what the cell publishes on the bus.

:class:`CellView` is fed every bus message (``feed(key, payload)``) and every liveliness change
(``alive(key, present)``) and keeps: the daemon's presence and its devices, the current run's
status (``remaster/<cell>/run/<run-id>/status``, the dict ``RunController.status()`` returns),
the last measured sample, the last joint state and the last warnings (skipped / failed
configurations, retries, lost targets, a restarted controller, an aborted run). It renders as
a rich panel (:meth:`CellView.renderable`) for a terminal, and ``feed`` returns the plain lines
(status changes, samples, warnings) a pipe or journal gets instead.

Keys (acquire/live/bus.py): ``remaster/<cell>/daemon`` and ``remaster/<cell>/device/<name>``
(liveliness), ``remaster/<cell>/run/<run-id>/{status,event,sample}``,
``remaster/<cell>/<device>/joint_state``.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any, Callable

from acquire.record.jsonpayload import PayloadError, decode_json
from acquire.live.progress import format_eta, status_line

#: Run states after which nothing more happens in that run.
TERMINAL_STATES = ("finished", "aborted", "failed")
#: Warnings kept for the view.
MAX_WARNINGS = 6


def cell_of(key: str) -> str | None:
    """``remaster/<cell>/…`` → ``<cell>``; None for other keys."""
    parts = key.split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == "remaster" else None


def _fmt_vec(values: Any, digits: int = 2) -> str:
    try:
        return "[" + " ".join(f"{float(v):.{digits}f}" if v is not None else "—" for v in values) + "]"
    except (TypeError, ValueError):
        return str(values)


def warning_text(ev: dict) -> str | None:
    """The operator's line for a run event that deserves attention, else None."""
    kind, cid = ev.get("kind"), ev.get("config_id")
    at = f" {cid}" if cid else ""
    if kind in ("skipped", "failed"):
        return f"{kind}{at}: {ev.get('reason', '')}"
    if kind == "retry":
        return f"retry{at} ({ev.get('step', '?')}): {ev.get('reason', '')}"
    if kind == "suspended" and ev.get("cause") == "device_fault":
        return f"suspended{at}: {ev.get('reason', '')} (waiting up to {ev.get('allowance_s', '?')} s for {ev.get('device', '?')})"
    if kind == "suspended":
        return f"suspended{at}: {ev.get('sensor', '')}/{ev.get('marker', '')} {ev.get('reason', '')}".rstrip()
    if kind == "searched" and not ev.get("found", True):
        return f"search{at}: {ev.get('sensor', '')} did not find the target within {ev.get('radius_mm', '?')} mm"
    if kind == "controller_restarted":
        return f"controller restarted{at}: {ev.get('reason', '')}"
    if kind == "aborted":
        return f"aborted: {ev.get('reason', '')}"
    if kind == "state" and ev.get("state") == "failed":
        return f"run failed: {ev.get('reason', '')}"
    return None


def sample_text(rec: dict) -> str:
    """``p03-b1  q [..]°  mocap/sir (x y z) mm ± 0.012 (5)`` for a sample record."""
    parts = [str(rec.get("config_id", "?"))]
    if rec.get("q_measured_deg") is not None:
        parts.append(f"q {_fmt_vec(rec['q_measured_deg'])}°")
    for mk in rec.get("markers") or []:
        std = mk.get("std_mm")
        spread = ""
        if isinstance(std, (list, tuple)) and std and all(isinstance(s, (int, float)) for s in std):
            spread = f" ± {max(std):.3f}"
        elif isinstance(std, (int, float)):
            spread = f" ± {std:.3f}"
        parts.append(f"{mk.get('sensor', '?')}/{mk.get('marker', '?')} {_fmt_vec(mk.get('mean_mm') or [], 2)} mm"
                     f"{spread} ({mk.get('count', '?')})")
    return "  ".join(parts)


class CellView:
    """The live state of one cell (see the module docstring); ``clock`` is for the ages shown."""

    def __init__(self, cell: str, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.cell = cell
        self.clock = clock
        self.daemon: bool | None = None  # None: never seen either way
        self.devices: set[str] = set()
        self.run_id: str | None = None
        self.status: dict = {}
        self.sample: dict | None = None
        self.sample_t: float | None = None
        self.joints: list | None = None
        self.joints_t: float | None = None
        self.warnings: deque[tuple[float, str]] = deque(maxlen=MAX_WARNINGS)
        self.messages = 0
        self._status_key: tuple | None = None

    # ------------------------------------------------------------------ input
    @property
    def source(self) -> str:
        """``daemon`` when the cell's daemon is alive, else ``run`` (a stand-alone ``acquire run``)."""
        return "daemon" if self.daemon else "run"

    @property
    def run_done(self) -> bool:
        """The watched run has ended (finished, aborted or failed)."""
        return self.status.get("state") in TERMINAL_STATES

    def alive(self, key: str, present: bool) -> list[str]:
        """A liveliness change of ``remaster/<cell>/daemon`` or ``…/device/<name>``."""
        parts = key.split("/")
        if cell_of(key) != self.cell:
            return []
        if parts[2:] == ["daemon"]:
            if self.daemon == present:
                return []
            self.daemon = present
            return [f"daemon of cell {self.cell}: {'alive' if present else 'gone'}"]
        if len(parts) == 4 and parts[2] == "device":
            (self.devices.add if present else self.devices.discard)(parts[3])
        return []

    def feed(self, key: str, payload: bytes) -> list[str]:
        """Take one bus message; return the plain lines it is worth (maybe none)."""
        if cell_of(key) != self.cell:
            return []
        self.messages += 1
        try:
            doc = decode_json(payload)
        except PayloadError:
            return []
        parts = key.split("/")
        now = self.clock()
        if len(parts) == 5 and parts[2] == "run":
            run_id, kind = parts[3], parts[4]
            lines: list[str] = []
            if run_id != self.run_id and kind in ("status", "event"):
                if self.run_id is not None:
                    self.warnings.clear()
                    self.sample = self.sample_t = None
                self.run_id, self.status, self._status_key = run_id, {}, None
                lines.append(f"run {run_id} of cell {self.cell}")
            if run_id != self.run_id:
                return lines
            if kind == "status":
                self.status = doc
                k = (doc.get("state"), doc.get("done"), doc.get("skipped"), doc.get("failed"))
                if k != self._status_key:
                    self._status_key = k
                    lines.append(f"run {run_id}: {status_line(doc)}")
            elif kind == "sample":
                self.sample, self.sample_t = doc, now
                lines.append(f"sample {sample_text(doc)}")
            elif kind == "event":
                text = warning_text(doc)
                if text is not None:
                    self.warnings.append((now, text))
                    lines.append(f"warning {text}")
            return lines
        if len(parts) == 4 and parts[3] == "joint_state":
            pos = doc.get("position_deg")
            if pos is not None:
                self.joints, self.joints_t = pos, now
        return []

    # ------------------------------------------------------------------ output
    def _age(self, t: float | None) -> str:
        return "" if t is None else f"  ({format_eta(self.clock() - t)} ago)"

    def renderable(self, footer: str = "") -> Any:
        """A rich panel: daemon, run progress, current configuration, last sample, joints, warnings."""
        from rich.panel import Panel
        from rich.progress_bar import ProgressBar
        from rich.table import Table
        from rich.text import Text

        grid = Table.grid(padding=(0, 2))
        grid.add_column(style="bold", no_wrap=True)
        grid.add_column()
        if self.daemon is not None:
            devs = ", ".join(sorted(self.devices)) or "none"
            grid.add_row("daemon", Text(f"alive, devices {devs}" if self.daemon else "gone",
                                        style="" if self.daemon else "red"))
        st = self.status
        if self.run_id is None:
            grid.add_row("run", Text("no run seen yet", style="dim"))
        else:
            done, total = int(st.get("done") or 0), int(st.get("total") or 0)
            bar = Table.grid(padding=(0, 1))
            bar.add_row(Text(str(st.get("state") or "?"), style="bold"),
                        ProgressBar(total=max(total, 1), completed=done if total else 0, width=30),
                        Text(f"{done}/{total}  measured {st.get('measured', 0)}  skipped {st.get('skipped', 0)}  "
                             f"failed {st.get('failed', 0)}  ETA {format_eta(st.get('eta_s'))}"))
            grid.add_row("run", Text(self.run_id))
            grid.add_row("progress", bar)
            if st.get("current"):
                grid.add_row("at", Text(str(st["current"])))
            if st.get("reason"):
                grid.add_row("reason", Text(str(st["reason"]), style="yellow"))
        if self.sample is not None:
            grid.add_row("last sample", Text(sample_text(self.sample) + self._age(self.sample_t)))
        if self.joints is not None:
            grid.add_row("joints", Text(f"{_fmt_vec(self.joints)}°" + self._age(self.joints_t)))
        if self.warnings:
            warn = Text()
            for i, (t, text) in enumerate(self.warnings):
                warn.append(("\n" if i else "") + text + self._age(t), style="yellow")
            grid.add_row("warnings", warn)
        title = f"cell {self.cell} — {self.source}"
        return Panel(grid, title=title, subtitle=footer or None, expand=False)
