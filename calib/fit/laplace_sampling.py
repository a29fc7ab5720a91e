"""The default posterior of ``calib.fit.offsets`` (``method="laplace"``): the Laplace approximation,
checked by importance sampling, with a random walk in its whitened coordinates where the check fails.

1. Draw S points from the Laplace approximation — the Levenberg–Marquardt solution and its
   Gauss–Newton covariance — as a Student t with 10 degrees of freedom (``laplace_importance``).
2. Weight them by target / proposal and smooth the weights (PSIS, ``calib.fit.psis``). When the
   Pareto k̂ is below 0.7 the Gaussian covers the posterior's mass: the weighted draws are the
   posterior (resampled by their weights into ``n_chains × n_draws`` draws, so the moments
   downstream are the importance-weighted moments).
3. Otherwise (a curved or heavy-tailed posterior) random-walk Metropolis in the
   Laplace-whitened coordinates with the optimal scale adapted during the burn-in
   (``random_walk``): it mixes in the ~40 parameters of an offsets+tool+links model, where
   ``emcee``'s ensemble moves did not. R-hat and ESS over its chains are checked as for every
   sampler, and the R-hat of the log density besides.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np

from calib.fit.psis import KHAT_MAX, psis
from calib.fit.sampling import Chains

LogTarget = Callable[[np.ndarray], np.ndarray]  # (b, d) -> (b,)
#: Told what a sampler is doing: (a line, the fraction of its work done or None).
Told = Callable[..., None]


def _evaluate(log_target: LogTarget, x: np.ndarray, batch: int = 256) -> np.ndarray:
    """log_target at x (N, d) in batches: 256 proposals × a few hundred rows keep the walk's arrays in
    cache (1024 were a third slower per proposal on the UR10 data)."""
    return np.concatenate([np.asarray(log_target(x[i: i + batch]), dtype=float) for i in range(0, len(x), batch)])


#: The fast predictor's log density may differ from the exact one's by this much (nats, std over a
#: check subset of the proposals) before every proposal is weighted by the exact one instead.
MAX_PREDICTOR_LOGP_STD = 0.05
N_PREDICTOR_CHECK = 256


def _t_logpdf(x: np.ndarray, mean: np.ndarray, chol: np.ndarray, df: float | None) -> np.ndarray:
    """Log density (b,) of the multivariate t (None: Gaussian) with ``mean`` (d,) and scale
    ``chol`` @ ``chol``ᵀ at points x (b, d), up to the constant shared by every t of this ``df``
    and dimension (the weights are normalised, and the stages of one fit share their df)."""
    from scipy.linalg import solve_triangular

    z = solve_triangular(chol, (x - mean).T, lower=True).T
    log_det = float(np.sum(np.log(np.abs(np.diag(chol)))))
    q2 = np.sum(z * z, axis=1)
    if df is None:
        return -0.5 * q2 - log_det
    return -0.5 * (df + mean.size) * np.log1p(q2 / df) - log_det


def _t_constant(df: float | None, d: int) -> float:
    """The log normalising constant ``_t_logpdf`` leaves out: needed where stages of different df mix."""
    from calib.fit.sampling import student_t_logpdf_constant

    return -0.5 * d * math.log(2 * math.pi) if df is None else student_t_logpdf_constant(df, d)


def _t_draws(rng: np.random.Generator, mean: np.ndarray, chol: np.ndarray, df: float | None, n: int) -> np.ndarray:
    """n draws (n, d) of the multivariate t (None: Gaussian) with ``mean`` and scale ``chol`` @ ``chol``ᵀ."""
    z = rng.standard_normal((n, mean.size))
    if df is not None:
        z = z / np.sqrt(rng.chisquare(df, n) / df)[:, None]
    return mean + z @ chol.T


#: The importance check draws its proposals in chunks of this many (at least ``n_chains × n_draws``)
#: and judges the weights after each.
CHUNK = 4000
#: The Laplace stage stops before ``min_proposals`` where k̂ is below ``EARLY_KHAT`` — finite-variance
#: weights, far from the 0.7 limit (a few thousand draws can under-estimate k̂: on UR10 series D 4 000
#: draws gave 0.53 where 16 000 gave 0.74) — with ``EARLY_MIN_ESS`` effective draws: means to a few
#: hundredths of a standard deviation.
EARLY_KHAT = 0.3
EARLY_MIN_ESS = 1000.0
#: A stage whose k̂ is ≥ 0.7 after this many of its own draws gives way to an adapted one.
STAGE_MIN_DRAWS = 8000
#: Adapted stages of the importance check (``laplace_importance``) before the random walk: the
#: proposal moved to the weighted draws' mean and covariance, every stage's draws kept.
ADAPT_STAGES = 2
#: An adapted stage needs this many effective draws per parameter before it: fewer cannot say
#: where the mass is (its covariance would be noise).
ADAPT_MIN_ESS_PER_DIM = 2.0
#: The adapted proposals' scale: the weighted covariance, this much wider (their tails must not
#: fall under the target's).
ADAPT_INFLATE = 1.1


def _weighted_moments(x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (d,) and covariance (d, d) of draws x (N, d) under normalised weights w (N,)."""
    mean = w @ x
    dev = x - mean
    cov = dev.T @ (dev * w[:, None])
    return mean, 0.5 * (cov + cov.T)


