"""What the station does with a run once its files are archived: its history entry and drift verdict."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass

from acquire.station.archive import Archive
from acquire.station.drift import FALSE_ALARM, check_drift
from acquire.station.history import CHECK_MAX_CONFIGURATIONS, add_entry, entry_from_result, load_history, reference_for

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriftPolicy:
    """The plant's drift settings: false-alarm rate α of the offset test, the accuracy limit (mm,
    None: off), what counts as a check, and whether calibrations count as entered."""

    alpha: float = FALSE_ALARM
    accuracy_limit_mm: float | None = None
    check_max_configurations: int = CHECK_MAX_CONFIGURATIONS
    auto_enter: bool = True


def record_run(archive: Archive, manifest: dict, policy: DriftPolicy = DriftPolicy()) -> dict | None:
    """Add an archived run with a ``result.json`` to its robot's history, with its drift verdict
    against the last entered calibration before it; returns the entry (None: no result)."""
    if not any(f["name"] == "result.json" for f in manifest["files"]):
        return None
    result = json.loads((archive.folder(manifest) / "result.json").read_text())
    serial = manifest["robot_serial"]
    entry = entry_from_result(result, run_id=manifest["run_id"], finished=manifest["finished"],
                              site=manifest["site"], cell=manifest["cell"],
                              check_max_configurations=policy.check_max_configurations, auto_enter=policy.auto_enter)
    reference = reference_for(load_history(archive.root, serial), entry)
    if reference is not None:
        verdict = check_drift(reference, entry, alpha=policy.alpha, accuracy_limit_mm=policy.accuracy_limit_mm)
    else:
        verdict = check_drift(None, entry, accuracy_limit_mm=policy.accuracy_limit_mm)
    entry["drift"] = verdict.to_dict()
    if verdict.drifted:
        log.warning("robot %s (cell %s) drifted in run %s: %s", serial, manifest["cell"], entry["run_id"],
                    "; ".join(verdict.reasons))
    return add_entry(archive.root, serial, entry)
