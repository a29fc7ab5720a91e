"""Have a robot's offsets moved since its last entered calibration?

After a calibration is entered, the controller's zeros are that calibration's
   estimate, so a later measurement (a short check or a full run) should find offsets of zero
   up to the uncertainty of both: the entered values' error (σ_ref, per joint) and the new
   measurement's (σ_new). With Δ the new offsets less what the reference leaves expected
   (``expected_deg``: 0 on an axis whose value was entered, the reference's offset on an axis
   left unchanged; for a reference *not* in the controller, the reference's offset), over the
   k joints determined in both::

       D = Σ_j Δ_j² / (σ_ref,j² + σ_new,j²)   ~ χ²(k) when nothing moved

   (diagonal covariances: ``result.json`` carries per-joint σ; the fit's joint offsets are
   nearly uncorrelated in the well-designed plans, and a correlated pair makes the test
   conservative or liberal by the size of the correlation). The robot is flagged when D exceeds
   the χ²(k) quantile 1 − α: with α = ``FALSE_ALARM`` = 1 % a stable robot is flagged in 1 %
   of checks. The joints with |Δ_j| / √(σ_ref,j² + σ_new,j²) > 3 are named.

Accuracy over a limit is another state (``out of tolerance``, ``acquire.station.states``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from scipy.stats import chi2

#: Default false-alarm rate of the offset test.
FALSE_ALARM = 0.01


@dataclass
class DriftVerdict:
    """The outcome of a drift check; ``drifted`` when the offsets moved."""

    drifted: bool
    reference: str | None               # run id of the reference calibration
    statistic: float | None = None      # D
    dof: int = 0                        # k
    threshold: float | None = None      # χ²(k) quantile 1 − α
    p_value: float | None = None
    alpha: float = FALSE_ALARM
    joints: list[str] = field(default_factory=list)   # joints beyond 3 combined σ
    reasons: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def expected_deg(reference: dict, j: int, reference_in_controller: bool = True) -> float:
    """The offset of joint ``j`` (deg) a later run finds if nothing moved since ``reference``: with
    its values in the controller, its offset less what it entered (``entered_deg``; an entry
    without it is taken as having entered every offset); otherwise its offset."""
    value = reference["offsets_deg"][j]
    if not reference_in_controller:
        return value
    entered = reference.get("entered_deg")
    return 0.0 if entered is None else value - (entered[j] or 0.0)


def check_drift(reference: dict | None, new: dict, *, alpha: float = FALSE_ALARM,
                reference_in_controller: bool = True) -> DriftVerdict:
    """The drift verdict of history entry ``new`` against ``reference`` (see the module docstring).

    Entries are ``acquire.station.history`` entries (offsets_deg, std_deg per joint, degrees).
    """
    if not 0 < alpha < 1:
        raise ValueError(f"alpha (false-alarm rate) must be in (0, 1), given {alpha}")
    verdict = DriftVerdict(False, reference["run_id"] if reference else None, alpha=alpha)
    if reference is not None:
        if reference["joints"] != new["joints"]:
            raise ValueError(f"run {new['run_id']} has joints {new['joints']}, its reference "
                             f"{reference['run_id']} {reference['joints']}: not the same robot model")
        stat, names, details = 0.0, [], []
        for j, name in enumerate(new["joints"]):
            vals = (new["offsets_deg"][j], new["std_deg"][j], reference["offsets_deg"][j], reference["std_deg"][j])
            if any(v is None for v in vals) or vals[1] <= 0 or vals[3] <= 0:
                continue
            delta = vals[0] - expected_deg(reference, j, reference_in_controller)
            z2 = delta * delta / (vals[1] ** 2 + vals[3] ** 2)
            stat += z2
            verdict.dof += 1
            if z2 > 9.0:
                names.append(name)
                details.append(f"{name} {delta:+.4f}° (3σ {3 * math.sqrt(vals[1] ** 2 + vals[3] ** 2):.4f}°)")
        if verdict.dof:
            verdict.statistic = stat
            verdict.threshold = float(chi2.ppf(1 - alpha, verdict.dof))
            verdict.p_value = float(chi2.sf(stat, verdict.dof))
            verdict.joints = names
            if stat > verdict.threshold:
                verdict.drifted = True
                verdict.reasons.append(
                    f"offsets moved: χ² = {stat:.1f} > {verdict.threshold:.1f} (k = {verdict.dof}, α = {alpha:g}, "
                    f"p = {verdict.p_value:.2g})" + (f"; beyond 3 combined σ: {', '.join(details)}" if names else ""))
    return verdict
