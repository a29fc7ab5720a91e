"""Did entering the offsets do what the calibration predicted? The verdict of a verification run.

A verification run measures fresh configurations (not the calibration's) after the values were
entered on the controller. ``verify_entry(model, data, delta_deg, prediction)`` scores them as the
robot now runs (``calib.fit.as_running``: the nominal arm at the angles the controller reports,
registration and tool fitted on the other folds, held out) and compares:

- **after**: what the robot does now at the fresh configurations (and the 95 % interval of its
  score over them);
- **before, calibration**: the calibration's own held-out score of the robot as found (other
  configurations of the same region). The **measured improvement** is that less *after*: it
  does not depend on what was entered;
- **before, replayed**: the same fresh measurements with the result's δ taken back off the
  reported angles (entering δ made the controller report δ more for the same position): the robot
  as found at these configurations *if* the controller holds the result's values. It must agree
  with the calibration's as found (within three standard errors); where it does not, the values
  in the controller are not the result's — a wrong sign, another result — and a note says so.
  Without a calibration score it is the *before* of the measured improvement (paired).

The **predicted improvement** and its 95 % interval come from the calibration
(``result.json["entered"]["heldout"]["improvement_mm"]``, or ``as_running.predict_entry``). That
interval is for the region's mean; this run saw a finite sample of it, so the check widens it by
the run's own sampling spread (the after-score's half-width, in quadrature) — the interval a
measurement of this many configurations should fall in. Verdict: ``as predicted`` inside it,
``better than predicted`` above, ``worse than predicted`` below (entered with the wrong sign,
something moved, the calibration did not describe the robot). Whether the measured value lies
inside the prediction's own ci95 is reported too. Units: mm, degrees for δ.
"""

from __future__ import annotations

import math

import numpy as np

from calib.fit.as_running import ConfigErrors, paired_improvement, score_as_running
from calib.measure.dataset import Dataset
from calib.robot.model import RobotModel

FORMAT = "remaster-verify/1"
VERDICTS = ("as predicted", "better than predicted", "worse than predicted", "no prediction")


def _half_width(interval) -> float:
    return 0.5 * (interval[1] - interval[0])


def _interval_for_sample(predicted: dict, half: float) -> list[float]:
    """The predicted interval widened by a measurement's own half-width (quadrature, per side)."""
    v, (lo, hi) = predicted["value"], predicted["ci95"]
    return [v - math.hypot(v - lo, half), v + math.hypot(hi - v, half)]


def _mean_interval(errors: ConfigErrors, metric: str, n_boot: int = 4000, seed: int = 0) -> list[float]:
    """Bootstrap 95 % interval of ``metric`` over the configurations of ``errors``, mm."""
    e = errors.errors_mm
    idx = np.random.default_rng(seed).integers(0, e.size, size=(n_boot, e.size))
    boot = e[idx].mean(axis=1) if metric == "mean_mm" else np.sqrt((e[idx] ** 2).mean(axis=1))
    return [float(v) for v in np.percentile(boot, [2.5, 97.5])]


def _standard_error(score: dict, metric: str) -> float:
    """Standard error (mm) of ``metric`` of a ``{"rms_mm", "mean_mm", "n"}`` score (the spread of
    the per-configuration errors is √(rms² − mean²); for the rms, its delta-method share)."""
    sd = math.sqrt(max(score["rms_mm"] ** 2 - score["mean_mm"] ** 2, 0.0))
    se_mean = sd / math.sqrt(max(score["n"], 1))
    return se_mean if metric == "mean_mm" else se_mean * score["mean_mm"] / max(score["rms_mm"], 1e-12)