def _agrees(mean: np.ndarray, cov: np.ndarray, ref_mean: np.ndarray, ref_cov: np.ndarray) -> bool:
    """Whether weighted moments are those an adapted stage was drawn with: every mean within a
    tenth of a standard deviation, every standard deviation within 10 % (else the adaptation has
    not settled: adapt again)."""
    sd, ref_sd = np.sqrt(np.maximum(np.diag(cov), 0.0)), np.sqrt(np.diag(ref_cov))
    return bool(np.all(np.abs(mean - ref_mean) <= 0.1 * ref_sd) and np.all(np.abs(sd / ref_sd - 1.0) <= 0.1))


def laplace_importance(log_target: LogTarget, mode: np.ndarray, cov: np.ndarray, *, n_chains: int = 4,
                       n_draws: int = 1000, seed: int = 0, oversample: int = 2,
                       min_proposals: int = 16000, df: float = 10.0, adapt: int = ADAPT_STAGES,
                       adapt_df: float = 5.0, exact_target: LogTarget | None = None,
                       progress: Told | None = None) -> tuple[Chains | None, dict]:
    """Importance sampling of ``log_target`` with the Laplace approximation as the proposal: mean
    ``mode`` (d,), covariance ``cov`` (d, d), as a multivariate Student t with ``df`` degrees of
    freedom (None: the Gaussian itself). With σ integrated out the posterior of θ has t-like tails
    (∝ E(θ)^(−(3n+1)/2)); the Gaussian's lighter tails under-weight them and push k̂ up (0.65–0.71
    on the README's example run), a t with 10 dof covers them (k̂ ≈ −0.1, ESS 7000 of 16000).

    The proposals come in chunks (``CHUNK``) and the PSIS weights are judged after each: the check
    passes with k̂ < 0.7 on at least ``min_proposals`` draws, or earlier with k̂ < ``EARLY_KHAT``
    and ``EARLY_MIN_ESS`` effective draws. Where k̂ is ≥ 0.7 after ``STAGE_MIN_DRAWS`` draws of a
    stage — a posterior whose mean is a fraction of a standard deviation off the mode, or whose
    tails curve away from the Laplace Gaussian's — up to ``adapt`` further stages draw from a t
    with ``adapt_df`` degrees of freedom at the current weighted mean and covariance
    (×``ADAPT_INFLATE``²), and every draw of every stage is weighted by the target over the mixture
    of all the stages' proposals in proportion to their draws (the deterministic mixture, or
    balance heuristic, of multiple importance sampling: Veach & Guibas 1995, Owen & Zhou 2000; the
    adaptation is that of adaptive multiple importance sampling, Cornuet et al. 2012). The mixture
    keeps the Laplace proposal, so no region it covered is lost; PSIS judges the final weights as it
    judged the first. On real UR10 data (series D, 120 configurations, 29 parameters) the Laplace
    stage gave k̂ 0.74 and one adapted stage 0.60, where the random walk had needed 32 chains ×
    26 000 steps.

    ``exact_target``: the same density without ``log_target``'s shortcuts (an expansion of the
    kinematics). It is evaluated on ``N_PREDICTOR_CHECK`` of the first proposals; where the two
    differ by more than ``MAX_PREDICTOR_LOGP_STD`` nats (std), every proposal is weighted by the
    exact one (the expansion's neglected terms matter where link and offset directions are nearly
    degenerate). ``progress``: told what the check is doing (stage, draws, k̂) and its fraction done.

    Returns (draws or None, diagnostics): draws as ``Chains`` (n_chains, n_draws, d) resampled by
    the PSIS weights when the check passes, else None. Diagnostics: ``k_hat`` (of the final
    weights), ``k_hat_stages`` (at the end of each stage), ``ess`` (of the weights),
    ``n_proposals`` (all stages), ``stages``, ``seconds``, ``predictor`` ("expansion" or "exact"),
    ``predictor_logp_std``, and ``mean``/``covariance`` (d,)/(d, d): the weighted moments."""
    t0 = time.perf_counter()
    mode = np.asarray(mode, dtype=float)
    d = mode.size
    rng = np.random.default_rng(seed)
    n = max(oversample * n_chains * n_draws, min_proposals)  # k̂ of a few thousand weights is noisy
    chunk = min(n, max(n_chains * n_draws, CHUNK))
    stages = [(mode, np.linalg.cholesky(cov + 1e-300 * np.eye(d)), df)]
    counts = [0]
    x, log_p = np.zeros((0, d)), np.zeros(0)
    predictor, spread, k_stages = "exact" if exact_target is None else "expansion", None, []
    limit = n * (1 + adapt)
    while True:
        m, c, f = stages[-1]
        new = _t_draws(rng, m, c, f, chunk)
        lp_new = _evaluate(log_target, new)
        if exact_target is not None and spread is None:  # the predictor's check, on the first chunk
            sub = rng.choice(chunk, size=min(N_PREDICTOR_CHECK, chunk), replace=False)
            diff = _evaluate(exact_target, new[sub]) - lp_new[sub]
            spread = float(np.std(diff)) if np.all(np.isfinite(diff)) else float("inf")
            if spread > MAX_PREDICTOR_LOGP_STD:
                lp_new, predictor, log_target = _evaluate(exact_target, new), "exact", exact_target
        x, log_p = np.concatenate([x, new]), np.concatenate([log_p, lp_new])
        counts[-1] += chunk
        total = x.shape[0]
        # Every draw against the mixture of the stages' proposals, each in proportion to its draws.
        log_q = np.logaddexp.reduce([math.log(k / total) + _t_logpdf(x, sm, sc, sf) + _t_constant(sf, d)
                                     for (sm, sc, sf), k in zip(stages, counts)], axis=0)
        res = psis(np.where(np.isfinite(log_p), log_p - log_q, -np.inf))
        if progress is not None:
            what = "Laplace proposal" if len(stages) == 1 else f"adapted stage {len(stages) - 1} of at most {adapt}"
            progress(f"importance check: {what}, {total} draws, Pareto k̂ {res.k_hat:.2f}, {res.ess:.0f} effective",
                     min(total / limit, 1.0))
        if len(stages) == 1 and res.k_hat < EARLY_KHAT and res.ess >= EARLY_MIN_ESS:
            break
        mean, wcov = _weighted_moments(x, res.weights)
        settled = len(stages) == 1 or _agrees(mean, wcov, m, c @ c.T / ADAPT_INFLATE**2)
        if (total >= n and res.reliable and settled) or total >= limit:
            break
        if (not res.reliable or not settled) and counts[-1] >= STAGE_MIN_DRAWS:
            k_stages.append(res.k_hat)
            if len(stages) > adapt or res.ess < ADAPT_MIN_ESS_PER_DIM * d:
                break
            try:
                stages.append((mean, np.linalg.cholesky(wcov * ADAPT_INFLATE**2), adapt_df))
            except np.linalg.LinAlgError:
                break
            counts.append(0)
    k_stages.append(res.k_hat)
    mean, wcov = _weighted_moments(x, res.weights)
    diag = {"k_hat": res.k_hat, "k_hat_max": KHAT_MAX, "k_hat_stages": k_stages, "stages": len(stages),
            "ess": res.ess, "n_proposals": int(x.shape[0]), "proposal_df": df, "predictor": predictor,
            "predictor_logp_std": spread, "seconds": time.perf_counter() - t0, "mean": mean, "covariance": wcov}
    if not res.reliable:
        return None, diag
    pick = rng.choice(x.shape[0], size=n_chains * n_draws, replace=True, p=res.weights)
    draws = x[pick].reshape(n_chains, n_draws, d)
    diag["seconds"] = time.perf_counter() - t0
    how = "laplace + PSIS importance sampling" + (f" ({len(stages) - 1} adapted stage(s))" if len(stages) > 1 else "")
    return Chains(draws, np.full(n_chains, res.ess / x.shape[0]), diag["seconds"], how,
                  pick.reshape(n_chains, n_draws)), diag


