"""The run log's file on disk: whole writes, a space reserve, and a clean stop when the disk is full.

A run log (``acquire.record.recorder.RunLog``) writes its MCAP bytes through :class:`LogFile`, an
unbuffered file whose every ``write`` either reaches the OS whole or raises :class:`StorageError`
(a short write, ENOSPC, EDQUOT, EIO, …). What happens on such an error, once:

1. the free space of the file system is measured (for the message);
2. the **reserve** is released: a file ``<log>.reserve`` beside the log, allocated
   (``posix_fallocate``) at twice the size the log's MCAP summary would take (at least
   ``RESERVE_MIN_BYTES``) and grown as the log grows, so that there is room to finish the log;
3. the log is **sealed**: read back unit by unit (``acquire.record.mcapfile.scan``), cut after its last
   complete unit (a chunk with all its message indexes, or a record outside chunks), and given
   DataEnd + summary + Footer (``finish_truncated``) — an indexed MCAP file that every reader
   opens, holding every record that was completely written. If even that cannot be written,
   the file is cut after its last complete unit and ``--resume`` finishes it later;
4. the error is kept: every later write raises the same :class:`StorageError` at once, so a
   caller cannot go on as if the record were stored.

``StorageError`` is deliberately *not* an ``OSError``: the run loop's "log it and carry on"
handlers (``except OSError``) must not swallow it. Its message is one line naming the file,
the system's reason and the space left.
"""

from __future__ import annotations

import errno
import io
import logging
import os
import shutil
from pathlib import Path

from acquire.record.mcapfile import McapIndex, finish_truncated, scan

log = logging.getLogger(__name__)

#: The smallest reserve kept beside a log (bytes): room for the summary of ~2000 chunks.
RESERVE_MIN_BYTES = 256 * 1024
RESERVE_SUFFIX = ".reserve"

# The system calls, named so that a test can stand in for a full disk (tests/acquire/test_run_disk_full.py).
_write = os.write
_fallocate = os.posix_fallocate
_unlink = os.unlink


class StorageError(Exception):
    """The run log could not be written (disk full, quota, I/O error). One line: file, reason,
    space free, and what became of the log. Attributes: ``path``, ``errno``, ``free_bytes``
    (None if unknown), ``sealed`` (the log was closed readable at its last complete record)."""

    def __init__(self, path: Path, cause: OSError, free_bytes: int | None, sealed: bool, kept_bytes: int) -> None:
        self.path, self.errno, self.free_bytes, self.sealed = path, cause.errno, free_bytes, sealed
        free = "free space unknown" if free_bytes is None else f"{human_bytes(free_bytes)} free on its file system"
        kept = (f"the log is closed at its last complete record ({human_bytes(kept_bytes)}, readable)" if sealed else
                f"the log ends at its last complete record ({human_bytes(kept_bytes)}); --resume completes it")
        super().__init__(f"cannot write the run log {path}: {cause.strerror or cause} ({free}); {kept}")


