"""Registration statistics: the tests the registration seed uses to compare registrations.

From ``registration-strategies`` (Van Wyk & Marvel, IEEE T-ASE 2018), Sec. II-C, IV and V:

``spatial_correlation``   Pearson r (and its p-value) between the translation error e and the
                          distance of each point from the sensor frame's origin (Sec. IV-A,
                          Table I). Significant r means the errors grow across the workspace.
``ks_two_sample``         two-sample Kolmogorov–Smirnov: do two registrations' error samples come
                          from one distribution (Sec. IV-B)?
``brown_forsythe_levene`` Levene's test with the Brown–Forsythe (median-centred) statistic: equal
                          error variances (Sec. IV-C)?
``mean_difference_test``  t-test on the mean errors (Sec. IV-D). Rule: Welch's t-test when the
                          Brown–Forsythe test rejects equal variances at the same alpha,
                          Student's pooled t-test otherwise (the seed: "depending on the outcome
                          of the Levene test, an appropriate Student's T-test").
``compare_registrations`` the three above in the seed's order, as in its Table II.
``success_probability_bound``  eq. (18): from m successes in n trials, the probability of
                          success PS that can be claimed at confidence CL (Sec. V, Table III).
``correlation``           Pearson r of any two samples (Sec. V correlates max(e) with PS).

Every function returns a small frozen dataclass with the statistic, the p-value and a
plain-language ``decision`` at the given ``alpha`` (the seed uses a 95 % confidence level,
alpha = 0.05). scipy.stats does the arithmetic; inputs are checked here so that degenerate
samples raise ``ValueError`` instead of returning NaN with a warning.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


def _sample(name: str, x: object, min_n: int) -> np.ndarray:
    """Validate a 1-D finite sample with at least ``min_n`` values."""
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a 1-D array of numbers; got {type(x).__name__}") from exc
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D (one value per point); got shape {a.shape}")
    if a.size < min_n:
        raise ValueError(f"{name} needs at least {min_n} values; got {a.size}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} holds non-finite values (NaN or inf) at {np.flatnonzero(~np.isfinite(a)).tolist()}")
    return a


def _alpha(alpha: float) -> float:
    if not (isinstance(alpha, (int, float)) and 0.0 < alpha < 1.0):
        raise ValueError(f"alpha must be a significance level strictly between 0 and 1; got {alpha!r}")
    return float(alpha)


def _pct(alpha: float) -> str:
    return f"{100.0 * (1.0 - alpha):g} %"


@dataclass(frozen=True)
class Correlation:
    """Pearson correlation. r in [−1, 1]; p_value two-sided for H0: r = 0; n pairs."""

    r: float
    p_value: float
    n: int
    alpha: float
    significant: bool
    decision: str


def correlation(x: np.ndarray, y: np.ndarray, alpha: float = 0.05, what: str = "x and y") -> Correlation:
    """Pearson r between x (n,) and y (n,), n ≥ 3, with its two-sided p-value (t with n−2 dof)."""
    alpha = _alpha(alpha)
    a = _sample("x", x, 3)
    b = _sample("y", y, 3)
    if a.shape != b.shape:
        raise ValueError(f"x and y must pair up (same length); got {a.size} and {b.size}")
    for name, v in (("x", a), ("y", b)):
        if np.ptp(v) == 0.0:
            raise ValueError(f"{name} is constant ({v[0]!r}); a correlation with a constant is undefined")
    # Pearson's r and its two-sided p from Student's t with n − 2 dof (what scipy.stats.pearsonr
    # computes; scipy.special alone, so the default fit does not load scipy.stats for it)
    from scipy.special import stdtr

    r = float(np.clip(np.corrcoef(a, b)[0, 1], -1.0, 1.0))
    dof = a.size - 2
    t = r * math.sqrt(dof / max(1.0 - r * r, 1e-300))
    p = float(min(1.0, 2.0 * stdtr(dof, -abs(t))))
    sig = p < alpha
    decision = (
        f"{what} are correlated (r = {r:.3f}, p = {p:.3g} < {alpha:g}) at {_pct(alpha)} confidence"
        if sig
        else f"no significant correlation between {what} (r = {r:.3f}, p = {p:.3g} ≥ {alpha:g})"
    )
    return Correlation(r=r, p_value=p, n=int(a.size), alpha=alpha, significant=sig, decision=decision)


def spatial_correlation(
    errors_mm: np.ndarray, points_sensor: np.ndarray, origin_mm: np.ndarray | None = None, alpha: float = 0.05
) -> Correlation:
    """Spatial correlation of the registration seed, Sec. IV-A (Table I).

    Pearson r between the translation error e_i (n,), mm, and the distance |p_i − origin| of
    each point p_i (n, 3), sensor frame, mm, from the origin of the sensor frame N (or
    ``origin_mm`` (3,) if given). A significant positive r means the registration error grows
    with distance from the origin — the spatially correlated error the combinatorial and
    annealing strategies are meant to remove, and a warning that the later tests' error rates
    assume independent samples.
    """
    e = _sample("errors_mm", errors_mm, 3)
    p = np.asarray(points_sensor, dtype=float)
    if p.shape != (e.size, 3):
        raise ValueError(f"points_sensor must have shape ({e.size}, 3), one point per error; got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("points_sensor holds non-finite values (NaN or inf)")
    o = np.zeros(3) if origin_mm is None else np.asarray(origin_mm, dtype=float)
    if o.shape != (3,) or not np.isfinite(o).all():
        raise ValueError(f"origin_mm must be a finite point of shape (3,); got {o!r}")
    dist = np.linalg.norm(p - o, axis=1)
    return correlation(dist, e, alpha, what="translation error and distance from the origin")


@dataclass(frozen=True)
class KSResult:
    """Two-sample Kolmogorov–Smirnov test. statistic D = max |F_a − F_b|; two-sided p-value."""

    statistic: float
    p_value: float
    alpha: float
    significant: bool
    decision: str


def ks_two_sample(a: np.ndarray, b: np.ndarray, alpha: float = 0.05) -> KSResult:
    """Two-sample KS test of errors a (n_a,) and b (n_b,), each ≥ 2 values (Sec. IV-B).

    scipy chooses the exact distribution for small samples and the asymptotic one otherwise.
    """
    alpha = _alpha(alpha)
    x, y = _sample("a", a, 2), _sample("b", b, 2)
    from scipy import stats

    res = stats.ks_2samp(x, y)
    d, p = float(res.statistic), float(res.pvalue)
    sig = p < alpha
    decision = (
        f"the error distributions differ (D = {d:.3f}, p = {p:.3g} < {alpha:g})"
        if sig
        else f"no significant difference between the error distributions (D = {d:.3f}, p = {p:.3g} ≥ {alpha:g})"
    )
    return KSResult(statistic=d, p_value=p, alpha=alpha, significant=sig, decision=decision)


@dataclass(frozen=True)
class LeveneResult:
    """Brown–Forsythe Levene test. statistic W ~ F(k−1, N−k) under H0 (equal variances)."""

    statistic: float
    p_value: float
    df: tuple[int, int]
    alpha: float
    significant: bool
    decision: str


def brown_forsythe_levene(*samples: np.ndarray, alpha: float = 0.05) -> LeveneResult:
    """Levene's test with the Brown–Forsythe statistic (deviations from each group's median).

    samples: k ≥ 2 groups (n_i,), each with ≥ 2 values (Sec. IV-C). W is the one-way ANOVA F of
    the absolute deviations |x_ij − median_i|.
    """
    alpha = _alpha(alpha)
    if len(samples) < 2:
        raise ValueError(f"Levene's test needs at least 2 samples; got {len(samples)}")
    groups = [_sample(f"sample {i}", s, 2) for i, s in enumerate(samples)]
    dev = [np.abs(g - np.median(g)) for g in groups]
    within = sum(float(((d - d.mean()) ** 2).sum()) for d in dev)
    if within == 0.0:
        raise ValueError(
            "every sample's absolute deviations from its median are identical within the sample; "
            "the Brown–Forsythe statistic is undefined (0/0 or ∞)"
        )
    from scipy import stats

    res = stats.levene(*groups, center="median")
    w, p = float(res.statistic), float(res.pvalue)
    n_total = sum(g.size for g in groups)
    df = (len(groups) - 1, n_total - len(groups))
    sig = p < alpha
    decision = (
        f"the error variances differ (W = {w:.3f}, p = {p:.3g} < {alpha:g})"
        if sig
        else f"no significant difference between the error variances (W = {w:.3f}, p = {p:.3g} ≥ {alpha:g})"
    )
    return LeveneResult(statistic=w, p_value=p, df=df, alpha=alpha, significant=sig, decision=decision)


@dataclass(frozen=True)
class TTestResult:
    """Two-sample t-test of means. welch: True for Welch's (unequal variances), False for
    Student's pooled test; df: degrees of freedom (Welch–Satterthwaite for Welch);
    levene_p_value: the Brown–Forsythe p-value that chose the variant (None if forced)."""

    statistic: float
    p_value: float
    df: float
    welch: bool
    levene_p_value: float | None
    alpha: float
    significant: bool
    decision: str


def mean_difference_test(
    a: np.ndarray, b: np.ndarray, alpha: float = 0.05, equal_var: bool | None = None
) -> TTestResult:
    """Two-sided t-test of mean(a) = mean(b) (Sec. IV-D), a and b each ≥ 2 values.

    Rule when ``equal_var`` is None: run ``brown_forsythe_levene`` at the same alpha; if it
    rejects equal variances use Welch's t-test, otherwise Student's pooled t-test. Pass
    ``equal_var`` to force one.
    """
    alpha = _alpha(alpha)
    x, y = _sample("a", a, 2), _sample("b", b, 2)
    va, vb = float(np.var(x, ddof=1)), float(np.var(y, ddof=1))
    if va == 0.0 and vb == 0.0:
        raise ValueError("both samples are constant; the t statistic is undefined (zero standard error)")
    lev_p: float | None = None
    if equal_var is None:
        lev = brown_forsythe_levene(x, y, alpha=alpha)
        lev_p = lev.p_value
        equal_var = not lev.significant
    from scipy import stats

    res = stats.ttest_ind(x, y, equal_var=equal_var)
    t, p = float(res.statistic), float(res.pvalue)
    if equal_var:
        df = float(x.size + y.size - 2)
    else:
        qa, qb = va / x.size, vb / y.size
        df = (qa + qb) ** 2 / (qa**2 / (x.size - 1) + qb**2 / (y.size - 1))
    sig = p < alpha
    kind = "Student (pooled)" if equal_var else "Welch"
    decision = (
        f"the mean errors differ ({kind} t = {t:.3f}, df = {df:.3g}, p = {p:.3g} < {alpha:g}): "
        f"mean {x.mean():.4g} vs {y.mean():.4g}"
        if sig
        else f"no significant difference in mean error ({kind} t = {t:.3f}, df = {df:.3g}, p = {p:.3g} ≥ {alpha:g})"
    )
    return TTestResult(
        statistic=t, p_value=p, df=df, welch=not equal_var, levene_p_value=lev_p, alpha=alpha, significant=sig,
        decision=decision,
    )


@dataclass(frozen=True)
class Comparison:
    """Two registrations compared as in the seed's Table II: KS, then Brown–Forsythe, then t.

    mean_mm, variance_mm2: (a, b) sample means (mm) and unbiased variances (mm²) of the errors.
    """

    ks: KSResult
    levene: LeveneResult
    ttest: TTestResult
    mean_mm: tuple[float, float]
    variance_mm2: tuple[float, float]

    @property
    def decision(self) -> str:
        """The three decisions, one line each."""
        return "\n".join(
            (f"distribution: {self.ks.decision}", f"variance: {self.levene.decision}", f"mean: {self.ttest.decision}")
        )


def compare_registrations(errors_a_mm: np.ndarray, errors_b_mm: np.ndarray, alpha: float = 0.05) -> Comparison:
    """Compare two registrations' translation errors (n_a,), (n_b,), mm (Sec. IV-B to IV-D)."""
    a, b = _sample("errors_a_mm", errors_a_mm, 2), _sample("errors_b_mm", errors_b_mm, 2)
    lev = brown_forsythe_levene(a, b, alpha=alpha)
    return Comparison(
        ks=ks_two_sample(a, b, alpha),
        levene=lev,
        ttest=mean_difference_test(a, b, alpha, equal_var=not lev.significant),
        mean_mm=(float(a.mean()), float(b.mean())),
        variance_mm2=(float(np.var(a, ddof=1)), float(np.var(b, ddof=1))),
    )


