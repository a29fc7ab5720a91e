"""A progress display for a run: a live rich bar on a terminal, plain lines otherwise.

Both take ``RunController.status()`` dicts through ``update(status)``:

- :class:`RichProgress` (a terminal): a bar with done/total, measured / skipped / failed, the
  run's own ETA (its cell-time estimate scaled by how the run has gone so far), elapsed time, the
  state, and a second line with the configuration being measured (``describe`` turns its id into
  pose, branch and joint targets). Log lines print above it.
- :class:`Progress`: one plain line per completed configuration or state change, never a control
  character (journald, CI, pipes); with ``tty=True`` a single redrawn line (no rich).

:func:`make_progress` picks one for the stream.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, Callable, TextIO


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
    if st.get("fit"):  # the end-of-run fit (``acquire.run.state.RunState.fitting``)
        parts.append(f"fit: {st['fit']['doing']} (ETA {format_eta(st['fit'].get('eta_s'))})")
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


class RichProgress:
    """A live bar on a terminal (rich). ``describe(config_id) -> str`` adds detail to the current
    configuration's line; ``console`` is a ``rich.console.Console`` (default: stderr)."""

    def __init__(self, *, describe: Callable[[str], str] | None = None, console: Any = None,
                 refresh_per_second: float = 4.0) -> None:
        from rich.console import Console
        from rich.live import Live

        self.console = console if console is not None else Console(stderr=True)
        self.describe = describe
        self._st: dict = {}
        self._t0 = time.monotonic()
        self._live = Live(self, console=self.console, refresh_per_second=refresh_per_second, transient=False,
                          redirect_stdout=False, redirect_stderr=True)
        self._live.start()

    def update(self, st: dict) -> None:
        self._st = dict(st)
        self._live.refresh()

    def __rich__(self) -> Any:
        return self.renderable()

    def renderable(self) -> Any:
        """The two lines for the last status (a rich renderable)."""
        from rich.console import Group
        from rich.progress_bar import ProgressBar
        from rich.table import Table
        from rich.text import Text

        st = self._st
        done, total = int(st.get("done", 0) or 0), int(st.get("total", 0) or 0)
        head = Table.grid(padding=(0, 1))
        head.add_column(no_wrap=True)
        head.add_column(width=32)
        head.add_column(no_wrap=True)
        state = st.get("state") or "starting"
        counts = Text.assemble(
            (f"{done}/{total}", "bold"), "  measured ", (str(st.get("measured", 0)), "green"),
            "  skipped ", (str(st.get("skipped", 0)), "yellow" if st.get("skipped") else ""),
            "  failed ", (str(st.get("failed", 0)), "red" if st.get("failed") else ""),
            "  ETA ", (format_eta(st.get("eta_s")), "cyan"),
            f"  elapsed {format_eta(time.monotonic() - self._t0)}",
        )
        head.add_row(Text(state, style="bold" if state == "running" else "yellow"),
                     ProgressBar(total=max(total, 1), completed=done if total else 0, width=32), counts)
        current = st.get("current")
        if current:
            detail = self.describe(current) if self.describe is not None else ""
            line = Text.assemble("at ", (str(current), "bold"), f"  {detail}" if detail else "")
        elif st.get("reason"):
            line = Text(f"{st['reason']}", style="yellow")
        else:
            line = Text("")
        return Group(head, line)

    def close(self) -> None:
        """Draw the last state and leave it on the screen; later output starts below."""
        self._live.stop()


def make_progress(stream: TextIO | None = None, *, describe: Callable[[str], str] | None = None):
    """:class:`RichProgress` when ``stream`` (default stderr) is a terminal, else :class:`Progress`."""
    stream = stream if stream is not None else sys.stderr
    if stream.isatty():
        return RichProgress(describe=describe)
    return Progress(stream, tty=False)