def human_bytes(n: int) -> str:
    """``n`` bytes as ``512 B``, ``12.3 kB``, ``4.0 MB``, ``1.2 GB`` (powers of 1000)."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n} B"


def summary_bytes(index: McapIndex) -> int:
    """An upper estimate (bytes) of the MCAP summary + footer that ``index`` makes."""
    per_record = 120 + 12 * len(index.channels)  # a chunk index lists every channel's message-index offset
    n = len(index.chunk_indexes) + len(index.attachment_indexes) + len(index.metadata_indexes)
    schemas = sum(len(s.data) + len(s.name) + 64 for s in index.schemas.values())
    channels = sum(len(c.topic) + 64 + sum(len(k) + len(v) + 8 for k, v in c.metadata.items()) for c in index.channels.values())
    return 4096 + n * per_record + schemas + channels + 16 * len(index.channels)


def _write_all(fd: int, data: bytes) -> int:
    view = memoryview(data).cast("B")
    while view:
        n = _write(fd, view)
        view = view[n:]
    return len(data)


class _WholeWrites(io.FileIO):
    """A raw file whose ``write`` writes everything or raises (used to seal a log)."""

    def write(self, data) -> int:  # type: ignore[override]
        return _write_all(self.fileno(), data)


class LogFile(io.FileIO):
    """The run log's file, created exclusively at ``path`` (``FileExistsError`` if it exists).

    Unbuffered: ``write`` hands the bytes to the OS before it returns; ``flush`` does nothing;
    ``fsync`` syncs. Any ``OSError`` from writing, syncing or growing the reserve seals the log
    and raises :class:`StorageError` (see the module text), as does every call after it.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(str(path), "x")
        self.path = Path(path)
        self.reserve_path = self.path.with_name(self.path.name + RESERVE_SUFFIX)
        self.error: StorageError | None = None
        self._reserved = 0

    def write(self, data) -> int:  # type: ignore[override]
        if self.error is not None:
            raise self.error
        try:
            return _write_all(self.fileno(), data)
        except OSError as exc:
            raise self._fail(exc) from None

    def fsync(self) -> None:
        if self.error is not None:
            raise self.error
        try:
            os.fsync(self.fileno())
        except OSError as exc:
            raise self._fail(exc) from None

    def ensure_reserve(self, need: int) -> None:
        """Keep at least ``need`` bytes (the log's summary estimate, ``summary_bytes``) reserved,
        twice that when it grows; ``StorageError`` if the disk has no room for it."""
        if self.error is not None or (self._reserved and need <= self._reserved // 2):
            return
        size = max(RESERVE_MIN_BYTES, 2 * need)
        try:
            fd = os.open(self.reserve_path, os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                _fallocate(fd, 0, size)
            finally:
                os.close(fd)
        except OSError as exc:
            if exc.errno in (errno.EOPNOTSUPP, errno.EINVAL):  # no preallocation here: go on without a reserve
                log.debug("%s: no space reserve (%s)", self.reserve_path, exc)
                self._reserved = size
                return
            raise self._fail(exc) from None
        self._reserved = size

    @staticmethod
    def release_stale_reserve(log_path: str | os.PathLike) -> None:
        """Remove the reserve a killed writer left beside ``log_path`` (if any)."""
        Path(str(log_path) + RESERVE_SUFFIX).unlink(missing_ok=True)

    def release_reserve(self) -> None:
        """Give the reserve's space back (before writing the summary, and on close)."""
        try:
            _unlink(self.reserve_path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.debug("%s: cannot remove the reserve: %s", self.reserve_path, exc)
        self._reserved = 0

    def _fail(self, cause: OSError) -> StorageError:
        try:
            free: int | None = shutil.disk_usage(self.path.parent).free
        except OSError:
            free = None
        self.release_reserve()
        sealed, kept = self._seal()
        self.error = StorageError(self.path, cause, free, sealed, kept)
        return self.error

    def _seal(self) -> tuple[bool, int]:
        """Cut after the last complete unit and finish the file; (finished?, bytes kept)."""
        kept = 0
        try:
            with _WholeWrites(str(self.path), "r+") as fh:
                res = scan(fh, os.fstat(fh.fileno()).st_size, where=str(self.path))
                kept = res.data_end_start if res.data_end_start is not None else res.good_end
                try:
                    finish_truncated(fh, res)
                    os.fsync(fh.fileno())
                    return True, kept
                except OSError as exc:
                    log.debug("%s: cannot finish the log: %s", self.path, exc)
                    fh.truncate(kept)
                    return False, kept
        except (OSError, ValueError) as exc:
            log.debug("%s: cannot seal the log: %s", self.path, exc)
            return False, kept

    def close(self) -> None:
        """Close the file and release the reserve; never raises after a storage error."""
        try:
            super().close()
        except OSError:
            if self.error is None:
                raise
        finally:
            self.release_reserve()