@dataclass(frozen=True)
class SuccessBound:
    """Probability-of-success bound, eq. (18) of the registration seed.

    ps: the seed's PS — the smallest p (on the ``precision`` grid if one is given) with
        F(m−1; n, p) ≤ CL. This is the one-sided Clopper–Pearson *lower* confidence bound:
        "with confidence CL, P(success) ≥ ps". (The seed calls it the "upper probability of
        success": the best PS the data let one claim.)
    upper: one-sided Clopper–Pearson upper bound at the same confidence: P(success) ≤ upper.
    p_value: if ``required`` was given, the exact one-sided binomial p-value for
        H0: P(success) ≤ required; else None.
    """

    ps: float
    upper: float
    successes: int
    trials: int
    confidence: float
    required: float | None
    p_value: float | None
    decision: str


def success_probability_bound(
    successes: int,
    trials: int,
    confidence: float = 0.95,
    precision: float | None = None,
    required: float | None = None,
) -> SuccessBound:
    """PS from m = ``successes`` of n = ``trials`` independent pass/fail trials, eq. (18).

    Eq. (18): F(m−1; n, PS) = Σ_{i=0}^{m−1} C(n, i) PS^i (1−PS)^(n−i) ≤ CL, PS its minimum
    (Gilliam et al. 2009 [24]). Solved exactly as the beta quantile
    ``PS = B⁻¹(1 − CL; m, n − m + 1)`` (PS = 0 when m = 0); with ``precision`` (e.g. 0.001, as
    the seed's Table III) PS is the smallest multiple of it that still satisfies (18), so it
    is never rounded down past the bound. Example: 160 of 160 insertions at CL = 0.95 gives
    PS = 0.05^(1/160) = 0.98145…, 0.982 at precision 0.001 — the seed's Table III value.

    required: optional target probability in (0, 1); the decision then says whether the data
    demonstrate P(success) > required at alpha = 1 − CL (exact binomial test).
    """
    from scipy import stats

    if int(trials) != trials or trials < 1:
        raise ValueError(f"trials must be a positive integer; got {trials!r}")
    if int(successes) != successes or not 0 <= successes <= trials:
        raise ValueError(f"successes must be an integer between 0 and trials ({trials}); got {successes!r}")
    if not (isinstance(confidence, (int, float)) and 0.0 < confidence < 1.0):
        raise ValueError(f"confidence must be strictly between 0 and 1 (e.g. 0.95); got {confidence!r}")
    if precision is not None and not (isinstance(precision, (int, float)) and 0.0 < precision < 1.0):
        raise ValueError(f"precision must be a step in (0, 1) such as 0.001, or None; got {precision!r}")
    if required is not None and not (isinstance(required, (int, float)) and 0.0 < required < 1.0):
        raise ValueError(f"required must be a probability strictly between 0 and 1, or None; got {required!r}")
    m, n, cl = int(successes), int(trials), float(confidence)

    def satisfies(p: float) -> bool:  # eq. (18)
        return m == 0 or float(stats.binom.cdf(m - 1, n, p)) <= cl

    ps = 0.0 if m == 0 else float(stats.beta.ppf(1.0 - cl, m, n - m + 1))
    if precision is not None:
        step = float(precision)
        k = math.floor(ps / step)
        while not satisfies(min(k * step, 1.0)) and k * step < 1.0:  # at most a couple of steps
            k += 1
        ps = min(round(k * step, 12), 1.0)
    upper = 1.0 if m == n else float(stats.beta.ppf(cl, m + 1, n - m))
    p_value: float | None = None
    claim = f"with {100 * cl:g} % confidence the probability of success is at least {ps:.4g} ({m} of {n} succeeded)"
    if required is not None:
        p_value = float(stats.binomtest(m, n, float(required), alternative="greater").pvalue)
        shown = p_value < 1.0 - cl
        claim += (
            f"; that it exceeds the required {required:g} is demonstrated (p = {p_value:.3g})"
            if shown
            else f"; that it exceeds the required {required:g} is NOT demonstrated (p = {p_value:.3g} ≥ {1 - cl:g})"
        )
    return SuccessBound(
        ps=ps, upper=upper, successes=m, trials=n, confidence=cl, required=required, p_value=p_value, decision=claim
    )
