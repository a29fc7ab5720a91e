"""Each robot's calibration history: one JSON line per archived run with a result.

``<archive>/<serial>/history.jsonl``, oldest first; an entry::

    {"run_id", "finished" (ISO 8601 UTC), "site", "cell", "kind": "calibration" | "check",
     "entered": bool, "joints": [names], "offsets_deg": [value or null per joint],
     "std_deg": [σ or null], "ci95_deg": [[lo, hi] or null],
     "accuracy_mm": {"before": mean absolute error or null, "after": … },
     "do_not_enter": [the fit's reasons not to enter its offsets], "n_configurations",
     "drift": the drift verdict against the reference (acquire.station.drift) or null}

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

from acquire.station.drift import check_drift
from acquire.station.states import CHECK_MAX_CONFIGURATIONS, Policy, reference_problem


def entry_from_result(result: dict, *, run_id: str, finished: str, site: str, cell: str,
                      check_max_configurations: int = CHECK_MAX_CONFIGURATIONS, auto_enter: bool = True) -> dict:
    """A history entry from a ``result.json`` (``calib.fit.result``, format remaster.fit/1)."""
    offsets = result.get("joint_offsets")
    if not isinstance(offsets, list) or not offsets:
        raise ValueError(f"run {run_id}: result.json has no joint_offsets list; is it a remaster.fit/1 result?")
    n_conf = int((result.get("data") or {}).get("n_configurations") or 0)
    kind = "check" if n_conf <= check_max_configurations else "calibration"
    fitted = [bool(o.get("identifiable")) and o.get("value_deg") is not None and o.get("std_deg") is not None
              and o.get("status", "fitted") == "fitted" for o in offsets]
    absolute = ((result.get("metrics") or {}).get("absolute") or {})
    return {
        "run_id": run_id, "finished": finished, "site": site, "cell": cell, "kind": kind,
        "n_configurations": n_conf,
        "entered": bool(auto_enter and kind == "calibration" and all(fitted)),
        "joints": [str(o.get("joint")) for o in offsets],
        "offsets_deg": [o.get("value_deg") if f else None for o, f in zip(offsets, fitted)],
        "std_deg": [o.get("std_deg") if f else None for o, f in zip(offsets, fitted)],
        "ci95_deg": [o.get("ci95_deg") if f else None for o, f in zip(offsets, fitted)],
        "accuracy_mm": {"before": (absolute.get("before") or {}).get("mean"),
                        "after": (absolute.get("after") or {}).get("mean")},
        "do_not_enter": [str(r) for r in result.get("do_not_enter") or []],
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
