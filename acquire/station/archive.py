"""The station's archive: every finished run's files by robot serial and date, verified.

Layout under the archive root::

    <serial>/<YYYY-MM-DD>/<run-id>/          the run's files (MCAP log segments, result.json,
                                             report.html, the run's .log) and manifest.json
    <serial>/history.jsonl                   the robot's calibration history (acquire.station.history)
    .index/<site>~<cell>~<run-id>.json       which folder holds a run (idempotence)
    .incoming/<site>~<cell>~<run-id>/        transfers under way: <name>.part, appended chunk by chunk

``manifest.json``: ``{"format": "remaster.archive/1", "run_id", "site", "cell", "robot_serial",
"finished", "archived_at", "files": [{"name", "bytes", "sha256"}]}``.

A transfer is resumable: ``Transfer.offset(name)`` is how many bytes of a file are already here
(the partial file survives a restart of the station); ``write`` appends a chunk at exactly that
offset. ``finish`` checks every file's size and sha256 against what the cell announced before
anything enters the archive, then moves the folder in and writes the manifest and the index
entry. Storing a run that is already archived (a re-send after a lost confirmation) is a no-op
that returns the stored manifest, provided the checksums agree. A run archived before with other
content (resumed on the cell after it was confirmed) is stored beside the earlier copy as
``<run-id>.v2`` (``.v3`` …; ``"version"`` in its manifest), which the index then names.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

FORMAT = "remaster.archive/1"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")


class ArchiveError(ValueError):
    """What a cell announced or sent does not fit the archive (bad name, offset, checksum)."""


def _check_name(what: str, value: str) -> str:
    if not isinstance(value, str) or not _NAME_RE.match(value) or value in (".", ".."):
        raise ArchiveError(f"{what} {value!r} is not allowed: use letters, digits, '_', '.', '-'")
    return value


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


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
        if not isinstance(size, int) or size < 0:
            raise ArchiveError(f"files[{i}].bytes must be an integer ≥ 0, given {size!r}")
        if not isinstance(sha, str) or not _SHA_RE.match(sha):
            raise ArchiveError(f"files[{i}].sha256 must be 64 lowercase hex digits, given {sha!r:.80}")
        if name in seen or name == "manifest.json":
            raise ArchiveError(f"files[{i}].name {name!r} is repeated or reserved")
        seen.add(name)
        out.append({"name": name, "bytes": size, "sha256": sha})
    return out


class Transfer:
    """One run's files arriving in ``.incoming/`` (see the module docstring)."""

    def __init__(self, archive: "Archive", ref: RunRef, files: list[dict], finished: str) -> None:
        self.archive = archive
        self.ref = ref
        self.files = {f["name"]: f for f in check_files(files)}
        self.finished = finished
        self.folder = archive.root / ".incoming" / ref.tag
        self.folder.mkdir(parents=True, exist_ok=True)
        announced = self.folder / "announced.json"
        if announced.exists():
            before = json.loads(announced.read_text())
            if before != sorted(self.files.values(), key=lambda f: f["name"]):
                # The cell re-announced different content (e.g. a resumed run grew): start over.
                shutil.rmtree(self.folder)
                self.folder.mkdir(parents=True)
        announced.write_text(json.dumps(sorted(self.files.values(), key=lambda f: f["name"])))

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

    def write(self, name: str, offset: int, data: bytes) -> int:
        """Append ``data`` at ``offset`` (must equal ``offset(name)``); returns the new size."""
        have = self.offset(name)
        if offset != have:
            raise ArchiveError(f"chunk of {name!r} at offset {offset}, but {have} bytes are here; resume at {have}")
        if have + len(data) > self.files[name]["bytes"]:
            raise ArchiveError(f"chunk of {name!r} runs past its announced size {self.files[name]['bytes']}")
        with open(self._part(name), "ab") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        return have + len(data)

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
        manifest = {
            "format": FORMAT, "run_id": self.ref.run_id, "site": self.ref.site, "cell": self.ref.cell,
            "robot_serial": self.ref.robot_serial, "finished": self.finished,
            "archived_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "files": sorted(self.files.values(), key=lambda f: f["name"]),
        }
        return self.archive._commit(self, manifest)


class Archive:
    """The archive folder tree (see the module docstring). ``root`` is created if missing."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        (self.root / ".index").mkdir(parents=True, exist_ok=True)
        (self.root / ".incoming").mkdir(parents=True, exist_ok=True)

    def _index(self, ref: RunRef) -> Path:
        return self.root / ".index" / f"{ref.tag}.json"

    def manifest(self, ref: RunRef) -> dict | None:
        """The stored manifest of a run, or None when it is not archived."""
        idx = self._index(ref)
        if not idx.exists():
            return None
        folder = self.root / json.loads(idx.read_text())["folder"]
        return json.loads((folder / "manifest.json").read_text())

    def folder(self, manifest: dict) -> Path:
        day = manifest["finished"][:10]
        version = manifest.get("version", 1)
        name = manifest["run_id"] if version == 1 else f"{manifest['run_id']}.v{version}"
        return self.root / manifest["robot_serial"] / day / name

    def begin(self, ref: RunRef, files: list[dict], finished: str) -> Transfer:
        """A transfer of ``files`` (announced by the cell: name, bytes, sha256) for ``ref``.

        ``finished``: when the run ended (ISO 8601 UTC), which sets the date folder."""
        try:
            datetime.fromisoformat(finished)
        except (TypeError, ValueError):
            raise ArchiveError(f"finished must be an ISO 8601 time, given {finished!r:.80}") from None
        return Transfer(self, ref, files, finished)

    def _commit(self, transfer: Transfer, manifest: dict) -> dict:
        ref = transfer.ref
        stored = self.manifest(ref)
        if stored is not None:
            if stored["files"] == manifest["files"]:
                shutil.rmtree(transfer.folder, ignore_errors=True)
                return stored
            manifest["version"] = stored.get("version", 1) + 1  # kept beside the earlier copy
        dest = self.folder(manifest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        if dest.exists():  # a commit interrupted between move and index: redo it
            shutil.rmtree(dest)
        tmp = transfer.folder
        (tmp / "announced.json").unlink()
        for name in transfer.files:
            (tmp / f"{name}.part").rename(tmp / name)
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1))
        tmp.rename(dest)
        idx = self._index(ref)
        idx.with_suffix(".tmp").write_text(json.dumps({"folder": str(dest.relative_to(self.root))}))
        idx.with_suffix(".tmp").replace(idx)
        return manifest

    def is_complete(self, ref: RunRef, files: list[dict]) -> bool:
        """Whether ``ref`` is archived with exactly these files (a re-send needs no transfer)."""
        stored = self.manifest(ref)
        return stored is not None and stored["files"] == sorted(check_files(files), key=lambda f: f["name"])

    def verify(self, manifest: dict) -> list[str]:
        """Problems of a stored run (missing file, wrong size or sha256); empty when intact."""
        folder = self.folder(manifest)
        problems = []
        for f in manifest["files"]:
            p = folder / f["name"]
            if not p.is_file():
                problems.append(f"{p}: missing")
            elif p.stat().st_size != f["bytes"] or sha256_file(p) != f["sha256"]:
                problems.append(f"{p}: content does not match the manifest's sha256")
        return problems

    def manifests(self) -> list[dict]:
        """Every archived run's manifest, oldest first."""
        out = []
        for idx in sorted((self.root / ".index").glob("*.json")):
            folder = self.root / json.loads(idx.read_text())["folder"]
            out.append(json.loads((folder / "manifest.json").read_text()))
        return sorted(out, key=lambda m: (m["finished"], m["run_id"]))
