"""Registration statistics against hand-computed values and the seed's published numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.fit.regstats import (
    brown_forsythe_levene,
    compare_registrations,
    correlation,
    ks_two_sample,
    mean_difference_test,
    spatial_correlation,
    success_probability_bound,
)

# ---------------------------------------------------------------------------- spatial correlation


def test_spatial_correlation_hand_example() -> None:
    # Distances 1, 2, 3, 4 (points on the x axis), errors 1, 3, 2, 4. Deviations from the means
    # (2.5, 2.5): d = (−1.5, −0.5, 0.5, 1.5), e = (−1.5, 0.5, −0.5, 1.5); Σde = 4, Σd² = Σe² = 5,
    # r = 4/5 = 0.8. With n − 2 = 2 dof, t² = 2r²/(1 − r²) and the two-sided p of Student's t(2)
    # is 1 − |t|/√(t² + 2) = 1 − |r| = 0.2.
    pts = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, -3.0], [4.0, 0, 0]])
    res = spatial_correlation(np.array([1.0, 3.0, 2.0, 4.0]), pts)
    assert res.r == pytest.approx(0.8, abs=1e-12)
    assert res.p_value == pytest.approx(0.2, abs=1e-12)
    assert res.n == 4 and not res.significant
    assert "no significant correlation" in res.decision


def test_spatial_correlation_measures_distance_from_the_given_origin() -> None:
    origin = np.array([100.0, -50.0, 20.0])
    pts = origin + np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, -3.0], [4.0, 0, 0]])
    errs = np.array([1.0, 3.0, 2.0, 4.0])
    assert spatial_correlation(errs, pts, origin_mm=origin).r == pytest.approx(0.8, abs=1e-12)
    assert spatial_correlation(errs, pts).r != pytest.approx(0.8, abs=1e-3)


def test_spatial_correlation_detects_error_growing_with_distance() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-500, 500, (60, 3))
    dist = np.linalg.norm(pts, axis=1)
    growing = 0.001 * dist + rng.normal(0, 0.05, 60)
    flat = np.abs(rng.normal(0.3, 0.05, 60))
    yes = spatial_correlation(growing, pts)
    no = spatial_correlation(flat, pts)
    assert yes.significant and yes.r > 0.8 and "are correlated" in yes.decision
    assert not no.significant and abs(no.r) < 0.3


def test_correlation_reproduces_the_seeds_table_iii_within_its_rounding() -> None:
    # Sec. V: max(e) vs PS over the seven registrations of Table III, reported r = −0.805,
    # p = 0.029 (significant); mean e vs PS r = −0.740, p = 0.057 (not). From the 3-decimal
    # table values r comes out within 0.015 of the reported ones, with the same decisions.
    mean_e = [0.699, 1.006, 0.435, 0.594, 0.383, 0.410, 0.422]
    max_e = [1.493, 1.911, 0.987, 1.271, 0.851, 0.813, 0.758]
    ps = [0.427, 0.590, 0.817, 0.889, 0.897, 0.982, 0.982]
    mx = correlation(max_e, ps, what="max error and PS")
    mn = correlation(mean_e, ps)
    assert mx.r == pytest.approx(-0.805, abs=0.015) and mx.significant
    assert mn.r == pytest.approx(-0.740, abs=0.015) and not mn.significant
    assert mx.p_value == pytest.approx(0.029, abs=0.006) and mn.p_value == pytest.approx(0.057, abs=0.006)


# ------------------------------------------------------------------------------------------- KS


def test_ks_hand_example_exact_p_value() -> None:
    # a = (1, 2, 3) and b = (4, 5, 6) are fully separated: D = 1. Under H0 every one of the
    # C(6, 3) = 20 splits is equally likely and exactly 2 (all-low or all-high) reach D = 1,
    # so the exact two-sided p is 2/20 = 0.1.
    res = ks_two_sample([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    assert res.statistic == 1.0
    assert res.p_value == pytest.approx(0.1, abs=1e-12)
    assert not res.significant


def test_ks_separates_different_distributions() -> None:
    rng = np.random.default_rng(1)
    a, b = np.abs(rng.normal(0, 1.0, 80)), np.abs(rng.normal(0, 0.3, 80))
    assert ks_two_sample(a, b).significant
    assert not ks_two_sample(a[:40], a[40:]).significant


# --------------------------------------------------------------------------- Brown–Forsythe Levene


def test_brown_forsythe_hand_table() -> None:
    # a = (1, 2, 4, 7), median 3, |dev| = (2, 1, 1, 4), mean 2, SS within = 0 + 1 + 1 + 4 = 6
    # b = (3, 4, 5, 6), median 4.5, |dev| = (1.5, 0.5, 0.5, 1.5), mean 1, SS within = 4·0.25 = 1
    # grand mean 1.5, SS between = 4·0.5² + 4·0.5² = 2
    # W = (N − k)/(k − 1) · SSB/SSW = 6/1 · 2/7 = 12/7, df (1, 6).
    # F(1, 6) is the square of t(6), so p = P(|T₆| > √(12/7)), from t's closed form below.
    res = brown_forsythe_levene([1.0, 2.0, 4.0, 7.0], [3.0, 4.0, 5.0, 6.0])
    assert res.statistic == pytest.approx(12.0 / 7.0, rel=1e-12)
    assert res.df == (1, 6)
    x = math.sqrt(12.0 / 7.0)
    z = x / math.sqrt(x * x + 6.0)
    # Student t, even ν = 6: P(|T| < x) = z·(1 + u/2 + 3u²/8), z = x/√(x² + ν), u = 1 − z²
    c = 1.0 - z * z
    p = 1.0 - z * (1.0 + 0.5 * c + 0.375 * c * c)
    assert res.p_value == pytest.approx(p, rel=1e-9)
    assert not res.significant


def test_brown_forsythe_detects_a_variance_difference_and_takes_k_groups() -> None:
    rng = np.random.default_rng(2)
    wide, narrow = rng.normal(0, 1.0, 50), rng.normal(0, 0.2, 50)
    assert brown_forsythe_levene(wide, narrow).significant
    three = brown_forsythe_levene(narrow[:20], narrow[20:35], narrow[35:])
    assert three.df == (2, 47) and not three.significant


# -------------------------------------------------------------------------------------- t-tests


def test_student_t_hand_example() -> None:
    # a = 1..5, b = 3..7: means 3 and 5, both variances 2.5, pooled s² = 2.5,
    # SE = √(2.5·(1/5 + 1/5)) = 1, t = −2, df = 8. Equal spreads → Levene accepts → Student.
    res = mean_difference_test([1.0, 2, 3, 4, 5], [3.0, 4, 5, 6, 7])
    assert not res.welch and res.levene_p_value == pytest.approx(1.0)
    assert res.statistic == pytest.approx(-2.0, rel=1e-12)
    assert res.df == 8.0
    # t(8) two-sided p at |t| = 2, closed form for even ν: with u = ν/(ν + t²) = 2/3,
    # P(|T| > t) = 1 − z(1 + u/2 + 3u²/8 + 5u³/16), z = t/√(ν + t²) = 1/√3
    z, u = 1.0 / math.sqrt(3.0), 2.0 / 3.0
    assert res.p_value == pytest.approx(1.0 - z * (1 + u / 2 + 3 * u**2 / 8 + 5 * u**3 / 16), rel=1e-9)


def test_welch_t_hand_example() -> None:
    # a = 1..5 (var 2.5), b = 10..50 step 10 (var 250): SE² = 2.5/5 + 250/5 = 50.5,
    # t = (3 − 30)/√50.5, Welch–Satterthwaite df = 50.5² / (0.5²/4 + 50²/4) = 2550.25/625.0625.
    res = mean_difference_test([1.0, 2, 3, 4, 5], [10.0, 20, 30, 40, 50], equal_var=False)
    assert res.welch and res.levene_p_value is None
    assert res.statistic == pytest.approx(-27.0 / math.sqrt(50.5), rel=1e-12)
    assert res.df == pytest.approx(2550.25 / 625.0625, rel=1e-12)
    assert res.significant and "Welch" in res.decision


def test_levene_rejection_switches_to_welch() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.normal(1.0, 1.0, 40), rng.normal(1.0, 0.1, 40)
    res = mean_difference_test(a, b)
    assert res.levene_p_value is not None and res.levene_p_value < 0.05
    assert res.welch
    assert res.df < 78  # Welch–Satterthwaite, not the pooled n_a + n_b − 2


def test_compare_registrations_runs_the_table_ii_sequence() -> None:
    rng = np.random.default_rng(4)
    three_point = np.abs(rng.normal(0.0, 1.0, 60)) + 0.3
    combinatorial = np.abs(rng.normal(0.0, 0.3, 60)) + 0.1
    cmp = compare_registrations(three_point, combinatorial)
    assert cmp.ks.significant and cmp.levene.significant and cmp.ttest.significant
    assert cmp.ttest.welch  # variances differ → Welch
    assert cmp.mean_mm[0] == pytest.approx(three_point.mean())
    assert cmp.variance_mm2[1] == pytest.approx(np.var(combinatorial, ddof=1))
    assert cmp.decision.count("\n") == 2 and "variances differ" in cmp.decision


# -------------------------------------------------------------------------- binomial bound (18)


def binom_cdf(k: int, n: int, p: float) -> float:
    """Σ_{i=0}^{k} C(n, i) pⁱ (1 − p)^(n−i), written out as eq. (18)."""
    return sum(math.comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(k + 1))


def test_binomial_bound_reproduces_table_iii_all_successes() -> None:
    # 16 sites × 2 orientations × 5 repetitions = 160 insertions, all successful: Table III
    # gives PS = 0.982. With m = n eq. (18) reads 1 − PSⁿ ≤ 0.95, so PS = 0.05^(1/160).
    exact = success_probability_bound(160, 160, confidence=0.95)
    assert exact.ps == pytest.approx(0.05 ** (1 / 160), rel=1e-12)
    assert success_probability_bound(160, 160, precision=0.001).ps == pytest.approx(0.982, abs=1e-12)
    assert exact.upper == 1.0
    assert "at least 0.9815" in exact.decision


@pytest.mark.parametrize("m,n", [(1, 10), (7, 10), (50, 100), (68, 160)])
def test_binomial_bound_is_the_smallest_p_satisfying_eq_18(m: int, n: int) -> None:
    res = success_probability_bound(m, n, confidence=0.95)
    assert binom_cdf(m - 1, n, res.ps) == pytest.approx(0.95, abs=1e-9)
    grid = success_probability_bound(m, n, confidence=0.95, precision=0.001)
    assert binom_cdf(m - 1, n, grid.ps) <= 0.95
    assert binom_cdf(m - 1, n, grid.ps - 0.001) > 0.95
    # upper one-sided Clopper–Pearson bound: P(X ≤ m; upper) = 1 − CL
    assert binom_cdf(m, n, res.upper) == pytest.approx(0.05, abs=1e-9)
    assert res.ps < m / n < res.upper


def test_binomial_bound_with_no_success_and_a_required_probability() -> None:
    none = success_probability_bound(0, 20)
    assert none.ps == 0.0
    assert none.upper == pytest.approx(1 - 0.05 ** (1 / 20), rel=1e-12)  # (1 − p)²⁰ = 0.05
    shown = success_probability_bound(50, 100, required=0.4)
    # P(X ≥ 50 | n = 100, p = 0.4), summed by hand
    assert shown.p_value == pytest.approx(1 - binom_cdf(49, 100, 0.4), rel=1e-9)
    assert shown.ps > 0.4 and shown.p_value < 0.05 and "is demonstrated" in shown.decision
    not_shown = success_probability_bound(50, 100, required=0.45)
    assert not_shown.ps < 0.45 and not_shown.p_value > 0.05 and "NOT demonstrated" in not_shown.decision


# --------------------------------------------------------------------------------- bad input


def test_degenerate_samples_are_refused_with_reasons() -> None:
    with pytest.raises(ValueError, match="constant"):
        correlation([1.0, 1.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="at least 3 values; got 2"):
        correlation([1.0, 2.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="same length"):
        correlation([1.0, 2.0, 3.0], [1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ValueError, match=r"non-finite.*\[1\]"):
        ks_two_sample([1.0, np.nan, 2.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="1-D"):
        ks_two_sample(np.ones((2, 2)), [1.0, 2.0])
    with pytest.raises(ValueError, match="undefined"):
        brown_forsythe_levene([1.0, 1.0], [2.0, 2.0])
    with pytest.raises(ValueError, match="at least 2 samples"):
        brown_forsythe_levene([1.0, 2.0])
    with pytest.raises(ValueError, match="both samples are constant"):
        mean_difference_test([1.0, 1.0], [2.0, 2.0])
    with pytest.raises(ValueError, match="alpha"):
        ks_two_sample([1.0, 2.0], [3.0, 4.0], alpha=1.5)
    with pytest.raises(ValueError, match=r"points_sensor must have shape \(3, 3\)"):
        spatial_correlation([1.0, 2.0, 3.0], np.zeros((4, 3)))
    with pytest.raises(ValueError, match="successes"):
        success_probability_bound(11, 10)
    with pytest.raises(ValueError, match="trials"):
        success_probability_bound(0, 0)
    with pytest.raises(ValueError, match="confidence"):
        success_probability_bound(5, 10, confidence=95)
    with pytest.raises(ValueError, match="precision"):
        success_probability_bound(5, 10, precision=0.0)
