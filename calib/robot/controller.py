"""Values to enter on the robot controller, with the sign convention spelled out.

The fit's zero-offset δ_i (degrees, the controller's axis convention) means

    true axis angle = angle the controller reports + δ_i.

What to type depends on how the controller turns an encoder reading into an axis angle:

``kss``      KUKA KR C4/C5: the zero positions are ``$MAMES[1..6]`` (external axes 7–12) in the
             machine data, degrees. *Assuming* KSS computes axis angle = encoder angle − $MAMES,
             the new value is ``$MAMES[i] − δ_i`` (correction −δ_i). This sign is UNVERIFIED on a
             real controller (``/work/shared/PROTOCOLS.md``): check it on one axis first — after
             entering it, a fresh measurement must give δ_i ≈ 0, not 2·δ_i.
``sunrise``  KUKA LBR iiwa: mastering is electronic and has no public file format; a per-axis
             table (δ and the correction −δ to the axis zero) to enter through the vendor's
             tools.
other        a per-axis table in the same form.

An axis whose offset is not identifiable (undetermined, or not fitted) gets "leave unchanged"
and no number.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from calib.robot.canonical import wrap_deg
from calib.robot.model import RobotModel

CONVENTION = "δ = fitted zero-offset: true axis angle = reported axis angle + δ (degrees, controller's axis sense)"

KSS_CONVENTION = (
    "KSS: assumed axis angle = encoder angle − $MAMES[i], so new $MAMES[i] = old $MAMES[i] − δ_i "
    "(correction −δ_i). UNVERIFIED sign convention: change one axis first and re-measure — the "
    "new fit must give δ_i ≈ 0 (if it gives ≈ 2·δ_i, the sign is the other way round)."
)
SUNRISE_CONVENTION = (
    "Sunrise (LBR iiwa): no public mastering file; correct each axis zero so the reported angle "
    "grows by δ_i (correction to the zero position: −δ_i if the zero is subtracted from the "
    "encoder angle). UNVERIFIED on a real controller."
)
GENERIC_CONVENTION = (
    "Generic controller: add δ_i to the reported axis angle, i.e. shift the axis zero by −δ_i if "
    "the controller subtracts the zero from the encoder angle. Check the sign on one axis first."
)


@dataclass(frozen=True)
class AxisValue:
    """One axis: δ and the correction (−δ) in degrees, or ``None`` with action "leave unchanged"."""

    axis: str
    index: int
    delta_deg: float | None
    std_deg: float | None
    correction_deg: float | None
    action: str
    reason: str = ""


@dataclass(frozen=True)
class ControllerValues:
    controller: str
    convention: str
    sign_convention: str
    verified: bool
    axes: list[AxisValue]
    lines: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["axes"] = [asdict(a) for a in self.axes]
        return d

    def format(self) -> str:
        """Human-readable block for the terminal and the report."""
        out = [f"values to enter ({self.controller}):", f"  {self.convention}", f"  {self.sign_convention}"]
        if self.lines:
            out += [f"  {line}" for line in self.lines]
        else:
            out.append(f"  {'axis':<6} {'δ (deg)':>10} {'± std':>8} {'correction':>11}  action")
            for a in self.axes:
                if a.delta_deg is None:
                    out.append(f"  {a.axis:<6} {'—':>10} {'':>8} {'—':>11}  leave unchanged ({a.reason})")
                else:
                    out.append(f"  {a.axis:<6} {a.delta_deg:+10.4f} {a.std_deg:8.4f} {a.correction_deg:+11.4f}  {a.action}")
        return "\n".join(out)


#: Guards of ``do_not_enter_reasons``: sampler convergence, model-robust spread, σ against noise.
MAX_RHAT = 1.05
MAX_SANDWICH_RATIO = 2.0
MAX_SIGMA_OVER_NOISE = 10.0
#: ... and above this σ (mm) in any case: a calibrated arm's unmodelled error is tenths of a mm.
MIN_SIGMA_GUARD_MM = 1.0


def do_not_enter_reasons(doc: dict, *, sandwich: bool = True) -> list[str]:
    """Why the offsets of a fit result (``result.json``) must not be entered; [] when none.

    R-hat above ``MAX_RHAT`` (the chains disagree), a sandwich/posterior std ratio above
    ``MAX_SANDWICH_RATIO`` (the intervals are far too narrow for the errors seen), or a fitted σ
    above ``MIN_SIGMA_GUARD_MM`` and more than ``MAX_SIGMA_OVER_NOISE`` × the sensor noise measured
    in the samples' spread (the model does not describe the data: wrong marker or tool position,
    wrong robot model, units). ``sandwich`` False: no refusal on the sandwich ratio (for offsets
    whose stds were widened by it, ``calib.fit.entered``).
    """
    reasons = []
    d = doc.get("diagnostics", {})
    rhat = d.get("rhat_max")
    if rhat is not None and rhat > MAX_RHAT:
        reasons.append(f"the sampler has not converged (R-hat {rhat:.2f} > {MAX_RHAT})")
    ratios = [j["sandwich_std_ratio"] for j in doc.get("joint_offsets", []) if j.get("sandwich_std_ratio")]
    if sandwich and ratios and max(ratios) > MAX_SANDWICH_RATIO:
        reasons.append(f"a model-robust (sandwich) std is {max(ratios):.1f}× the posterior's (> {MAX_SANDWICH_RATIO}): "
                       "the errors are not what the model assumes and the intervals are too narrow")
    for sensor, b in d.get("error_budget", {}).items():
        noise, sigma = b.get("noise_mm") or 0.0, b.get("sigma_mm")
        if sigma is not None and sigma > max(MAX_SIGMA_OVER_NOISE * noise, MIN_SIGMA_GUARD_MM):
            seen = f", {sigma / noise:.0f}× the sensor noise ({noise:.3g} mm)" if noise else ""
            reasons.append(f"sensor {sensor}: the fit leaves σ = {sigma:.3g} mm{seen}: the model does not describe the "
                           "data (tool/marker position, robot model, units?)")
    return reasons


#: "Enter" is earned (``earned_reasons``): the chosen model's held-out error per axis must stay
#: within this many times the noise of one measurement as fitted (a posterior predictive check), ...
MAX_HELDOUT_OVER_NOISE = 3.0
#: ... no fitted marker may lie more than this many prior standard deviations from the model's place,
MAX_TOOL_PRIOR_SIGMAS = 3.0
#: ... and the posterior needs at least this many effective draws.
MIN_ESS = 100.0


def _noise_mm(doc: dict) -> tuple[float, str] | None:
    """The rms per-axis noise of one measurement row as it enters the fit, over all sensors
    (``error_budget``), and what it is: the standard error of the averaged samples (``noise_mm``,
    std_mm / √n) — a row that averages 20 samples is √20 times quieter than one sample, and a
    model that describes the robot predicts held-out rows to that noise (plus its own
    estimation error, a fraction of it), not to the spread of one sample. None without std_mm."""
    budget = [b for b in doc.get("diagnostics", {}).get("error_budget", {}).values() if b.get("noise_mm")]
    if not budget:
        return None
    rows = np.array([b.get("n_rows", 1) for b in budget], dtype=float)
    noise = float(np.sqrt(np.sum(rows * np.array([b["noise_mm"] for b in budget]) ** 2) / rows.sum()))
    if doc.get("noise_estimate"):
        return noise, "the noise estimated from the data (no spreads in the file; calib.fit.noise)"
    spread = [b.get("sample_spread_mm") for b in budget]
    averaged = all(sp is not None and sp > noise * 1.05 for sp in spread)
    return noise, ("the noise of the averaged measurement, the samples' spread / √n" if averaged
                   else "the measured spread of one sample")


def _worst_text(mc: dict, chosen: dict, noise: float) -> str:
    """What to do about a held-out error above the noise: the configurations that carry it when a
    few stand out (an outlier: a marker not seated, a beam break, a bump), else the model."""
    worst = chosen.get("worst_configurations") or []
    median = chosen.get("cv_median_mm")
    if worst and median is not None and worst[0][1] > 5 * max(median, noise * math.sqrt(3.0)):
        out = [f"{c} ({e:.3g} mm)" for c, e in worst if e > 5 * max(median, noise * math.sqrt(3.0))]
        return (f"configuration{'s' if len(out) > 1 else ''} {', '.join(out)} held out lie{'' if len(out) > 1 else 's'} "
                f"far off the others (median {median:.3g} mm): measure {'them' if len(out) > 1 else 'it'} again or "
                f"leave {'them' if len(out) > 1 else 'it'} out, and fit again")
    return f"{_unexplained(mc)} — see the model-choice table"


def _unexplained(mc: dict) -> str:
    """What a held-out error far above the noise says to the operator: which of tool, link errors
    and gravity sag the chosen model of ``mc`` (the model-choice document) leaves out, or that even
    a model with all three does not describe the robot."""
    name = mc["chosen"]
    can_sag = any(c["model"].endswith("+compliance") for c in mc["candidates"])
    missing = [what for what, inside in (("tool", "tool" in name or name == "full"),
                                         ("link errors", "links" in name or name == "full"),
                                         ("gravity sag" if can_sag else "gravity sag (the robot model has no link masses)",
                                          "compliance" in name)) if not inside]
    if missing:
        return f"the chosen model ({name}) does not describe this robot (not in it: {', '.join(missing)})"
    return (f"even the chosen model ({name}: tool, link errors and gravity sag) leaves robot error that none of the "
            "candidates describes")


#: Validation points the calibration's registration misses by this factor over their own registration
#: (and by more than ``FOREIGN_FRAME_MM``) are in another frame: another mounting, not a worse robot.
FOREIGN_FRAME_FACTOR = 10.0
FOREIGN_FRAME_MM = 10.0


def earned_reasons(doc: dict) -> list[str]:
    """Why "enter" is not earned, one line each ([] when it is): the model choice
    (``doc["model_choice"]``, ``calib.fit.model_choice``) found no model, or the chosen one does not
    predict held-out configurations better than the uncalibrated robot; the chosen model's held-out
    error (rms per axis) is more than ``MAX_HELDOUT_OVER_NOISE`` × the noise of one measurement row
    (``_noise_mm``: of the averaged samples), or above ``MIN_SIGMA_GUARD_MM``; validation points (``--validate``, scored with the offsets
    alone, as the controller will have them) that do not improve or stay above ``MIN_SIGMA_GUARD_MM``
    per axis; a fitted marker more than
    ``MAX_TOOL_PRIOR_SIGMAS`` prior standard deviations from the model's place (the tool drawing is
    wrong: something else may have absorbed it); the Laplace check failed and the fallback sampler
    has fewer than ``MIN_ESS`` effective draws."""
    reasons = []
    noise = _noise_mm(doc)
    mc = doc.get("model_choice")
    if mc:
        chosen = next((c for c in mc["candidates"] if c["model"] == mc["chosen"]), None)
        nominal = mc["nominal"]
        if chosen is None or chosen.get("failed") or chosen.get("cv_mean_mm") is None:
            reasons.append(f"the chosen model {mc['chosen']} could not be fitted in every cross-validation fold")
        else:
            if nominal.get("cv_mean_mm") is not None and chosen["cv_mean_mm"] >= nominal["cv_mean_mm"]:
                reasons.append(f"the chosen model ({mc['chosen']}) predicts held-out configurations no better than the "
                               f"uncalibrated robot ({chosen['cv_mean_mm']:.3f} mm against {nominal['cv_mean_mm']:.3f} mm)")
            per_axis = chosen["cv_rms_mm"] / math.sqrt(3.0)
            if noise and per_axis > MAX_HELDOUT_OVER_NOISE * noise[0]:
                reasons.append(f"held-out error {per_axis:.3f} mm per axis is {per_axis / noise[0]:.0f}× {noise[1]} "
                               f"({noise[0]:.3g} mm): the residuals are not the sensor's noise — "
                               + _worst_text(mc, chosen, noise[0]))
            elif per_axis > MIN_SIGMA_GUARD_MM:
                reasons.append(f"held-out error {per_axis:.2f} mm per axis (above {MIN_SIGMA_GUARD_MM:g} mm)")
    val = doc.get("metrics", {}).get("validation_absolute")
    rereg = doc.get("metrics", {}).get("validation_absolute_reregistered")
    if (isinstance(val, dict) and isinstance(rereg, dict) and isinstance(rereg.get("before"), dict)
            and val["before"]["mean"] > max(FOREIGN_FRAME_FACTOR * rereg["before"]["mean"], FOREIGN_FRAME_MM)):
        # Another mounting (the tracker or the robot moved): the calibration's registration does not hold
        # there, and only figures that register each robot on those points (``entered.heldout``) mean anything.
        val = None
    if isinstance(val, dict) and isinstance(val.get("after"), dict):
        # The controller is told the offsets only: the validation points carry what the offsets
        # alone do (link errors of a richer model stay). They must improve, and stay below the guard.
        before, after = val["before"]["mean"], val["after"]["mean"]
        if after >= before:
            reasons.append(f"the validation points get no better with these offsets ({before:.3f} → {after:.3f} mm mean)")
        elif after / math.sqrt(3.0) > MIN_SIGMA_GUARD_MM:
            reasons.append(f"validation error after the correction {after:.3f} mm (mean), above {MIN_SIGMA_GUARD_MM:g} mm per "
                           "axis: the model does not describe the validation points (tool, markers, robot model?)")
    reasons += tool_reasons(doc)
    d = doc.get("diagnostics", {})
    imp = d.get("importance")
    ess = d.get("ess_min")
    ens = (imp or {}).get("walk") or {}
    if imp and imp.get("fallback") and ens.get("rhat_log_density") is not None and ens["rhat_log_density"] > MAX_RHAT:
        reasons.append(f"the fallback sampler has not settled: R-hat of the log density {ens['rhat_log_density']:.2f} "
                       f"(> {MAX_RHAT}) — its chains are still spreading out or drawing in, and its intervals are not yet "
                       "the posterior's")
    if imp and imp.get("fallback") and ess is not None and ess < MIN_ESS:
        reasons.append(f"the Laplace approximation failed its check (Pareto k̂ {imp['k_hat']:.2f} ≥ {imp['k_hat_max']}) and the "
                       f"fallback sampler has only {ess:.0f} effective draws (< {MIN_ESS:g})")
    return reasons


def tool_reasons(doc: dict) -> list[str]:
    """A fitted marker more than ``MAX_TOOL_PRIOR_SIGMAS`` prior standard deviations from the model's
    place (``doc["tool"]``): the tool drawing is wrong, and the prior's pull may have moved the offsets."""
    out = []
    for t in (doc.get("tool") or {}).get("markers") or []:
        off = np.abs(np.subtract(t["value_mm"], t["nominal_mm"]))
        if t.get("prior_mm") and off.max() > MAX_TOOL_PRIOR_SIGMAS * t["prior_mm"]:
            out.append(f"marker {t['marker']} fitted {np.linalg.norm(np.subtract(t['value_mm'], t['nominal_mm'])):.1f} mm "
                       f"from the model's place, outside its prior (±{t['prior_mm']:g} mm): the tool drawing is wrong — "
                       "measure the markers on the flange, correct the model and fit again")
    return out


