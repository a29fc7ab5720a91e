"""How far held-out configurations lie from a fit's prediction, in units of the spread the fit
itself predicts for them — a Birge ratio measured on data the fit never saw — and the intervals
scaled by it.

**The ratio.** A fit on the training folds (``calib.fit.offsets.ModeFit``) predicts a held-out
coordinate with variance

    v = s² + (J C Jᵀ)_ii,    s² = σ² · N / (N − p_eff),    C = H⁻¹ · N / (N − p_eff)

σ the fit's noise (its mode: SSE/(N+1), N coordinates), H = JᵀWJ + P the Gauss–Newton precision
with the Gaussian priors P, p_eff = tr(JᵀWJ H⁻¹) the parameters the data pay for (the priors pay
for the rest), J the held-out rows' Jacobian. The ratio R = √(Σ r²/v / n) over all held-out
coordinates of all folds is 1 (± √(1/2n), 0.04 for 300 coordinates) when the model describes the
robot, and above 1 where the fit bent its parameters to errors it does not describe (which then
come back, unexplained, in the held-out configurations). What a model takes for noise — its σ
grows to hold it — shows only in that part: R measures how far the intervals are too narrow
*given* σ, and the guard on σ against the sensor's noise (``calib.robot.controller``) the rest.
The raw ratio of held-out rms to σ is not R: on simulated cells whose model is exactly right it
is 1.2 (the fit's σ is the in-sample residual, and the held-out prediction carries the
parameters' own uncertainty) where R is 1.01–1.02; the same sagging cells fitted without the
compliance give R 1.2–1.4, TX60 cells with 0.3–1 mm link errors fitted by offsets alone 1.06–1.17
(the right model 0.99–1.01) (``tests/calib/test_heldout_misfit.py``).

**The scale.** Where R > 1, the chosen model's offsets are reported with their intervals widened
by R about the posterior mean (``scale_offset_intervals``): the Birge ratio's classical use (Birge
1932; the Particle Data Group's scale factor S = √(χ²/(N−1)), applied only when S > 1). Measured
on held-out data, it cannot be bought down by fitting the scored points, and it is per candidate
model: a model that describes the robot is not penalised for another's misfit. It widens the
intervals for errors that behave like noise across configurations; it cannot repair a bias that a
missing term puts into every configuration alike — that is what the model choice and the
guards (held-out error against the sensor noise, ``calib.robot.controller``) are for.
"""

from __future__ import annotations

import math

import numpy as np

from calib.measure.dataset import Dataset


def heldout_chi2(mf, test: Dataset) -> tuple[float, int]:
    """(Σ r²/v over the coordinates of ``test``, their number) for the mode fit ``mf``
    (``calib.fit.offsets.ModeFit``) on other configurations; see the module's docstring."""
    from calib.fit.offsets import _prior_precision
    from calib.fit.posterior import OffsetPosterior

    post = mf.post
    sig2 = np.exp(2.0 * np.asarray(mf.log_sigma))[post.sensor_index]  # (k,)
    j = post.jacobian(mf.theta).reshape(post.n_rows, 3, -1)
    h_data = np.einsum("kip,k,kiq->pq", j, 1.0 / sig2, j)
    h_inv = np.linalg.pinv(h_data + _prior_precision(post))
    n = 3 * post.n_rows
    p_eff = float(np.trace(h_data @ h_inv))
    inflate = n / max(n - p_eff, 1.0)
    other = OffsetPosterior(post.chain, test, mf.b2s0, mf.mask, error=post.error, nu=post.nu, link_prior=mf.link_prior,
                            compliance=bool(post.C), sag_params=mf.sag_params, orientation=False)
    r = other.residuals(mf.theta)  # (k', 3): positions (as the CV scores; attitude rows would re-fit the target frame)
    jt = other.jacobian(mf.theta).reshape(other.n_rows, 3, -1)
    s2 = np.exp(2.0 * np.asarray(mf.log_sigma))[[post.sensors.index(s) for s in test.sensor]] * inflate  # (k',)
    var = s2[:, None] + inflate * np.einsum("kip,pq,kiq->ki", jt, h_inv, jt)
    return float(np.sum(r**2 / var)), int(r.size)


def birge_ratio(chi2: float, count: int) -> float | None:
    """√(χ²/n), or None without held-out coordinates."""
    return math.sqrt(chi2 / count) if count else None


def scale_offset_intervals(doc: dict, factor: float) -> None:
    """Widen every fitted offset's std and 95 % interval of the result document ``doc`` by
    ``factor`` (> 1) about its value, in place, and record it under ``doc["interval_scale"]``."""
    for j in doc.get("joint_offsets", []):
        if j.get("std_deg") is None or j.get("ci95_deg") is None or j.get("value_deg") is None:
            continue
        v = j["value_deg"]
        j["std_deg"] = j["std_deg"] * factor
        j["ci95_deg"] = [v + factor * (c - v) for c in j["ci95_deg"]]
    doc["interval_scale"] = {
        "factor": factor,
        "why": f"σ scaled ×{factor:.2f} by held-out misfit: held-out configurations lie {factor:.2f}× as far from "
               "the chosen model's predictions as its own uncertainty says (a Birge ratio on data the fit never saw)"}
