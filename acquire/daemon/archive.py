"""The cell's side of the plant archive: finished runs offered to the station, read in chunks,
kept until the station confirms it stored them.

Operations (``acquire.daemon.control``, permission ``archive``, each one SCRAM-authenticated exchange):

``archive-list``     ``{}`` → ``{"robot_serial", "runs": [{"run_id", "finished", "files":
                     [{"name", "bytes", "sha256"}]}]}``: every run in the runs folder that is not
                     the active one and not yet confirmed (finished, aborted or failed: every run
                     is kept). ``finished``: the newest file's modification time, ISO 8601 UTC.
``archive-chunk``    ``{"run_id", "name", "offset", "size"}`` → ``{"data": base64, "offset", "eof"}``
                     at most ``MAX_CHUNK_BYTES``.
``archive-confirm``  ``{"run_id", "files", "verified"?}`` → ``{"confirmed": true}`` when ``files``
                     (what the station stored) equals the run's current listing; the run is then
                     marked ``<run>/.archived`` (JSON: station, at, the files) and no longer offered
                     — unless its files change later (a resumed run), then it is offered again.
                     ``"verified": true`` is sent later, once the station's scrub has read its
                     copy back intact: the mark gets ``verified_at``.

**Retention** (``archive_keep_days`` in the daemon's configuration; default: keep every run): a
run is deleted from the cell only when the station has confirmed it *and* re-verified its copy
(``verified_at``), its files are still those the station holds, and it was confirmed at least
``keep_days`` ago (``CellRuns.prune``, run after each confirmation). Until then the station can
fetch any file of it again (``archive-chunk`` serves confirmed runs too) to repair its copy.

sha256 of each file is cached in ``<run>/.sha256.json`` by (name, size, mtime).
"""

from __future__ import annotations

import base64
import json
import logging
import shutil
from datetime import datetime, timezone
from pathlib import Path

from acquire.daemon.control import BadRequest, Conflict
from acquire.record.digest import sha256_file

log = logging.getLogger(__name__)

#: Largest chunk one archive-chunk reply carries (bytes; base64 in JSON adds a third).
MAX_CHUNK_BYTES = 4 << 20

_MARK = ".archived"
_CACHE = ".sha256.json"


