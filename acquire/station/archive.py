"""The station's archive: every finished run's files by robot serial and date, verified.

Layout under the archive root::

    <serial>/<YYYY-MM-DD>/<run-id>/          the run's files (MCAP log segments, result.json,
                                             report.html, the run's .log) and manifest.json
    <serial>/history.jsonl                   the robot's calibration history (acquire.station.history)
    .index/<site>~<cell>~<run-id>.json       which folder holds a run, its scrub state
    .incoming/<site>~<cell>~<run-id>/        transfers under way: <name>.part, appended chunk by chunk
    .quarantine/<serial>/<day>/<run-id>/     copies the scrub found bad (``<name>.<UTC time>``)

``manifest.json``: ``{"format": "remaster.archive/1", "run_id", "site", "cell", "robot_serial",
"finished", "archived_at", "files": [{"name", "bytes", "sha256"}]}``. The index entry:
``{"folder", "verified_at"?, "damaged"?: [names quarantined, to fetch again], "told_verified"?}``.

A transfer is resumable: ``Transfer.offset(name)`` is how many bytes of a file are already here
(the partial file survives a restart of the station); ``write`` appends a chunk at exactly that
offset. ``finish`` checks every file's size and sha256 against what the cell announced before
anything enters the archive, then moves the folder in and writes the manifest and the index
entry.

**An archived run is never replaced.** Storing a run that is already archived with the same
files (a re-send after a lost confirmation) is a no-op that returns the stored manifest. A run
archived before with other content (resumed on the cell after it was confirmed) is stored
*beside* the earlier copy as ``<run-id>.v2`` (``.v3`` …; ``"version"`` in its manifest), which
the index then names. A folder that already holds another run is never removed or written into:
the transfer is refused (``ArchiveRefused``) and logged.

**Limits** (``Limits``): each announced file at most ``max_file_bytes``, a run at most
``max_run_bytes``, and the archive's file system keeps ``reserve_free_bytes`` free after every
transfer under way has received what it announced — checked when a run is announced, before any
byte is fetched, and again before each chunk is written (``ArchiveFull``).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from acquire.record.digest import sha256_file

log = logging.getLogger(__name__)

FORMAT = "remaster.archive/1"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
GiB = 1 << 30


class ArchiveError(ValueError):
    """What a cell announced or sent does not fit the archive (bad name, offset, checksum)."""


class ArchiveRefused(ArchiveError):
    """The run would replace or write into a run already archived: refused, nothing changed."""


class ArchiveFull(ArchiveError):
    """A size limit or the free-space reserve refuses the run (``Limits``)."""


def _check_name(what: str, value: str) -> str:
    if not isinstance(value, str) or not _NAME_RE.match(value) or value in (".", ".."):
        raise ArchiveError(f"{what} {value!r} is not allowed: use letters, digits, '_', '.', '-'")
    return value


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


@dataclass(frozen=True)
class Limits:
    """Size limits of one run (bytes) and the free space the archive's file system keeps."""

    max_file_bytes: int = 16 * GiB
    max_run_bytes: int = 32 * GiB
    reserve_free_bytes: int = 2 * GiB

    def __post_init__(self) -> None:
        for name in ("max_file_bytes", "max_run_bytes", "reserve_free_bytes"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 0:
                raise ValueError(f"Limits.{name} must be an integer ≥ 0 (bytes), given {getattr(self, name)!r}")


@dataclass(frozen=True)
class RunRef:
    """Which run: the cell's site (or "" without one), cell id, run id; and the robot's serial."""

    site: str
    cell: str
    run_id: str
    robot_serial: str

    def __post_init__(self) -> None:
        if self.site:
            _check_name("site", self.site)
        _check_name("cell", self.cell)
        _check_name("run_id", self.run_id)
        _check_name("robot_serial", self.robot_serial)

    @property
    def tag(self) -> str:
        return f"{self.site or '-'}~{self.cell}~{self.run_id}"

    @classmethod
    def of(cls, manifest: dict) -> "RunRef":
        return cls(manifest["site"], manifest["cell"], manifest["run_id"], manifest["robot_serial"])


def check_files(files: list[dict]) -> list[dict]:
    """The announced files [{name, bytes, sha256}], validated (ArchiveError naming the field)."""
    if not isinstance(files, list) or not files:
        raise ArchiveError(f"a run needs a non-empty list of files, given {files!r:.80}")
    out, seen = [], set()
    for i, f in enumerate(files):
        if not isinstance(f, dict):
            raise ArchiveError(f"files[{i}] must be an object {{name, bytes, sha256}}")
        name = _check_name(f"files[{i}].name", f.get("name"))
        size, sha = f.get("bytes"), f.get("sha256")
        if not isinstance(size, int) or isinstance(size, bool) or size < 0:
            raise ArchiveError(f"files[{i}].bytes must be an integer ≥ 0, given {size!r}")
        if not isinstance(sha, str) or not _SHA_RE.match(sha):
            raise ArchiveError(f"files[{i}].sha256 must be 64 lowercase hex digits, given {sha!r:.80}")
        if name in seen or name == "manifest.json":
            raise ArchiveError(f"files[{i}].name {name!r} is repeated or reserved")
        seen.add(name)
        out.append({"name": name, "bytes": size, "sha256": sha})
    return sorted(out, key=lambda f: f["name"])


class Transfer:
    """One run's files arriving in ``.incoming/`` (see the module docstring). ``repair``: the
    stored manifest when the transfer fetches quarantined files of an archived run again."""

    def __init__(self, archive: "Archive", ref: RunRef, files: list[dict], finished: str,
                 repair: dict | None = None) -> None:
        self.archive = archive
        self.ref = ref
        self.files = {f["name"]: f for f in check_files(files)}
        self.finished = finished
        self.repair = repair
        self.folder = archive.root / ".incoming" / (ref.tag + (".repair" if repair else ""))
        self.folder.mkdir(parents=True, exist_ok=True)
        announced = self.folder / "announced.json"
        listing = sorted(self.files.values(), key=lambda f: f["name"])
        if announced.exists() and json.loads(announced.read_text()) != listing:
            # The cell re-announced different content (e.g. a resumed run grew): start over.
            shutil.rmtree(self.folder)
            self.folder.mkdir(parents=True)
        announced.write_text(json.dumps(listing))

    def _part(self, name: str) -> Path:
        if name not in self.files:
            raise ArchiveError(f"file {name!r} was not announced for run {self.ref.run_id}; announced: "
                               f"{sorted(self.files)}")
        return self.folder / f"{name}.part"

    def offset(self, name: str) -> int:
        """Bytes of ``name`` already received (resume from here)."""
        p = self._part(name)
        return p.stat().st_size if p.exists() else 0

    def missing(self) -> dict[str, int]:
        """{name: offset} of the files not yet complete."""
        return {n: self.offset(n) for n, f in self.files.items() if self.offset(n) < f["bytes"]}

    def remaining(self) -> int:
        """Bytes announced and not yet received."""
        return sum(f["bytes"] - min(self.offset(n), f["bytes"]) for n, f in self.files.items())

    def write(self, name: str, offset: int, data: bytes) -> int:
        """Append ``data`` at ``offset`` (must equal ``offset(name)``); returns the new size."""
        have = self.offset(name)
        if offset != have:
            raise ArchiveError(f"chunk of {name!r} at offset {offset}, but {have} bytes are here; resume at {have}")
        if have + len(data) > self.files[name]["bytes"]:
            raise ArchiveError(f"chunk of {name!r} runs past its announced size {self.files[name]['bytes']}")
        self.archive.check_free(len(data), f"{self.ref.run_id}/{name}")
        with open(self._part(name), "ab") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        return have + len(data)

    def close(self) -> None:
        """The transfer stops (finished, failed or refused): its bytes no longer count as expected."""
        self.archive._transfers.pop(self.folder.name, None)

    def finish(self) -> dict:
        """Verify every file (size and sha256), move the run into the archive; its manifest.

        A file whose checksum does not match is deleted (it is fetched again from the start)
        and ArchiveError says which.
        """
        for name, f in self.files.items():
            part = self._part(name)
            size = self.offset(name)
            if size != f["bytes"]:
                raise ArchiveError(f"{name}: {size} of {f['bytes']} bytes received; resume at {size}")
            digest = sha256_file(part)
            if digest != f["sha256"]:
                part.unlink()
                raise ArchiveError(f"{name}: sha256 {digest} does not match the announced {f['sha256']}; "
                                   "the file is fetched again")
        try:
            if self.repair is not None:
                return self.archive._restore(self)
            manifest = {
                "format": FORMAT, "run_id": self.ref.run_id, "site": self.ref.site, "cell": self.ref.cell,
                "robot_serial": self.ref.robot_serial, "finished": self.finished, "archived_at": _now(),
                "files": sorted(self.files.values(), key=lambda f: f["name"]),
            }
            return self.archive._commit(self, manifest)
        finally:
            self.close()


class Archive:
    """The archive folder tree (see the module docstring). ``root`` is created if missing."""

    def __init__(self, root: Path | str, limits: Limits = Limits()) -> None:
        self.root = Path(root)
        self.limits = limits
        for sub in (".index", ".incoming"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._transfers: dict[str, Transfer] = {}   # open transfers by folder name
        self._lock = threading.Lock()               # commits and index updates

    # ------------------------------------------------------------------ index
    def _index(self, ref: RunRef) -> Path:
        return self.root / ".index" / f"{ref.tag}.json"

    def index_entry(self, ref: RunRef) -> dict | None:
        idx = self._index(ref)
        return json.loads(idx.read_text()) if idx.exists() else None

    def _write_index(self, ref: RunRef, entry: dict) -> None:
        idx = self._index(ref)
        tmp = idx.with_suffix(".tmp")
        tmp.write_text(json.dumps(entry))
        tmp.replace(idx)

    def update_index(self, ref: RunRef, **fields) -> dict:
        """Set (value) or drop (None) fields of a run's index entry; returns it."""
        with self._lock:
            entry = self.index_entry(ref)
            if entry is None:
                raise ArchiveError(f"run {ref.tag} is not archived")
            for k, v in fields.items():
                if v is None:
                    entry.pop(k, None)
                else:
                    entry[k] = v
            self._write_index(ref, entry)
            return entry

    def manifest(self, ref: RunRef) -> dict | None:
        """The stored manifest of a run, or None when it is not archived."""
        entry = self.index_entry(ref)
        if entry is None:
            return None
        return json.loads((self.root / entry["folder"] / "manifest.json").read_text())

    def folder(self, manifest: dict) -> Path:
        day = manifest["finished"][:10]
        version = manifest.get("version", 1)
        name = manifest["run_id"] if version == 1 else f"{manifest['run_id']}.v{version}"
        return self.root / manifest["robot_serial"] / day / name

    # ------------------------------------------------------------------ limits
    def free_bytes(self) -> int:
        """Bytes free to an unprivileged writer on the archive's file system."""
        st = os.statvfs(self.root)
        return st.f_bavail * st.f_frsize

    def expected_bytes(self) -> int:
        """Bytes the open transfers have announced and not yet received."""
        with self._lock:
            transfers = list(self._transfers.values())
        return sum(t.remaining() for t in transfers)

    def check_free(self, nbytes: int, what: str) -> None:
        """ArchiveFull unless ``nbytes`` more leave the reserve free (beside the open transfers)."""
        free, reserve = self.free_bytes(), self.limits.reserve_free_bytes
        if free - nbytes < reserve:
            raise ArchiveFull(f"{what}: {nbytes} bytes would leave {free - nbytes} of the {reserve} bytes the "
                              f"archive keeps free (limits.reserve_free_bytes) on {self.root}; free space, "
                              "then the transfer resumes")

    def _check_limits(self, ref: RunRef, files: list[dict], already: int) -> None:
        lim = self.limits
        for f in files:
            if f["bytes"] > lim.max_file_bytes:
                raise ArchiveFull(f"run {ref.run_id} of cell {ref.cell}: file {f['name']} announced with "
                                  f"{f['bytes']} bytes, over limits.max_file_bytes {lim.max_file_bytes}; refused "
                                  "before any byte was fetched")
        total = sum(f["bytes"] for f in files)
        if total > lim.max_run_bytes:
            raise ArchiveFull(f"run {ref.run_id} of cell {ref.cell}: {total} bytes announced, over "
                              f"limits.max_run_bytes {lim.max_run_bytes}; refused before any byte was fetched")
        self.check_free(total - already + self.expected_bytes(), f"run {ref.run_id} of cell {ref.cell}")

    # ------------------------------------------------------------------ transfers
    def begin(self, ref: RunRef, files: list[dict], finished: str) -> Transfer:
        """A transfer of ``files`` (announced by the cell: name, bytes, sha256) for ``ref``.

        ``finished``: when the run ended (ISO 8601 UTC), which sets the date folder. Size limits
        and the free-space reserve are checked here, before any byte is fetched (ArchiveFull)."""
        try:
            datetime.fromisoformat(finished)
        except (TypeError, ValueError):
            raise ArchiveError(f"finished must be an ISO 8601 time, given {finished!r:.80}") from None
        checked = check_files(files)
        partial = self.root / ".incoming" / ref.tag
        already = sum((partial / f"{f['name']}.part").stat().st_size for f in checked
                      if (partial / f"{f['name']}.part").is_file())
        self._check_limits(ref, checked, already)
        self._destination(ref, checked, finished)   # a folder held by another run: refused before any byte
        return self._open(Transfer(self, ref, checked, finished))

    def _open(self, transfer: Transfer) -> Transfer:
        with self._lock:
            self._transfers[transfer.folder.name] = transfer
        return transfer

    def _destination(self, ref: RunRef, files: list[dict], finished: str) -> tuple[Path, int, dict | None]:
        """(folder, version, stored manifest) a run with these files would be stored in; ArchiveRefused
        when that folder already holds another run (it is never removed or written into)."""
        stored = self.manifest(ref)
        version = 1 if stored is None else (stored.get("version", 1) if stored["files"] == files
                                            else stored.get("version", 1) + 1)
        dest = self.folder({"run_id": ref.run_id, "finished": finished, "robot_serial": ref.robot_serial,
                            "version": version})
        held = _read_json(dest / "manifest.json") if dest.exists() else None
        if dest.exists() and not (held is not None and RunRef.of(held) == ref and held["files"] == files):
            who = f"run {held['run_id']} of cell {held['site'] or '-'}/{held['cell']}" if held else "other files"
            log.error("refused run %s of cell %s: %s already holds %s; an archived run is never replaced",
                      ref.run_id, _cell_name(ref), dest, who)
            raise ArchiveRefused(f"{dest} already holds {who}; an archived run is never replaced "
                                 f"(run {ref.run_id} of cell {_cell_name(ref)} refused, nothing changed)")
        return dest, version, stored

    def _commit(self, transfer: Transfer, manifest: dict) -> dict:
        ref = transfer.ref
        with self._lock:
            try:
                dest, version, stored = self._destination(ref, manifest["files"], manifest["finished"])
            except ArchiveRefused:
                shutil.rmtree(transfer.folder, ignore_errors=True)
                raise
            if stored is not None and stored["files"] == manifest["files"]:
                shutil.rmtree(transfer.folder, ignore_errors=True)   # a re-send of what is stored
                return stored
            if version > 1:
                manifest["version"] = version   # kept beside the earlier copy
            if dest.exists():   # this very run, moved in before its index was written: finish that
                shutil.rmtree(transfer.folder, ignore_errors=True)
                self._write_index(ref, {"folder": str(dest.relative_to(self.root))})
                return json.loads((dest / "manifest.json").read_text())
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp = transfer.folder
            (tmp / "announced.json").unlink()
            for name in transfer.files:
                (tmp / f"{name}.part").rename(tmp / name)
            (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1))
            tmp.rename(dest)
            self._write_index(ref, {"folder": str(dest.relative_to(self.root))})
            return manifest

    def begin_repair(self, manifest: dict) -> Transfer | None:
        """A transfer of an archived run's quarantined files (None: nothing to fetch again)."""
        ref = RunRef.of(manifest)
        damaged = set((self.index_entry(ref) or {}).get("damaged", []))
        files = [f for f in manifest["files"] if f["name"] in damaged]
        if not files:
            return None
        self.check_free(sum(f["bytes"] for f in files) + self.expected_bytes(), f"repair of run {ref.run_id}")
        return self._open(Transfer(self, ref, files, manifest["finished"], repair=manifest))

    def _restore(self, transfer: Transfer) -> dict:
        """Move fetched-again files (their sha256 is the manifest's) into the run's folder."""
        manifest = transfer.repair
        dest = self.folder(manifest)
        with self._lock:
            for name in transfer.files:
                if (dest / name).exists():   # only a quarantined (moved-away) file is ever written
                    raise ArchiveRefused(f"{dest / name} exists; an archived file is never replaced")
                (transfer.folder / f"{name}.part").rename(dest / name)
            shutil.rmtree(transfer.folder, ignore_errors=True)
            entry = self.index_entry(RunRef.of(manifest))
            entry.pop("damaged", None)
            entry["repaired_at"] = _now()
            self._write_index(RunRef.of(manifest), entry)
        log.warning("run %s (robot %s): %s fetched again from cell %s and verified", manifest["run_id"],
                    manifest["robot_serial"], ", ".join(sorted(transfer.files)), manifest["cell"])
        return manifest

    def is_complete(self, ref: RunRef, files: list[dict]) -> bool:
        """Whether ``ref`` is archived with exactly these files (a re-send needs no transfer)."""
        stored = self.manifest(ref)
        return stored is not None and stored["files"] == check_files(files)

    # ------------------------------------------------------------------ reading back
    def verify(self, manifest: dict) -> list[str]:
        """Problems of a stored run (missing file, wrong size or sha256); empty when intact."""
        return [f"{self.folder(manifest) / name}: {why}" for name, why in self.damage(manifest)]

    def damage(self, manifest: dict) -> list[tuple[str, str]]:
        """(file name, what is wrong) per file of a stored run that is missing or differs."""
        folder = self.folder(manifest)
        out = []
        for f in manifest["files"]:
            p = folder / f["name"]
            if not p.is_file():
                out.append((f["name"], "missing"))
            elif p.stat().st_size != f["bytes"]:
                out.append((f["name"], f"{p.stat().st_size} bytes, the manifest says {f['bytes']}"))
            elif sha256_file(p) != f["sha256"]:
                out.append((f["name"], "content does not match the manifest's sha256"))
        return out

    def quarantine(self, manifest: dict, names: list[str]) -> list[Path]:
        """Move the named (bad) files of a stored run to ``.quarantine/`` and mark them in the index
        as to be fetched again; returns where they went."""
        folder = self.folder(manifest)
        qdir = self.root / ".quarantine" / folder.relative_to(self.root)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        moved = []
        with self._lock:
            qdir.mkdir(parents=True, exist_ok=True)
            for name in names:
                if (folder / name).exists():
                    dest = qdir / f"{name}.{stamp}"
                    (folder / name).rename(dest)
                    moved.append(dest)
            ref = RunRef.of(manifest)
            entry = self.index_entry(ref)
            entry["damaged"] = sorted(set(entry.get("damaged", [])) | set(names))
            entry.pop("verified_at", None)
            self._write_index(ref, entry)
        return moved

    def manifests(self) -> list[dict]:
        """Every archived run's manifest, oldest first."""
        out = []
        for idx in sorted((self.root / ".index").glob("*.json")):
            folder = self.root / json.loads(idx.read_text())["folder"]
            out.append(json.loads((folder / "manifest.json").read_text()))
        return sorted(out, key=lambda m: (m["finished"], m["run_id"]))


def _cell_name(ref: RunRef) -> str:
    return f"{ref.site}/{ref.cell}" if ref.site else ref.cell


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None
