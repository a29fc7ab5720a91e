"""Each robot's calibration history: one JSON line per archived run with a result.

``<archive>/<serial>/history.jsonl``, oldest first; an entry::

    {"run_id", "finished" (ISO 8601 UTC), "site", "cell", "kind": "calibration" | "check",
     "entered": bool, "joints": [names], "offsets_deg": [value or null per joint],
     "std_deg": [σ or null], "ci95_deg": [[lo, hi] or null],
     "entered_deg": [what this run tells the operator to enter per joint (calib.robot.entered:
                    the offsets fitted for the controller), 0 where nothing],
     "accuracy_mm": {"before", "after", "n", "how"} (acquire.station.accuracy: the robot as it
                    runs, scored held out on the controller's nominal arm; null when not scored),
     "do_not_enter": [the fit's reasons not to enter its offsets], "n_configurations",
     "drift": the drift verdict against the reference (acquire.station.drift) or null}

``offsets_deg`` are the fit's best estimate of the zeros (``joint_offsets``); what is typed into the
controller (``entered_deg``) may differ from them (fitted with the links at nominal), and the
drift test expects a later run to find the difference (``acquire.station.drift.expected_deg``).

``kind``: a run with at most ``check_max_configurations`` measured configurations is a *check*
(a short plan that only looks), otherwise a *calibration*. ``entered``: the offsets were typed
into the controller — the reference for later drift checks. By default the station takes every
calibration whose fit determined every offset as entered (``auto_enter``); a plant that enters
offsets by hand marks them with :func:`mark_entered` (``acquire fleet enter``), which refuses a
run that cannot be a reference (``acquire.station.states.reference_problem``). An offset the fit
left undetermined or marked "do not enter" is null. Offsets are as measured, i.e. relative to the
zeros the controller held during that run. ``drift`` is recomputed (``recompute``) whenever the
references change.
"""

from __future__ import annotations

import json
from pathlib import Path

from acquire.station.accuracy import not_scored
from acquire.station.drift import check_drift
from acquire.station.states import CHECK_MAX_CONFIGURATIONS, Policy, reference_problem
from calib.robot.entered import entered_values


def entry_from_result(result: dict, *, run_id: str, finished: str, site: str, cell: str,
                      check_max_configurations: int = CHECK_MAX_CONFIGURATIONS, auto_enter: bool = True,
                      accuracy: dict | None = None) -> dict:
    """A history entry from a ``result.json`` (``calib.fit.result``, format remaster.fit/1);
    ``accuracy``: the run's ``acquire.station.accuracy.run_accuracy`` (None: not scored)."""
    offsets = result.get("joint_offsets")
    if not isinstance(offsets, list) or not offsets:
        raise ValueError(f"run {run_id}: result.json has no joint_offsets list; is it a remaster.fit/1 result?")
    fitted = [bool(o.get("identifiable")) and o.get("value_deg") is not None and o.get("std_deg") is not None
              and o.get("status", "fitted") == "fitted" for o in offsets]
    joints = [str(o.get("joint")) for o in offsets]
    n_conf = int((result.get("data") or {}).get("n_configurations") or 0)
    kind = "check" if n_conf <= check_max_configurations else "calibration"
    refused = [str(r) for r in result.get("do_not_enter") or []]
    try:
        values = entered_values(result)
        to_enter = [0.0] * len(joints) if values.refused else values.delta_deg(joints)
    except ValueError:
        to_enter = [0.0] * len(joints)
    return {
        "run_id": run_id, "finished": finished, "site": site, "cell": cell, "kind": kind,
        "n_configurations": n_conf,
        "entered": bool(auto_enter and kind == "calibration" and all(fitted)),
        "joints": joints,
        "offsets_deg": [o.get("value_deg") if f else None for o, f in zip(offsets, fitted)],
        "std_deg": [o.get("std_deg") if f else None for o, f in zip(offsets, fitted)],
        "ci95_deg": [o.get("ci95_deg") if f else None for o, f in zip(offsets, fitted)],
        "entered_deg": to_enter,
        "accuracy_mm": accuracy or not_scored("the run's log was not scored"),
        "do_not_enter": refused,
        "drift": None,
    }


def history_path(archive_root: Path, serial: str) -> Path:
    return Path(archive_root) / serial / "history.jsonl"


def load_history(archive_root: Path, serial: str) -> list[dict]:
    """The robot's entries, oldest first (empty when it has none)."""
    p = history_path(archive_root, serial)
    if not p.exists():
        return []
    entries = [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
    return sorted(entries, key=lambda e: (e["finished"], e["run_id"]))


def write_history(archive_root: Path, serial: str, entries: list[dict]) -> None:
    p = history_path(archive_root, serial)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(".tmp")
    tmp.write_text("".join(json.dumps(e) + "\n" for e in entries))
    tmp.replace(p)


def add_entry(archive_root: Path, serial: str, entry: dict) -> dict:
    """Add ``entry`` (replacing one with the same run id: idempotent); returns it."""
    entries = [e for e in load_history(archive_root, serial) if e["run_id"] != entry["run_id"]]
    entries.append(entry)
    write_history(archive_root, serial, sorted(entries, key=lambda e: (e["finished"], e["run_id"])))
    return entry


def reference_for(entries: list[dict], entry: dict) -> dict | None:
    """The last entered calibration before ``entry`` (None: the robot has none yet)."""
    earlier = [e for e in entries if (e["finished"], e["run_id"]) < (entry["finished"], entry["run_id"])]
    entered = [e for e in earlier if e.get("entered")]
    return entered[-1] if entered else None


def mark_entered(archive_root: Path, serial: str, run_id: str, entered: bool = True,
                 policy: Policy = Policy()) -> dict:
    """Mark a run's offsets as entered into the controller (or not) and recompute the verdicts;
    returns the entry. ValueError for an unknown run, or one that cannot be a reference."""
    entries = load_history(archive_root, serial)
    for e in entries:
        if e["run_id"] == run_id:
            problem = reference_problem(e, policy) if entered else None
            if problem:
                raise ValueError(f"robot {serial}: {problem}; not entered")
            e["entered"] = entered
            write_history(archive_root, serial, recompute(entries, policy))
            return e
    raise ValueError(f"robot {serial!r} has no run {run_id!r} in its history; runs: {[e['run_id'] for e in entries]}")


def recompute(entries: list[dict], policy: Policy = Policy()) -> list[dict]:
    """Each entry's ``drift`` verdict against the reference it has now (in place; returned)."""
    for e in entries:
        ref = reference_for(entries, e)
        e["drift"] = None if ref is None else check_drift(ref, e, alpha=policy.alpha).to_dict()
    return entries


def robots(archive_root: Path) -> list[str]:
    """Serials with a history, sorted."""
    return sorted(p.parent.name for p in Path(archive_root).glob("*/history.jsonl"))