def _whitening(cov: np.ndarray) -> np.ndarray:
    """A square root L (d, d) of ``cov`` (L Lᵀ = cov): of the correlation matrix by its
    eigen-decomposition (a Gauss–Newton covariance may be singular to rounding: its tiny
    eigenvalues are floored), scaled by the standard deviations — parameters in mm and rad
    differ by ten orders in variance, which a floor on the covariance's own eigenvalues would not
    respect."""
    cov = 0.5 * (cov + cov.T)
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    w, v = np.linalg.eigh(cov / np.outer(sd, sd))
    w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
    return sd[:, None] * (v * np.sqrt(w))


#: The random walk runs until the kept half has split R-hat below this — of every coordinate and
#: of the log density — and ``WALK_MIN_ESS`` effective draws (or ``max_steps``); the guards
#: downstream judge what it reached.
WALK_RHAT = 1.02
WALK_MIN_ESS = 400.0
#: Most steps the walk takes before it is judged as it stands. Real UR10 data (series D, 120
#: configurations, offsets+tool+links+compliance, 29 parameters) have a posterior whose marginals
#: the Laplace approximation gets to 5 % but whose tails are curved — J5's zero against a₅ (a shift
#: along x₅, which turns with J5: the two move the wrist alike, to first order, when the marker sits
#: near the J6 axis) and the T-Mac's z against the tracker's x, y — so the importance check fails
#: (k̂ 0.72–0.85 with seeds) and the walk mixes slowly along them: R-hat 1.10 after 12 000 steps
#: (the former limit, and the reason the fit said "do not enter"), 1.02 with 1 446 effective draws
#: after 40 000 (7 minutes on a loaded 2-core machine; the walk stops as soon as it has settled).
WALK_MAX_STEPS = 48000
#: Keep every this-many steps (the chains' autocorrelation time in 40 dimensions is ~100 steps).
WALK_STORE_EVERY = 10