def verify_entry(model: RobotModel, data: Dataset, delta_deg, prediction: dict | None, *, k: int = 5,
                 tool_prior_mm: float = 10.0, seed: int = 0) -> dict:
    """The verification document of ``data`` (fresh configurations measured after entering
    ``delta_deg`` (n,) deg) against ``prediction`` (the calibration's ``heldout`` document, or
    None); see the module docstring for what it holds."""
    delta = np.asarray(delta_deg, dtype=float)
    if delta.shape != (model.n_joints,):
        raise ValueError(f"{delta.size} entered values given for a {model.n_joints}-axis robot")
    after = score_as_running(model, data, k=k, tool_prior_mm=tool_prior_mm, seed=seed)
    replayed = score_as_running(model, data, joint_shift_rad=-np.radians(delta), k=k, tool_prior_mm=tool_prior_mm,
                                seed=seed)
    imp = (prediction or {}).get("improvement_mm")
    metric = (imp or {}).get("metric") or (prediction or {}).get("metric") or "mean_mm"
    paired = paired_improvement(replayed, after, metric=metric, seed=seed)
    after_ci = _mean_interval(after, metric, seed=seed)
    doc = {
        "format": FORMAT,
        "scored_on": f"{after.errors_mm.size} fresh configurations, {k}-fold cross-validation (the controller's nominal "
                     "arm at the angles it reports; registration and tool fitted on the other folds)",
        "metric": metric,
        "entered_deg": {a: float(d) for a, d in zip(model.axis_names, delta)},
        "after": {**after.summary(), "ci95_mm": after_ci},
        "before": {"replayed": replayed.summary()},
        "measured": {"improvement_replayed_mm": paired},
        "per_configuration": {"configs": after.configs.tolist(), "after_mm": after.errors_mm.tolist(),
                              "before_replayed_mm": replayed.aligned(after)[0].tolist()},
        "notes": [],
    }
    found = (prediction or {}).get("as_found")
    if found:
        doc["before"]["calibration"] = found
        # the robot as found, replayed from this run, is the calibration's robot as found: unless the
        # values in the controller are not the result's (a wrong sign, another result, a mastering since)
        se = math.hypot(_standard_error(found, metric), _half_width(_mean_interval(replayed, metric, seed=seed)) / 1.96)
        diff = replayed.summary()[metric] - found[metric]
        doc["entry_matches_result"] = bool(abs(diff) <= 3.0 * se)
        if not doc["entry_matches_result"]:
            doc["notes"].append(
                f"the robot as found, replayed from these measurements with the result's values taken off, is "
                f"{replayed.summary()[metric]:.3f} mm against {found[metric]:.3f} mm in the calibration: the values in "
                "the controller are not the result's (entered with the other sign? another result? changed since?)")
        value = found[metric] - after.summary()[metric]
        half = math.hypot(_half_width(after_ci), 1.96 * _standard_error(found, metric))
        doc["measured"]["improvement_mm"] = {"value": value, "ci95": [value - half, value + half], "metric": metric,
                                             "against": "the calibration's held-out robot as found"}
    else:
        doc["measured"]["improvement_mm"] = {**paired, "against": "the robot as found, replayed at these configurations"}
    if imp is None:
        doc["verdict"] = "no prediction"
        doc["predicted"] = None
        return doc
    measured = doc["measured"]["improvement_mm"]
    # the prediction is for the region's mean; this run measured a sample of it (its after-score's spread)
    interval = _interval_for_sample(imp, _half_width(after_ci))
    v = measured["value"]
    doc["predicted"] = {"improvement_mm": {"value": imp["value"], "ci95": list(imp["ci95"]), "metric": metric},
                        "after": prediction.get("entered"), "full_model": prediction.get("full_model"),
                        "scored_on": prediction.get("scored_on"), "interval_for_this_run": interval}
    doc["within_predicted_ci95"] = bool(imp["ci95"][0] <= v <= imp["ci95"][1])
    doc["verdict"] = ("as predicted" if interval[0] <= v <= interval[1]
                      else "better than predicted" if v > interval[1] else "worse than predicted")
    return doc


def summary_lines(doc: dict) -> list[str]:
    """The verification in a few lines for the console and the report."""
    metric = doc["metric"]
    word = "mean" if metric == "mean_mm" else "rms"
    a, r = doc["after"], doc["before"]["replayed"]
    lines = [f"verification: {doc['scored_on']}",
             f"  robot now (after the entry)      {word} {a[metric]:.3f} mm (95 % {a['ci95_mm'][0]:.3f} … "
             f"{a['ci95_mm'][1]:.3f})   max {a['max_mm']:.3f} mm"]
    cal = doc["before"].get("calibration")
    if cal:
        lines.append(f"  robot as found (calibration)     {word} {cal[metric]:.3f} mm   held out, {cal['n']} other configurations")
    match = {True: "", False: "   ← not the calibration's: see the note"}.get(doc.get("entry_matches_result"), "")
    lines.append(f"  robot as found (replayed here)   {word} {r[metric]:.3f} mm   the entered values taken off{match}")
    m = doc["measured"]["improvement_mm"]
    lines.append(f"  measured improvement             {m['value']:+.3f} mm (95 % {m['ci95'][0]:+.3f} … {m['ci95'][1]:+.3f}), "
                 f"against {m['against']}")
    p = doc.get("predicted")
    if p is None:
        lines.append("  predicted: none in the result (no held-out prediction): measured only")
    else:
        pi, iv = p["improvement_mm"], p["interval_for_this_run"]
        lines.append(f"  predicted improvement            {pi['value']:+.3f} mm (95 % {pi['ci95'][0]:+.3f} … {pi['ci95'][1]:+.3f}; "
                     f"for {a['n']} configurations {iv[0]:+.3f} … {iv[1]:+.3f})")
        if p.get("after"):
            lines.append(f"  predicted after the entry        {word} {p['after'][metric]:.3f} mm")
        if p.get("full_model"):
            lines.append(f"  the full model (compensation)    {word} {p['full_model'][metric]:.3f} mm predicted: what the "
                         "rest of the gain is, for a consumer of the whole model")
        inside = "inside" if doc["within_predicted_ci95"] else "outside"
        lines.append(f"verdict: {doc['verdict']} (the measured improvement lies {inside} the predicted 95 % interval)")
    lines += [f"note: {n}" for n in doc.get("notes", [])]
    return lines
