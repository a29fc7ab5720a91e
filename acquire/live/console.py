"""What a command shows on the console and what goes to a run's log file.

- :func:`display_path`: a path as the operator wants to read it — relative to the working folder
  when inside it, else absolute; never ``plans/../../runs/…``.
- :func:`console_level`: on a terminal only warnings reach the console unless ``-v`` (INFO) or
  ``-vv`` (DEBUG); off a terminal (journald, CI, a pipe) INFO goes to stderr as before.
- :class:`ConsoleFormatter`: a failure the product foresees (logged with ``extra=FORESEEN``) is
  one line on the console; its traceback goes only to the text log.
- :class:`RunLogFile`: every log record of the run (INFO and up, DEBUG with ``-vv``) into
  ``<run-id>.log`` beside the run's MCAP log. Records from before the log's folder exists (device
  connection) are held in memory and written first; if the run never gets a folder they are
  printed to stderr at the end, so a failed start-up still shows what happened.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

#: One line per record in the run's log file.
FILE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
#: At most this many records are held before the log file exists (the oldest are kept).
_BUFFER_RECORDS = 20000


def display_path(path: str | os.PathLike | None, cwd: str | os.PathLike | None = None) -> str:
    """``path`` normalised (no ``..``), relative to ``cwd`` (default: the working folder) when it
    lies inside it, else absolute; ``"-"`` for None."""
    if path is None:
        return "-"
    p = Path(os.path.abspath(os.fspath(path)))
    base = Path(os.path.abspath(os.fspath(cwd))) if cwd is not None else Path.cwd()
    try:
        return str(p.relative_to(base))
    except ValueError:
        return str(p)


def console_level(verbose: int, tty: bool) -> int:
    """Level of the console handler: WARNING on a terminal, INFO off one; ``-v`` INFO, ``-vv`` DEBUG."""
    if verbose >= 2:
        return logging.DEBUG
    if verbose == 1 or not tty:
        return logging.INFO
    return logging.WARNING


#: ``log.error(..., exc_info=exc, extra=FORESEEN)``: a failure the product foresees (too many
#: configurations failed, a device that never answered): one line on a console, the traceback
#: in the run's text log only.
FORESEEN = {"foreseen": True}


class ConsoleFormatter(logging.Formatter):
    """The console's formatter: a record marked ``FORESEEN`` is shown without its traceback,
    unless ``tracebacks`` (``-vv``: whoever debugs wants them where they look)."""

    def __init__(self, fmt: str | None = None, *, tracebacks: bool = False) -> None:
        super().__init__(fmt)
        self.tracebacks = tracebacks

    def format(self, record: logging.LogRecord) -> str:
        if self.tracebacks or not (getattr(record, "foreseen", False) and record.exc_info):
            return super().format(record)
        saved = record.exc_info, record.exc_text
        record.exc_info, record.exc_text = None, None
        try:
            return super().format(record)
        finally:
            record.exc_info, record.exc_text = saved


class ConsoleHandler(logging.StreamHandler):
    """A stderr handler that looks ``sys.stderr`` up on every record, so a live display that
    redirects stderr (rich) prints log lines above itself instead of through it."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def configure_console(verbose: int) -> ConsoleHandler:
    """Replace the root logger's handlers by one :class:`ConsoleHandler` at :func:`console_level`;
    the root logger itself passes everything the run's log file wants."""
    tty = sys.stderr.isatty()
    handler = ConsoleHandler()
    fmt = "%(levelname)s %(name)s: %(message)s"
    handler.setFormatter(ConsoleFormatter(("%(asctime)s " + fmt) if tty else fmt, tracebacks=verbose >= 2))
    handler.setLevel(console_level(verbose, tty))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose >= 2 else logging.INFO)
    return handler


class _Held(logging.Handler):
    """Keeps the first ``capacity`` records (then counts the rest) until the log file exists."""

    def __init__(self, capacity: int, level: int) -> None:
        super().__init__(level)
        self.capacity = capacity
        self.buffer: list[logging.LogRecord] = []
        self.dropped = 0

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.buffer) < self.capacity:
            self.buffer.append(record)
        else:
            self.dropped += 1


class TextLogHandler(logging.FileHandler):
    """The run's text log file. When a write fails with an ``OSError`` (disk full, I/O error) the
    file stops there without a word: no "--- Logging error ---" traceback per record from
    ``logging``. The run reports a storage problem itself, in one line (``acquire.record.logstorage``);
    ``failed`` keeps the error."""

    failed: OSError | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.failed is None:
            super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):
            self.failed = exc
        else:
            super().handleError(record)

    def close(self) -> None:
        try:
            super().close()  # flushes what the stream still holds: may fail the same way
        except OSError as exc:
            self.failed = self.failed or exc


class RunLogFile:
    """The run's text log: attach at start, :meth:`open` once the MCAP path is known, :meth:`close`.

    ``level``: the least level written (INFO; DEBUG with ``-vv``).
    """

    def __init__(self, level: int = logging.INFO) -> None:
        self.path: Path | None = None
        self._buffer = _Held(_BUFFER_RECORDS, level)
        self._file: TextLogHandler | None = None
        logging.getLogger().addHandler(self._buffer)

    def open(self, mcap_path: str | os.PathLike) -> Path:
        """Start writing ``<mcap stem>.log`` beside ``mcap_path`` (appending on a resumed run):
        what was held so far first, then every record as it comes."""
        if self._file is not None:
            return self.path  # type: ignore[return-value]
        path = Path(mcap_path).with_suffix(".log")
        handler = TextLogHandler(path, mode="a", encoding="utf-8")
        handler.setLevel(self._buffer.level)
        handler.setFormatter(logging.Formatter(FILE_FORMAT))
        root = logging.getLogger()
        root.removeHandler(self._buffer)
        for record in self._buffer.buffer:
            handler.handle(record)
        if self._buffer.dropped:
            handler.stream.write(f"({self._buffer.dropped} records before the log existed were not kept)\n")
        self._buffer.buffer.clear()
        root.addHandler(handler)
        self._file, self.path = handler, path
        return path

    def close(self, shown_level: int = logging.WARNING) -> None:
        """Detach and close the file. When the run never got a folder, print the held records
        below ``shown_level`` (those the console did not show) to stderr."""
        root = logging.getLogger()
        root.removeHandler(self._buffer)
        unseen = [r for r in self._buffer.buffer if r.levelno < shown_level]
        if self._file is None and unseen:
            fallback = logging.StreamHandler(sys.stderr)
            fallback.setFormatter(logging.Formatter(FILE_FORMAT))
            sys.stderr.write("the run made no log folder; what it logged:\n")
            for record in unseen:
                fallback.handle(record)
        self._buffer.buffer.clear()
        self._buffer.close()
        if self._file is not None:
            root.removeHandler(self._file)
            self._file.close()


def configure_logging(verbose: bool = False) -> None:
    """One line per event; colour-free when not on a terminal (journald friendly)."""
    level = logging.DEBUG if verbose else logging.INFO
    fmt = "%(levelname)s %(name)s: %(message)s"
    if sys.stderr.isatty():
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level, format=fmt, stream=sys.stderr, force=True)
    for handler in logging.getLogger().handlers:
        handler.setFormatter(ConsoleFormatter(fmt, tracebacks=verbose))  # a foreseen failure: one line unless -v
