"""What the station does with a run once its files are archived: its robot's history entry (the
robot's accuracy as it runs scored from the archived log, ``acquire.station.accuracy``), every
verdict recomputed against the references."""

from __future__ import annotations

import json
import logging

from acquire.station.accuracy import run_accuracy, run_log_of
from acquire.station.archive import Archive
from acquire.station.history import add_entry, entry_from_result, load_history, recompute, write_history
from acquire.station.states import Policy

log = logging.getLogger(__name__)


def record_run(archive: Archive, manifest: dict, policy: Policy = Policy()) -> dict | None:
    """Add an archived run with a ``result.json`` to its robot's history and recompute the drift
    verdicts; returns the entry (None: the run has no result, or one that is not a fit result)."""
    if not any(f["name"] == "result.json" for f in manifest["files"]):
        return None
    serial = manifest["robot_serial"]
    path = archive.folder(manifest) / "result.json"
    try:
        result = json.loads(path.read_text())
        entry = entry_from_result(result, run_id=manifest["run_id"],
                                  finished=manifest["finished"], site=manifest["site"], cell=manifest["cell"],
                                  check_max_configurations=policy.check_max_configurations,
                                  auto_enter=policy.auto_enter)
        entry["accuracy_mm"] = run_accuracy(run_log_of(archive.folder(manifest), manifest["run_id"]), result)
    except (OSError, ValueError, TypeError, AttributeError) as exc:   # archived as sent; no history entry
        log.warning("run %s (robot %s): %s is not a result the history can use (%s); archived without a "
                    "history entry", manifest["run_id"], serial, path, exc)
        return None
    add_entry(archive.root, serial, entry)
    entries = recompute(load_history(archive.root, serial), policy)
    write_history(archive.root, serial, entries)
    entry = next(e for e in entries if e["run_id"] == entry["run_id"])
    if (entry.get("drift") or {}).get("drifted"):
        log.warning("robot %s (cell %s) drifted in run %s: %s", serial, manifest["cell"], entry["run_id"],
                    "; ".join(entry["drift"]["reasons"]))
    return entry


def catch_up(archive: Archive, policy: Policy = Policy()) -> list[str]:
    """Record every archived run with a ``result.json`` that its robot's history lacks (a station
    stopped between storing a run and recording it: the run, confirmed, is never sent again);
    returns the run ids added. Reads every manifest: seconds for tens of thousands of runs."""
    known: dict[str, set[str]] = {}
    added = []
    for manifest in archive.manifests():
        if not any(f["name"] == "result.json" for f in manifest["files"]):
            continue
        serial = manifest["robot_serial"]
        if serial not in known:
            known[serial] = {e["run_id"] for e in load_history(archive.root, serial)}
        if manifest["run_id"] not in known[serial] and record_run(archive, manifest, policy) is not None:
            added.append(manifest["run_id"])
    if added:
        log.warning("history: %d archived run(s) added that the station had stored but not recorded: %s",
                    len(added), ", ".join(added))
    return added
