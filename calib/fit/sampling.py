"""Posterior samplers and their convergence diagnostics.

Two samplers of the same target, ``log p(θ, log σ)`` from ``calib.fit.posterior``:

``paper_metropolis``  the remastering paper's sampler reproduced faithfully (Sec. IV): random-walk
    Metropolis in the paper's units (mm and degrees), uniform proposals ±0.0125 on every
    parameter and on σ, 2·10⁵ samples, burn-in to 1.75·10⁵, log-space acceptance (eq. 16),
    estimates as sample means and standard deviations.
``independence_mh``  the fast default: an independence Metropolis–Hastings sampler whose proposal
    is a multivariate Student-t centred on the posterior mode with the Laplace covariance. It is
    exact for the posterior (the MH correction removes any proposal mismatch); because the
    proposals do not depend on the chain state, their densities are evaluated in large batches
    by the batched kinematics, and several chains give R-hat.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

LogDensity = Callable[[np.ndarray], np.ndarray]  # (..., d) -> (...)


@dataclass(frozen=True)
class Chains:
    """Draws of several chains: samples (n_chains, n_draws, d); acceptance per chain."""

    samples: np.ndarray
    acceptance: np.ndarray
    seconds: float
    method: str
    proposal_index: np.ndarray | None = None  # (n_chains, n_draws): which proposal each draw holds (independence MH)
    diagnostics: dict | None = None  # the sampler's own (``calib.fit.laplace_sampling.random_walk``)

    @property
    def flat(self) -> np.ndarray:
        return self.samples.reshape(-1, self.samples.shape[-1])


# --- the paper's sampler -------------------------------------------------------------------
def paper_metropolis(
    log_density: LogDensity,
    x0: np.ndarray,
    *,
    unit_scale: np.ndarray,
    n_samples: int = 200_000,
    burn_in: int = 175_000,
    step: float = 0.0125,
    seed: int = 0,
) -> Chains:
    """Random-walk Metropolis exactly as in the paper.

    ``x0`` is the start in internal units (the paper starts at 0 and σ = 1 mm). ``unit_scale``
    converts internal units to the paper's (57.29… for radians → degrees, 1 for mm); the uniform
    ±``step`` proposal acts in the paper's units. A proposal with σ ≤ 0 is rejected. Returns the
    draws after ``burn_in`` (one chain). ``log_density`` takes and returns internal units.
    """
    if not 0 <= burn_in < n_samples:
        raise ValueError(f"burn_in must be in [0, n_samples), got {burn_in} of {n_samples}")
    rng = np.random.default_rng(seed)
    scale = np.asarray(unit_scale, dtype=float)
    x = np.asarray(x0, dtype=float).copy()
    lp = float(log_density(x))
    if not math.isfinite(lp):
        raise ValueError("the start point has zero posterior density")
    kept = np.empty((n_samples - burn_in, x.size))
    steps = rng.uniform(-step, step, size=(n_samples, x.size)) / scale
    log_u = np.log(rng.random(n_samples))
    accepted = 0
    t0 = time.perf_counter()
    for i in range(n_samples):
        y = x + steps[i]
        lq = float(log_density(y))
        if log_u[i] < lq - lp:
            x, lp = y, lq
            accepted += 1
        if i >= burn_in:
            kept[i - burn_in] = x
    return Chains(kept[None], np.array([accepted / n_samples]), time.perf_counter() - t0, "paper")


# --- fast exact sampler ----------------------------------------------------------------------
def _mvt_logpdf(z: np.ndarray, df: float) -> np.ndarray:
    """Log density of a standard multivariate t at whitened points z (..., d), up to a constant."""
    d = z.shape[-1]
    return -0.5 * (df + d) * np.log1p(np.sum(z * z, axis=-1) / df)


def independence_mh(
    log_density: LogDensity,
    mode: np.ndarray,
    covariance: np.ndarray,
    *,
    n_chains: int = 4,
    n_draws: int = 1000,
    burn_in: int = 100,
    df: float = 7.0,
    inflate: float = 1.2,
    batch: int = 1024,
    seed: int = 0,
) -> Chains:
    """Independence Metropolis–Hastings with a multivariate-t proposal around the mode.

    mode: (d,); covariance: (d, d) (Laplace approximation). Each chain starts from its own
    proposal draw, so R-hat compares over-dispersed starts. Returns (n_chains, n_draws, d).
    """
    mode = np.asarray(mode, dtype=float)
    d = mode.size
    chol = np.linalg.cholesky(np.asarray(covariance, dtype=float) * inflate**2)
    rng = np.random.default_rng(seed)
    total = n_draws + burn_in + 1
    n = n_chains * total
    z = rng.standard_normal((n, d))
    w = rng.chisquare(df, size=n) / df
    z = z / np.sqrt(w)[:, None]
    proposals = mode + z @ chol.T
    log_q = _mvt_logpdf(z, df)
    t0 = time.perf_counter()
    log_p = np.concatenate([np.asarray(log_density(proposals[i : i + batch])) for i in range(0, n, batch)])
    log_w = np.where(np.isfinite(log_p), log_p - log_q, -np.inf).reshape(n_chains, total)
    props = proposals.reshape(n_chains, total, d)
    log_u = np.log(rng.random((n_chains, total)))
    out = np.empty((n_chains, n_draws, d))
    held = np.empty((n_chains, n_draws), dtype=np.intp)
    acc = np.zeros(n_chains)
    for c in range(n_chains):
        cur = 0
        cur_w = log_w[c, 0]
        for i in range(1, total):
            if log_u[c, i] < log_w[c, i] - cur_w:
                cur, cur_w = i, log_w[c, i]
                if i > burn_in:
                    acc[c] += 1
            if i > burn_in:
                out[c, i - burn_in - 1] = props[c, cur]
                held[c, i - burn_in - 1] = c * total + cur
    return Chains(out, acc / n_draws, time.perf_counter() - t0, "independence-mh", held)


# --- diagnostics ---------------------------------------------------------------------------
def split_rhat(samples: np.ndarray) -> np.ndarray:
    """Split-R̂ (Gelman et al., BDA3 §11.4) per parameter; samples (n_chains, n_draws, d)."""
    c, n, d = samples.shape
    half = n // 2
    if half < 2:
        raise ValueError("need at least 4 draws per chain for split-R-hat")
    s = np.concatenate([samples[:, :half], samples[:, half : 2 * half]], axis=0)  # (2c, half, d)
    chain_means = s.mean(axis=1)
    b = half * chain_means.var(axis=0, ddof=1)
    w = s.var(axis=1, ddof=1).mean(axis=0)
    var_plus = (half - 1) / half * w + b / half
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.where(w > 0, var_plus / w, 1.0))


def effective_sample_size(samples: np.ndarray) -> np.ndarray:
    """Multi-chain ESS with Geyer's initial monotone sequence (BDA3 §11.5); (n_chains, n_draws, d)."""
    c, n, d = samples.shape
    x = samples - samples.mean(axis=1, keepdims=True)
    f = np.fft.rfft(x, n=2 * n, axis=1)
    acov = np.fft.irfft(f * np.conj(f), axis=1)[:, :n] / n  # (c, n, d)
    chain_var = samples.var(axis=1, ddof=1)  # (c, d)
    w = chain_var.mean(axis=0)
    b_over_n = samples.mean(axis=1).var(axis=0, ddof=1) if c > 1 else np.zeros(d)
    var_plus = (n - 1) / n * w + b_over_n
    ess = np.empty(d)
    for k in range(d):
        if var_plus[k] <= 0:
            ess[k] = c * n
            continue
        rho = 1.0 - (w[k] - acov[:, :, k].mean(axis=0)) / var_plus[k]
        rho[0] = 1.0
        total = 0.0
        prev_pair = math.inf
        for t in range(0, n - 1, 2):
            pair = rho[t] + rho[t + 1]
            if pair < 0:
                break
            pair = min(pair, prev_pair)
            total += pair
            prev_pair = pair
        tau = max(-1.0 + 2.0 * total, 1.0 / math.log10(max(c * n, 10)))
        ess[k] = c * n / tau
    return ess


def student_t_logpdf_constant(df: float, d: int) -> float:
    """Normalising constant of the standard multivariate t (for tests and reports)."""
    return float(math.lgamma((df + d) / 2) - math.lgamma(df / 2) - 0.5 * d * math.log(df * math.pi))
