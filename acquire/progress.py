"""A progress display for a run: a redrawn bar on a terminal, plain lines otherwise.

``Progress(stream).update(status)`` takes ``RunController.status()`` dicts. On a TTY it redraws
one line (``\\r``): bar, done/total, measured, skipped, failed, ETA, current configuration, state.
Not on a TTY (journald, CI, pipes) it writes one plain line per completed configuration or state
change and never a control character.
"""

from __future__ import annotations

import math
import sys
from typing import TextIO


def format_eta(seconds: float | None) -> str:
    """``1h02m``, ``4m05s``, ``12s``; ``--`` when unknown."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "--"
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600}h{(s % 3600) // 60:02d}m"
    if s >= 60:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s}s"


def render_bar(done: int, total: int, width: int = 24) -> str:
    """``[#####.....]`` for done/total; an empty bar for total 0."""
    if total <= 0:
        return "[" + "." * width + "]"
    full = min(width, int(width * done / total))
    return "[" + "#" * full + "." * (width - full) + "]"


def status_line(st: dict) -> str:
    """One line for a ``status()`` dict."""
    done, total = int(st.get("done", 0)), int(st.get("total", 0))
    parts = [
        f"{done}/{total}",
        f"measured {st.get('measured', 0)}",
        f"skipped {st.get('skipped', 0)}",
        f"failed {st.get('failed', 0)}",
        f"ETA {format_eta(st.get('eta_s'))}",
    ]
    state = st.get("state", "")
    if state not in ("running", ""):
        parts.append(state)
    if st.get("current"):
        parts.append(f"at {st['current']}")
    return "  ".join(parts)


class Progress:
    """Progress of a run on ``stream`` (stderr by default); ``tty`` overrides detection."""

    def __init__(self, stream: TextIO | None = None, *, tty: bool | None = None, width: int = 24) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty() if tty is None else tty
        self.width = width
        self._last_key: tuple | None = None
        self._drawn = False

    def update(self, st: dict) -> None:
        if self.tty:
            line = f"\r{render_bar(int(st.get('done', 0)), int(st.get('total', 0)), self.width)} {status_line(st)}"
            self.stream.write(line.ljust(110)[:160])
            self.stream.flush()
            self._drawn = True
            return
        key = (st.get("done"), st.get("state"), st.get("skipped"), st.get("failed"))
        if key == self._last_key:
            return
        self._last_key = key
        self.stream.write(status_line(st) + "\n")
        self.stream.flush()

    def close(self) -> None:
        """End the redrawn line (TTY) so later output starts on a fresh line."""
        if self.tty and self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
