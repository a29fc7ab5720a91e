"""Pareto-smoothed importance sampling (PSIS) and its k̂ diagnostic.

Vehtari, Simpson, Gelman, Yao, Gabry (2024), "Pareto smoothed importance sampling", JMLR 25.
Importance weights w_i = p(x_i) / q(x_i) of draws x_i ~ q have a right tail that a generalized
Pareto distribution (GPD) describes; its shape k̂ says how far the importance estimate can be
trusted:

    k̂ < 0.5   the weights have finite variance: the estimate is reliable;
    k̂ < 0.7   usable (the paper's practical threshold for S ≳ 2000 draws);
    k̂ ≥ 0.7   the proposal misses the target's mass: do not use the weighted estimate.

The tail (the M = min(S/5, 3√S) largest weights) is fitted by maximum likelihood with
``scipy.stats.genpareto`` (location fixed at the threshold weight; the paper uses Zhang and
Stephens' estimator with a weak prior — the two agree closely for M of a few hundred). The
smoothed weights replace the tail by the GPD's expected order statistics, capped at the largest
raw weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The paper's threshold above which the importance-weighted estimate is not used.
KHAT_MAX = 0.7


@dataclass(frozen=True)
class PsisResult:
    """``weights``: (S,) smoothed, normalised to sum 1; ``k_hat``: the tail shape; ``ess``: the
    effective sample size of the weights, 1 / Σ w²; ``tail``: how many weights were smoothed."""

    weights: np.ndarray
    k_hat: float
    ess: float
    tail: int

    @property
    def reliable(self) -> bool:
        return bool(np.isfinite(self.k_hat) and self.k_hat < KHAT_MAX)


def psis(log_weights: np.ndarray) -> PsisResult:
    """Smooth the importance weights whose logarithms are ``log_weights`` (S,) (−inf allowed: zero
    weight). Needs S ≥ 20 finite weights; fewer raises ValueError."""
    from scipy.stats import genpareto

    lw = np.asarray(log_weights, dtype=float).ravel()
    finite = np.isfinite(lw)
    if finite.sum() < 20:
        raise ValueError(f"PSIS needs at least 20 finite log weights, given {int(finite.sum())} of {lw.size}")
    lw = np.where(finite, lw - lw[finite].max(), -np.inf)
    s = lw.size
    m = int(min(0.2 * s, 3.0 * np.sqrt(s)))
    order = np.argsort(lw)
    tail_idx = order[-m:]
    cutoff = lw[order[-m - 1]]
    w = np.exp(lw)
    exceed = w[tail_idx] - np.exp(cutoff)
    k_hat = np.inf
    if np.all(np.isfinite(exceed)) and exceed.max() > 0:
        k_hat, _, scale = genpareto.fit(exceed, floc=0.0)
        probs = (np.arange(1, m + 1) - 0.5) / m
        smoothed = np.exp(cutoff) + genpareto.ppf(probs, k_hat, loc=0.0, scale=scale)
        w[tail_idx] = np.minimum(smoothed, 1.0)  # sorted ascending like tail_idx; 1.0 = the largest raw weight
    w = w / w.sum()
    return PsisResult(weights=w, k_hat=float(k_hat), ess=float(1.0 / np.sum(w**2)), tail=m)
