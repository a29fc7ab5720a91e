"""What an engineer can act on: each robot's state, computed from its history and the plant's policy.

``robot_state(entries, policy, now)`` → ``{"state", "reasons", "reference", "axes", …}``:

``never calibrated``   no calibration has been entered (none archived, or none usable); the
                       offsets and accuracy of its runs are shown, nothing is compared.
``drifted``            the last measurement after the entered calibration (the *reference*) finds
                       offsets beyond their combined uncertainty (χ² test, ``acquire.station.drift``);
                       the axes beyond 3 combined σ are named.
``out of tolerance``   that measurement's error as the robot runs is over the limit:
                       ``accuracy_limit_mm`` when set, else ``accuracy_factor`` × the error its
                       reference's values reach once entered. Both are what the controller runs
                       (its nominal arm at the reported angles, plus what is entered), scored
                       held out from the archived log (``acquire.station.accuracy``), never the
                       fit's model.
``check due``          nothing was measured for ``check_interval_days``.
``calibrated``         none of the above.

Several may hold; ``state`` is the first in the order drifted, out of tolerance, check due,
and ``reasons`` lists each. States are never stored: they are recomputed from the history each
time, so entering another reference (``acquire fleet enter``) changes them at once.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from datetime import datetime, timezone

from acquire.station.drift import FALSE_ALARM, check_drift

#: Runs with at most this many measured configurations are checks, not calibrations.
CHECK_MAX_CONFIGURATIONS = 12

STATES = ("calibrated", "drifted", "out of tolerance", "never calibrated", "check due")


@dataclass(frozen=True)
class Policy:
    """The plant's settings (``drift:`` in the station's configuration)."""

    alpha: float = FALSE_ALARM                  # false-alarm rate of the offset test
    accuracy_limit_mm: float | None = None      # absolute limit; None: relative
    accuracy_factor: float = 1.5                # relative limit: × the reference's error after
    check_interval_days: float | None = 30.0    # None: never due
    check_max_configurations: int = CHECK_MAX_CONFIGURATIONS
    auto_enter: bool = True

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Policy":
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})


def usable_axes(entry: dict) -> list[str]:
    """Axes whose offset a run determined (a value and a σ)."""
    return [j for j, v, s in zip(entry["joints"], entry["offsets_deg"], entry["std_deg"])
            if v is not None and s is not None and s > 0]


def reference_problem(entry: dict, policy: Policy) -> str | None:
    """Why a run cannot be a reference (entered calibration), or None when it can."""
    n = entry.get("n_configurations", 0)
    if n <= policy.check_max_configurations:
        return (f"run {entry['run_id']} measured {n} configurations; a reference needs at least "
                f"{policy.check_max_configurations + 1} (drift.check_max_configurations + 1): it is a check")
    if not usable_axes(entry):
        why = "; ".join(entry.get("do_not_enter") or [])
        return (f"run {entry['run_id']} has no offset that can be entered: every offset is undetermined or "
                "'do not enter'" + (f" (the fit says: {why})" if why else ""))
    return None


def accuracy_limit(reference: dict, policy: Policy) -> tuple[float | None, str]:
    """(limit in mm or None, how it was set)."""
    if policy.accuracy_limit_mm is not None:
        return policy.accuracy_limit_mm, f"the plant's limit {policy.accuracy_limit_mm:g} mm"
    after = (reference.get("accuracy_mm") or {}).get("after")
    if after is None or not math.isfinite(after):
        return None, ("no limit: the reference's accuracy with its values entered is unknown ("
                      + str((reference.get("accuracy_mm") or {}).get("how") or "not scored") + ")")
    limit = policy.accuracy_factor * after
    return limit, (f"{policy.accuracy_factor:g} × the {after:.3f} mm this robot runs with calibration "
                   f"{reference['run_id']} entered")


def _age_days(entry: dict, now: datetime) -> float:
    t = datetime.fromisoformat(entry["finished"])
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return (now - t).total_seconds() / 86400.0


def robot_state(entries: list[dict], policy: Policy = Policy(), now: datetime | None = None) -> dict:
    """The robot's state from its history ``entries`` (oldest first; see the module docstring)."""
    now = now or datetime.now(timezone.utc)
    out = {"state": "calibrated", "reasons": [], "reference": None, "axes": [], "last_run": None,
           "accuracy_mm": None, "accuracy_limit_mm": None, "drift": None}
    if entries:
        out["last_run"] = entries[-1]["run_id"]
    entered = [e for e in entries if e.get("entered")]
    if not entered:
        out["state"] = "never calibrated"
        out["reasons"].append("no calibration entered yet" + (
            f" ({len(entries)} run(s) archived; `acquire fleet enter SERIAL RUN` after typing one in)" if entries
            else ""))
        return out
    ref = entered[-1]
    out["reference"] = ref["run_id"]
    later = [e for e in entries if (e["finished"], e["run_id"]) > (ref["finished"], ref["run_id"])]
    states = []
    last = later[-1] if later else None
    if last is not None:
        verdict = check_drift(ref, last, alpha=policy.alpha)
        out["drift"] = verdict.to_dict()
        if verdict.drifted:
            states.append("drifted")
            out["axes"] = verdict.joints
            out["reasons"].append(f"run {last['run_id']}: " + "; ".join(verdict.reasons))
        elif verdict.dof == 0:
            out["reasons"].append(f"run {last['run_id']}: no axis determined in both it and the reference; "
                                  "offsets not compared")
        acc = (last.get("accuracy_mm") or {}).get("before")
        limit, how = accuracy_limit(ref, policy)
        out["accuracy_mm"], out["accuracy_limit_mm"] = acc, limit
        if acc is not None and limit is not None and math.isfinite(acc) and acc > limit:
            states.append("out of tolerance")
            out["reasons"].append(f"run {last['run_id']}: mean error {acc:.3f} mm as the robot runs, over "
                                  f"{limit:.3f} mm ({how})")
    newest = last or ref
    if policy.check_interval_days is not None and _age_days(newest, now) > policy.check_interval_days:
        states.append("check due")
        out["reasons"].append(f"last measured {_age_days(newest, now):.0f} days ago ({newest['run_id']}); "
                              f"a check is due every {policy.check_interval_days:g} days")
    if states:
        out["state"] = states[0]
    else:
        out["reasons"].append(f"as calibrated by {ref['run_id']}" + (f"; confirmed by {last['run_id']}" if last else ""))
    return out