class CellRuns:
    """The runs folder seen by the station. ``robot_serial``: the serial the runs are filed under."""

    def __init__(self, runs_dir: Path, robot_serial: str, keep_days: float | None = None) -> None:
        self.runs_dir = Path(runs_dir)
        self.robot_serial = robot_serial
        self.keep_days = keep_days

    def _folder(self, run_id: object) -> Path:
        if not isinstance(run_id, str) or "/" in run_id or run_id in ("", ".", "..") or run_id.startswith("."):
            raise BadRequest(f"run_id must be a run id string, given {str(run_id)[:80]!r}")
        folder = self.runs_dir / run_id
        if not folder.is_dir():
            raise BadRequest(f"no run {run_id!r} on this cell")
        return folder

    def files(self, folder: Path) -> list[dict]:
        """[{name, bytes, sha256}] of a run folder's files (hidden files left out), by name."""
        try:
            cache = json.loads((folder / _CACHE).read_text())
        except (OSError, ValueError):
            cache = {}
        out, fresh = [], {}
        for p in sorted(folder.iterdir()):
            if not p.is_file() or p.name.startswith("."):
                continue
            st = p.stat()
            tag = f"{st.st_size}:{st.st_mtime_ns}"
            sha = cache.get(p.name, {}).get(tag) or sha256_file(p)
            fresh[p.name] = {tag: sha}
            out.append({"name": p.name, "bytes": st.st_size, "sha256": sha})
        if fresh != cache:
            try:
                (folder / _CACHE).write_text(json.dumps(fresh))
            except OSError as exc:
                log.debug("sha256 cache of %s not written: %s", folder, exc)
        return out

    def pending(self, current: str | None) -> dict:
        """The ``archive-list`` reply: runs not active and not confirmed."""
        runs = []
        if self.runs_dir.is_dir():
            for folder in sorted(p for p in self.runs_dir.iterdir() if p.is_dir()):
                if folder.name == current:
                    continue
                files = self.files(folder)
                if not files or self._confirmed(folder) == files:
                    continue  # confirmed as it is (a run resumed since then is offered again)
                newest = max((folder / f["name"]).stat().st_mtime for f in files)
                finished = datetime.fromtimestamp(newest, timezone.utc).isoformat(timespec="seconds")
                runs.append({"run_id": folder.name, "finished": finished, "files": files})
        return {"robot_serial": self.robot_serial, "runs": runs}

    @staticmethod
    def _mark(folder: Path) -> dict | None:
        try:
            mark = json.loads((folder / _MARK).read_text())
            return mark if isinstance(mark, dict) else None
        except (OSError, ValueError):
            return None

    def _confirmed(self, folder: Path) -> list | None:
        return (self._mark(folder) or {}).get("files")

    def chunk(self, request: dict, current: str | None) -> dict:
        """The ``archive-chunk`` reply."""
        folder = self._folder(request.get("run_id"))
        if folder.name == current:
            raise Conflict(f"run {folder.name} is still active; it is offered once it has ended")
        name, offset, size = request.get("name"), request.get("offset"), request.get("size", MAX_CHUNK_BYTES)
        if not isinstance(name, str) or name.startswith(".") or "/" in name or not (folder / name).is_file():
            raise BadRequest(f"run {folder.name} has no file {str(name)[:80]!r}")
        if not isinstance(offset, int) or offset < 0 or not isinstance(size, int) or not 0 < size <= MAX_CHUNK_BYTES:
            raise BadRequest(f"offset must be an integer ≥ 0 and size 1…{MAX_CHUNK_BYTES}, given {offset!r}, {size!r}")
        with open(folder / name, "rb") as f:
            f.seek(offset)
            data = f.read(size)
            eof = f.read(1) == b""
        return {"run_id": folder.name, "name": name, "offset": offset, "data": base64.b64encode(data).decode(),
                "eof": eof}

    def confirm(self, request: dict, station: str, current: str | None = None) -> dict:
        """The ``archive-confirm`` reply; marks the run archived when the station's files match."""
        folder = self._folder(request.get("run_id"))
        stored = request.get("files")
        have = self.files(folder)
        if stored != have:
            raise Conflict(f"run {folder.name}: the files the station stored do not match the cell's "
                           "(changed since they were listed?); fetch it again")
        now = datetime.now(timezone.utc).isoformat(timespec="seconds")
        before = self._mark(folder)
        if request.get("verified") is True:
            if before is None or before.get("files") != have:
                raise Conflict(f"run {folder.name} was not confirmed with these files; confirm it first")
            mark = {**before, "verified_at": now}
            log.info("run %s re-verified by %s", folder.name, station)
        else:
            mark = {"station": station, "at": now, "files": have}
            log.info("run %s confirmed archived by %s", folder.name, station)
        tmp = folder / f"{_MARK}.tmp"
        tmp.write_text(json.dumps(mark))
        tmp.replace(folder / _MARK)
        self.prune(current=current)
        return {"run_id": folder.name, "confirmed": True}

    def prune(self, now: datetime | None = None, current: str | None = None) -> list[str]:
        """Delete the runs the retention policy allows (module docstring); their ids."""
        if self.keep_days is None or not self.runs_dir.is_dir():
            return []
        now = now or datetime.now(timezone.utc)
        gone = []
        for folder in sorted(p for p in self.runs_dir.iterdir() if p.is_dir() and p.name != current):
            mark = self._mark(folder)
            if not mark or not mark.get("verified_at"):
                continue
            try:
                age = (now - datetime.fromisoformat(mark["at"])).total_seconds() / 86400.0
            except (KeyError, TypeError, ValueError):
                continue
            if age < self.keep_days or mark.get("files") != self.files(folder):
                continue
            shutil.rmtree(folder)
            gone.append(folder.name)
            log.info("run %s deleted: archived by %s and re-verified %s, kept %.0f days (archive_keep_days %g)",
                     folder.name, mark.get("station"), mark["verified_at"], age, self.keep_days)
        return gone
