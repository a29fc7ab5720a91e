"""The archive checks itself: every stored file's size and sha256 read back against its manifest.

``scrub(archive)`` walks every archived run (``acquire station verify``, and the station every
``scrub_hours``):

- an intact run gets ``verified_at`` in its index entry — the station then tells its cell
  (``archive-confirm`` with ``"verified": true``), and only a run the station re-verified may be
  deleted by the cell's retention policy (``acquire.daemon.archive``);
- a missing, truncated or altered file is reported, moved to ``.quarantine/`` (never deleted:
  it is evidence) and marked ``damaged`` in the index; the station fetches it again from the
  cell that sent it on its next sync with that cell (``Station.sync_cell``), verifies it against
  the manifest's sha256 and puts it back. A cell that no longer has the run cannot repair it: the
  run stays ``damaged`` and every scrub reports it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timezone

from acquire.station.archive import Archive, RunRef

log = logging.getLogger(__name__)


@dataclass
class ScrubReport:
    """What one pass found. ``damaged``: (run tag, file, what is wrong) found now and quarantined;
    ``awaiting``: (run tag, files) quarantined earlier and not yet fetched again."""

    runs: int = 0
    bytes: int = 0
    verified: int = 0
    damaged: list[tuple[str, str, str]] = field(default_factory=list)
    awaiting: list[tuple[str, list[str]]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.damaged and not self.awaiting

    def lines(self) -> list[str]:
        out = [f"{self.runs} run(s), {self.bytes} bytes read back: {self.verified} intact, "
               f"{len({d[0] for d in self.damaged})} damaged now, {len(self.awaiting)} awaiting a copy from their cell"]
        out += [f"DAMAGED {tag}: {name}: {why} (quarantined; fetched again from the cell)"
                for tag, name, why in self.damaged]
        out += [f"AWAITING {tag}: {', '.join(names)} (quarantined earlier; the cell has not sent it again yet)"
                for tag, names in self.awaiting]
        return out


def scrub(archive: Archive) -> ScrubReport:
    """Read back every archived run; quarantine what differs from its manifest (module docstring)."""
    report = ScrubReport()
    for manifest in archive.manifests():
        ref = RunRef.of(manifest)
        entry = archive.index_entry(ref) or {}
        report.runs += 1
        already = set(entry.get("damaged", []))
        found = [(name, why) for name, why in archive.damage(manifest) if name not in already]
        report.bytes += sum(f["bytes"] for f in manifest["files"] if f["name"] not in already)
        if found:
            moved = archive.quarantine(manifest, [name for name, _ in found])
            for name, why in found:
                report.damaged.append((ref.tag, name, why))
                log.error("archive: run %s (robot %s, cell %s): %s %s; quarantined (%s), to be fetched again",
                          ref.run_id, ref.robot_serial, ref.cell, name, why, ", ".join(map(str, moved)) or "missing")
        elif already:
            report.awaiting.append((ref.tag, sorted(already)))
        else:
            archive.update_index(ref, verified_at=datetime.now(timezone.utc).isoformat(timespec="seconds"))
            report.verified += 1
    return report
