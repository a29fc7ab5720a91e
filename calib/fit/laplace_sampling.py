"""The default posterior of ``calib.fit.offsets`` (``method="laplace"``): the Laplace approximation,
checked by importance sampling, with an ensemble sampler where the check fails.

1. Draw S points from the Laplace approximation — the Levenberg–Marquardt solution and its
   Gauss–Newton covariance — as a Student t with 10 degrees of freedom (``laplace_importance``).
2. Weight them by target / proposal and smooth the weights (PSIS, ``calib.fit.psis``). When the
   Pareto k̂ is below 0.7 the Gaussian covers the posterior's mass: the weighted draws are the
   posterior (resampled by their weights into ``n_chains × n_draws`` draws, so the moments
   downstream are the importance-weighted moments).
3. Otherwise (a curved or heavy-tailed posterior) the affine-invariant ensemble sampler of
   ``emcee`` (Goodman & Weare 2010; Foreman-Mackey et al. 2013), started from the Laplace draws;
   it is indifferent to linear correlations between parameters, which is what the offsets,
   registration and link parameters have. R-hat and ESS over its walkers are checked as for
   every sampler.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from calib.fit.psis import KHAT_MAX, psis
from calib.fit.sampling import Chains

LogTarget = Callable[[np.ndarray], np.ndarray]  # (b, d) -> (b,)


def _evaluate(log_target: LogTarget, x: np.ndarray, batch: int = 1024) -> np.ndarray:
    return np.concatenate([np.asarray(log_target(x[i: i + batch]), dtype=float) for i in range(0, len(x), batch)])


def laplace_importance(log_target: LogTarget, mode: np.ndarray, cov: np.ndarray, *, n_chains: int = 4,
                       n_draws: int = 1000, seed: int = 0, oversample: int = 2,
                       min_proposals: int = 16000, df: float = 10.0) -> tuple[Chains | None, dict]:
    """Importance sampling of ``log_target`` with the Laplace approximation as the proposal: mean
    ``mode`` (d,), covariance ``cov`` (d, d), as a multivariate Student t with ``df`` degrees of
    freedom (None: the Gaussian itself). With σ integrated out the posterior of θ has t-like tails
    (∝ E(θ)^(−(3n+1)/2)); the Gaussian's lighter tails under-weight them and push k̂ up (0.65–0.71
    on the README's example run), a t with 10 dof covers them (k̂ ≈ −0.1, ESS 7000 of 16000).

    Returns (draws or None, diagnostics): draws as ``Chains`` (n_chains, n_draws, d) resampled by
    the PSIS weights when k̂ < 0.7, else None. Diagnostics: ``k_hat``, ``ess`` (of the weights),
    ``n_proposals``, ``seconds``. At least ``min_proposals`` draws: the tail fit needs them."""
    t0 = time.perf_counter()
    mode = np.asarray(mode, dtype=float)
    rng = np.random.default_rng(seed)
    n = max(oversample * n_chains * n_draws, min_proposals)  # k̂ of a few thousand weights is noisy
    chol = np.linalg.cholesky(cov + 1e-300 * np.eye(mode.size))
    z = rng.standard_normal((n, mode.size))
    if df is None:
        log_q = -0.5 * np.sum(z * z, axis=1)  # up to a constant: the weights are normalised
    else:
        z = z / np.sqrt(rng.chisquare(df, n) / df)[:, None]
        log_q = -0.5 * (df + mode.size) * np.log1p(np.sum(z * z, axis=1) / df)
    x = mode + z @ chol.T
    log_p = _evaluate(log_target, x)
    res = psis(np.where(np.isfinite(log_p), log_p - log_q, -np.inf))
    diag = {"k_hat": res.k_hat, "k_hat_max": KHAT_MAX, "ess": res.ess, "n_proposals": n, "proposal_df": df,
            "seconds": time.perf_counter() - t0}
    if not res.reliable:
        return None, diag
    pick = rng.choice(n, size=n_chains * n_draws, replace=True, p=res.weights)
    draws = x[pick].reshape(n_chains, n_draws, mode.size)
    diag["seconds"] = time.perf_counter() - t0
    return Chains(draws, np.full(n_chains, res.ess / n), diag["seconds"], "laplace + PSIS importance sampling",
                  pick.reshape(n_chains, n_draws)), diag


def ensemble(log_target: LogTarget, mode: np.ndarray, cov: np.ndarray, *, n_draws: int = 1000, burn_in: int = 1000,
             seed: int = 0, max_steps: int = 2000) -> Chains:
    """emcee's affine-invariant ensemble sampler: 2·d + 2 walkers (at least 32) started from the
    Laplace Gaussian; ``burn_in`` steps dropped, then at least ``n_draws`` steps, extended (up to
    ``max_steps`` in all) until the run is 50 integrated autocorrelation times τ long (emcee's
    own rule), and thinned by τ/2, so each walker's kept draws are nearly independent and split
    R-hat over the walkers means what it means for independent chains. Returns (walkers, kept, d)
    with the walkers' acceptance fractions."""
    import emcee

    t0 = time.perf_counter()
    mode = np.asarray(mode, dtype=float)
    d = mode.size
    walkers = max(2 * d + 2, 32)
    rng = np.random.default_rng(seed)
    start = rng.multivariate_normal(mode, cov, size=walkers, method="cholesky")

    def log_prob(x: np.ndarray) -> np.ndarray:
        out = _evaluate(log_target, x)
        return np.where(np.isfinite(out), out, -np.inf)

    sampler = emcee.EnsembleSampler(walkers, d, log_prob, vectorize=True)
    sampler.random_state = np.random.RandomState(seed).get_state()
    state = sampler.run_mcmc(start, burn_in + n_draws, progress=False)
    while True:
        tau = float(np.max(sampler.get_autocorr_time(discard=burn_in, tol=0)))
        kept = sampler.iteration - burn_in
        if kept >= 50 * tau or sampler.iteration + n_draws > max_steps:
            break
        state = sampler.run_mcmc(state, n_draws, progress=False)
    thin = max(1, int(np.ceil(tau / 2)))
    chain = sampler.get_chain(discard=burn_in, thin=thin)  # (kept / thin, walkers, d)
    return Chains(np.swapaxes(chain, 0, 1), np.asarray(sampler.acceptance_fraction), time.perf_counter() - t0,
                  f"emcee affine-invariant ensemble (Laplace check failed; τ {tau:.0f} steps, thinned by {thin})")
