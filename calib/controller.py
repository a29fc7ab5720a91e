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

from dataclasses import asdict, dataclass, field

from calib.canonical import wrap_deg
from calib.model import RobotModel

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


def do_not_enter_reasons(doc: dict) -> list[str]:
    """Why the offsets of a fit result (``result.json``) must not be entered; [] when none.

    R-hat above ``MAX_RHAT`` (the chains disagree), a sandwich/posterior std ratio above
    ``MAX_SANDWICH_RATIO`` (the intervals are far too narrow for the errors seen), or a fitted σ
    above ``MIN_SIGMA_GUARD_MM`` and more than ``MAX_SIGMA_OVER_NOISE`` × the sensor noise measured
    in the samples' spread (the model does not describe the data: wrong marker or tool position,
    wrong robot model, units).
    """
    reasons = []
    d = doc.get("diagnostics", {})
    rhat = d.get("rhat_max")
    if rhat is not None and rhat > MAX_RHAT:
        reasons.append(f"the sampler has not converged (R-hat {rhat:.2f} > {MAX_RHAT})")
    ratios = [j["sandwich_std_ratio"] for j in doc.get("joint_offsets", []) if j.get("sandwich_std_ratio")]
    if ratios and max(ratios) > MAX_SANDWICH_RATIO:
        reasons.append(f"a model-robust (sandwich) std is {max(ratios):.1f}× the posterior's (> {MAX_SANDWICH_RATIO}): "
                       "the errors are not what the model assumes and the intervals are too narrow")
    for sensor, b in d.get("error_budget", {}).items():
        noise, sigma = b.get("noise_mm") or 0.0, b.get("sigma_mm")
        if sigma is not None and sigma > max(MAX_SIGMA_OVER_NOISE * noise, MIN_SIGMA_GUARD_MM):
            seen = f", {sigma / noise:.0f}× the sensor noise ({noise:.3g} mm)" if noise else ""
            reasons.append(f"sensor {sensor}: the fit leaves σ = {sigma:.3g} mm{seen}: the model does not describe the "
                           "data (tool/marker position, robot model, units?)")
    return reasons


def apply_guards(doc: dict) -> list[str]:
    """Mark every offset of ``doc`` "do not enter" (with the reason) when a guard fires; returns the reasons."""
    reasons = do_not_enter_reasons(doc)
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