def random_walk(log_target: LogTarget, mode: np.ndarray, cov: np.ndarray, *, n_chains: int = 32,
                burn_in: int = 2000, block: int = 2000, max_steps: int = WALK_MAX_STEPS, seed: int = 0,
                progress: Told | None = None) -> Chains:
    """Random-walk Metropolis in the coordinates the Laplace approximation whitens, x = mode + L z
    with L Lᵀ = ``cov``: ``n_chains`` chains in parallel (one batch of the target per step), each
    proposing z' = z + s·N(0, I).

    Where the Laplace covariance is roughly right, the whitened posterior is roughly N(0, I) and
    the random walk's optimal scale is known: s ≈ 2.38/√d, acceptance ≈ 0.234 (Roberts, Gelman &
    Gilks 1997); during ``burn_in`` s is adapted to that acceptance (Robbins–Monro on log s), and
    at a third and two thirds of it the coordinates are re-whitened by the chains' own covariance
    (where the Laplace covariance missed a correlation); then both are fixed, so the kept steps
    are one Markov chain's. It replaced ``emcee`` here: in 40
    dimensions the stretch move did not mix (R-hat 1.7–2.1), and differential evolution, on a
    Gaussian whose Laplace covariance was 0.3–1× the truth per direction, still had the spread
    8–12 % short after 5900 steps with R-hat 1.04 — where this walk gives 0.97–1.04 in 6000 steps
    and a second.

    The chains start over-dispersed (2 N(0, I) in whitened coordinates), so split R-hat means what
    it should. After the burn-in the walk grows by ``block`` steps (at most ``max_steps`` in all)
    until the second half of all steps, stored every ``WALK_STORE_EVERY``, has split R-hat ≤
    ``WALK_RHAT`` — of every coordinate and of the log density, which shows a walk still spreading
    out or drawing in first — and ``WALK_MIN_ESS`` effective draws. Returns (n_chains, kept, d)
    in the original coordinates with each chain's acceptance fraction and ``diagnostics`` (steps,
    scale, R-hat of the coordinates and of the log density, ESS, ``settled``), judged downstream
    (``calib.robot.controller.earned_reasons``)."""
    from calib.fit.sampling import effective_sample_size, split_rhat

    t0 = time.perf_counter()
    mode = np.asarray(mode, dtype=float)
    d = mode.size
    rng = np.random.default_rng(seed)
    root = _whitening(np.asarray(cov, dtype=float))

    def log_prob(z: np.ndarray) -> np.ndarray:
        out = _evaluate(log_target, mode + z @ root.T)
        return np.where(np.isfinite(out), out, -np.inf)

    z = 2.0 * rng.standard_normal((n_chains, d))
    lp = log_prob(z)
    scale = 2.38 / np.sqrt(d)
    stored_z, stored_lp, accepted = [], [], np.zeros(n_chains)
    step, target_steps = 0, max(2 * burn_in, burn_in + block)
    # Where the Laplace covariance is far off (a correlation it missed), the chains' own spread
    # re-whitens the walk twice during the burn-in (Haario et al. 2001's adaptive Metropolis, frozen after it).
    rewhiten_at = {burn_in // 3, 2 * burn_in // 3}
    recent: list[np.ndarray] = []
    while True:
        while step < target_steps:
            prop = z + scale * rng.standard_normal(z.shape)
            lpp = log_prob(prop)
            acc = np.log(rng.uniform(size=n_chains)) < lpp - lp
            z[acc], lp[acc] = prop[acc], lpp[acc]
            if step < burn_in:
                scale *= np.exp((acc.mean() - 0.234) / np.sqrt((step % max(burn_in // 3, 1)) + 1.0))
                recent.append(z.copy())
                if step + 1 in rewhiten_at:
                    pts = np.concatenate(recent[len(recent) // 2:])  # the later half since the last re-whitening
                    c = np.cov(pts.T).reshape(d, d) + 1e-9 * np.eye(d)
                    lz = np.linalg.cholesky(c)
                    root, z = root @ lz, np.linalg.solve(lz, z.T).T  # same points, new coordinates
                    recent, scale = [], 2.38 / np.sqrt(d)
            else:
                accepted += acc
            step += 1
            if step % WALK_STORE_EVERY == 0:
                stored_z.append(z.copy())
                stored_lp.append(lp.copy())
        kept = np.swapaxes(np.array(stored_z[len(stored_z) // 2:]), 0, 1)  # (chains, kept, d), whitened
        kept_lp = np.swapaxes(np.array(stored_lp[len(stored_lp) // 2:]), 0, 1)[..., None]
        rhat = float(split_rhat(kept).max())
        rhat_lp = float(split_rhat(kept_lp)[0])
        ess = float(effective_sample_size(kept).min())
        settled = max(rhat, rhat_lp) <= WALK_RHAT and ess >= WALK_MIN_ESS
        if progress is not None:
            progress(f"random walk: {step} of at most {max_steps} steps × {n_chains} chains, R-hat "
                     f"{max(rhat, rhat_lp):.3f} (≤ {WALK_RHAT}), {ess:.0f} effective draws (≥ {WALK_MIN_ESS:.0f})", step / max_steps)
        if settled or step + block > max_steps:
            break
        target_steps = step + block
    info = {"steps": step, "chains": n_chains, "scale": float(scale), "rhat_max": rhat, "rhat_log_density": rhat_lp,
            "ess_min": ess, "settled": bool(settled)}
    return Chains(mode + kept @ root.T, accepted / max(step - burn_in, 1), time.perf_counter() - t0,
                  f"random-walk Metropolis in Laplace-whitened coordinates (Laplace check failed; {n_chains} chains, "
                  f"{step} steps, the first half dropped; R-hat of the log density {rhat_lp:.3f})", diagnostics=info)