def apply_guards(doc: dict) -> list[str]:
    """Mark every offset of ``doc`` "do not enter" (with the reason) when a guard fires; returns the reasons."""
    reasons = do_not_enter_reasons(doc)
    reasons += [r for r in earned_reasons(doc) if r not in reasons]
    if reasons:
        for j in doc.get("joint_offsets", []):
            if j.get("identifiable"):
                j["identifiable"] = False
                j["status"] = "do not enter"
                j["reason"] = "; ".join(reasons)
        doc["do_not_enter"] = reasons
    return reasons


def controller_values(model: RobotModel, joint_offsets: list[dict]) -> ControllerValues:
    """Values to enter from ``joint_offsets`` (the ``result.json`` entries, degrees)."""
    if len(joint_offsets) != model.n_joints:
        raise ValueError(f"{len(joint_offsets)} offsets given for a {model.n_joints}-axis model")
    axes = []
    for entry in joint_offsets:
        if entry["identifiable"] and entry["value_deg"] is not None:
            d = wrap_deg(float(entry["value_deg"]))  # a whole turn is no correction: (−180°, 180°]
            axes.append(AxisValue(entry["joint"], int(entry["index"]), d, float(entry["std_deg"]), -d, "enter"))
        else:
            reason = entry.get("status", "") or "not identifiable"
            axes.append(AxisValue(entry["joint"], int(entry["index"]), None, None, None, "leave unchanged", reason))
    if model.controller == "kss":
        lines = []
        for a in axes:
            if a.delta_deg is None:
                lines.append(f"$MAMES[{a.index}]: leave unchanged ({a.axis}: {a.reason})")
            else:
                lines.append(
                    f"$MAMES[{a.index}] = $MAMES[{a.index}] {a.correction_deg:+.4f}   "
                    f"; {a.axis}: δ = {a.delta_deg:+.4f}° ± {a.std_deg:.4f}°, correction {a.correction_deg:+.4f}° (UNVERIFIED sign)"
                )
        return ControllerValues("kss", CONVENTION, KSS_CONVENTION, False, axes, lines)
    if model.controller == "sunrise":
        return ControllerValues("sunrise", CONVENTION, SUNRISE_CONVENTION, False, axes)
    return ControllerValues(model.controller, CONVENTION, GENERIC_CONVENTION, False, axes)
