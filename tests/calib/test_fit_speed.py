"""The default fit's speed-ups keep its answers (issue 33): the adapted importance stages recover a
posterior the Laplace proposal misses, the early stop of the Laplace stage only where its weights
are clearly good, folds started from the fit of all the data reach the same mode, and the fit says
what it is doing with the time left (``calib.fit.progress``)."""

from __future__ import annotations

import numpy as np

from calib.fit.laplace_sampling import CHUNK, STAGE_MIN_DRAWS, laplace_importance
from calib.fit.model_choice import CV_TOL, options_for, parse_candidate
from calib.fit.offsets import FitOptions, fit_mode
from calib.fit.progress import Progress
from tests.calib.test_model_choice import cell


def _skewed_target(x: np.ndarray) -> np.ndarray:
    """A 3-D target whose mean is off its mode and whose covariance the Laplace proposal gets
    wrong: x0 ~ Gamma(8, 1) shifted to mode 0 (skewed), x1 | x0 ~ N(0.5 x0, 1), x2 ~ N(0, 2²)."""
    a = x[..., 0] + 7.0  # Gamma(8) has its mode at 7
    with np.errstate(invalid="ignore", divide="ignore"):
        lp0 = np.where(a > 0, 7.0 * np.log(np.maximum(a, 1e-300)) - a, -np.inf)
    return lp0 - 0.5 * (x[..., 1] - 0.5 * x[..., 0]) ** 2 - 0.5 * (x[..., 2] / 2.0) ** 2


def test_adapted_importance_stages_recover_a_skewed_correlated_posterior_the_laplace_proposal_misses():
    laplace = np.diag([1.0, 1.0, 0.25])  # too narrow in x2 (sd 0.5 for 2), blind to the x0–x1 correlation
    failed, diag0 = laplace_importance(_skewed_target, np.zeros(3), laplace, seed=3, adapt=0, df=None)
    assert failed is None and diag0["k_hat"] >= 0.7
    chains, diag = laplace_importance(_skewed_target, np.zeros(3), laplace, seed=3, df=None)
    assert chains is not None and diag["stages"] > 1 and diag["k_hat"] < 0.7, diag["k_hat_stages"]
    x = chains.flat
    # Exact moments: x0 = Gamma(8) − 7 has mean 1, variance 8; x1: mean 0.5, var 0.25·8 + 1; x2: 0, 4.
    np.testing.assert_allclose(x.mean(axis=0), [1.0, 0.5, 0.0], atol=0.15)
    np.testing.assert_allclose(x.var(axis=0), [8.0, 3.0, 4.0], rtol=0.12)


def test_the_laplace_stage_stops_early_only_where_its_weights_are_clearly_good():
    def gauss(x):
        return -0.5 * np.sum(x * x, axis=-1)

    chains, diag = laplace_importance(gauss, np.zeros(4), np.eye(4), seed=0)
    assert chains is not None and diag["n_proposals"] == CHUNK and diag["stages"] == 1
    # A Gaussian proposal of variance 0.3 for N(0, 1): weights with a Pareto tail of k = 0.7 — judged
    # on a whole stage's draws (not one chunk), and refused.
    refused, narrow = laplace_importance(gauss, np.zeros(4), 0.3 * np.eye(4), seed=0, adapt=0, df=None)
    assert refused is None and narrow["n_proposals"] >= STAGE_MIN_DRAWS and narrow["k_hat"] >= 0.7


def test_folds_started_at_the_fit_of_all_the_data_reach_the_same_mode_as_from_nominal():
    model, _, cal = cell(2, link_mm=0.2, angle_deg=0.02, k=24)
    options = options_for(parse_candidate("offsets+tool+links", model), FitOptions(method="laplace"), (0.3, 0.03))
    everything = fit_mode(model, cal, options, tol=CV_TOL)
    train = cal.subset(cal.config != cal.config[0])
    cold = fit_mode(model, train, options, tol=1e-12)
    warm = fit_mode(model, train, options, tol=1e-12, start=everything)
    assert not np.allclose(warm.b2s0[cal.sensor[0]], cold.b2s0[cal.sensor[0]])  # a different start …
    n = model.n_joints
    np.testing.assert_allclose(warm.post.full_vector(warm.theta)[:n], cold.post.full_vector(cold.theta)[:n], atol=1e-9)
    held_out = cal.subset(cal.config == cal.config[0])
    np.testing.assert_allclose(warm.predict_residuals(held_out), cold.predict_residuals(held_out), atol=1e-6)


def test_progress_says_the_step_and_the_time_left_and_keeps_quiet_between_lines():
    now = [0.0]
    lines: list[tuple[str, float | None]] = []
    p = Progress(lambda text, eta: lines.append((text, eta)), clock=lambda: now[0], every_s=1.0)
    p.begin("cross-validation", 4)
    p.step("fold 1")  # first line of a stage: always, no estimate yet
    now[0] = 2.0
    p.step("fold 2")  # one of four done in 2 s: 6 s left
    now[0] = 2.5
    p.step("fold 3")  # within every_s of the last line: not shown
    now[0] = 6.0
    p.note("sampler", 0.75)
    assert lines == [("fold 1 [1/4]", None), ("fold 2 [2/4]", 6.0), ("sampler", 2.0)]


def test_cross_along_any_trailing_axis_is_numpys_cross():
    from calib.robot.transforms import cross

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 1, 3, 7)), rng.normal(size=(5, 4, 3, 1))
    np.testing.assert_allclose(cross(a, b, axis=-2), np.cross(a, b, axis=-2), rtol=0, atol=1e-14)
    np.testing.assert_allclose(cross(a[0, 0, :, 0], b[:, :, :, 0]), np.cross(a[0, 0, :, 0], b[:, :, :, 0]), atol=1e-14)


def test_the_pareto_fit_recovers_the_shape_of_generalized_pareto_draws():
    """Draws by the inverse CDF, x = σ((1 − u)^(−k) − 1)/k: the fitted shape within the spread of
    an estimate from 2 000 draws (the weak prior pulls it towards 0.5 by 10 pseudo-draws)."""
    from calib.fit.psis import gpd_fit

    for k_true in (-0.2, 0.3, 0.8):
        ks = []
        for seed in range(3):
            u = np.random.default_rng(seed).random(2000)
            ks.append(gpd_fit(2.0 * np.expm1(-k_true * np.log1p(-u)) / k_true)[0])
        assert abs(np.mean(ks) - k_true) < 0.06, (k_true, ks)
