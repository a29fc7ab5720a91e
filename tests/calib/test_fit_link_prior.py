"""Link errors bias a zero-offset-only fit beyond its intervals; marginalising the link
parameters under a tolerance prior (the fast method's default) restores honest intervals."""

import numpy as np
import pytest

from calib.fit.offsets import FitOptions, fit_offsets
from tests.calib.test_fit import IIWA, simulate


def coverage(link_mm: float, link_tolerance, reps: int = 12) -> tuple[float, float]:
    hits, z = [], []
    for rep in range(reps):
        ds, truth, wrong = simulate(IIWA, seed=500 + rep, k=80, link_mm=link_mm, unmodelled_mm=0.05, jitter_deg=0.0)
        res = fit_offsets(IIWA, ds, FitOptions(registration={"sensor": wrong}, seed=rep, n_draws=500, link_tolerance=link_tolerance))
        ok = res.identifiable()
        lo, hi = res.offsets_ci95_rad[ok].T
        hits += list((truth[ok] >= lo) & (truth[ok] <= hi))
        z += list((res.offsets_rad[ok] - truth[ok]) / res.offsets_std_rad[ok])
    return float(np.mean(hits)), float(np.sqrt(np.mean(np.square(z))))


@pytest.mark.parametrize("link_mm", [0.1, 0.3])  # the prior says 0.2 mm: wider, then narrower than the truth
def test_link_prior_restores_interval_coverage_under_link_errors(link_mm):
    plain, plain_z = coverage(link_mm, None)
    marginal, marginal_z = coverage(link_mm, (0.2, 0.02))
    assert marginal >= 0.88, f"coverage with the link prior {marginal:.2f} (rms z {marginal_z:.2f})"
    assert plain < 0.8 and plain_z > 2.0, f"the paper's model was expected to be overconfident here: {plain:.2f}, rms z {plain_z:.2f}"


def test_link_prior_is_reported_with_posterior_deviations():
    ds, _, wrong = simulate(IIWA, seed=77, k=60, link_mm=0.2)
    res = fit_offsets(IIWA, ds, FitOptions(registration={"sensor": wrong}, seed=1, n_draws=300))
    lp = res.diagnostics["link_prior"]
    assert (lp["length_mm"], lp["angle_deg"]) == (0.2, 0.02)
    assert {"A3.d", "A3.a", "A3.alpha"} <= set(lp["parameters"])
    assert all(v["std"] > 0 for v in lp["parameters"].values())
    paper = fit_offsets(IIWA, ds, FitOptions(method="paper", registration={"sensor": wrong}, paper_samples=2000, paper_burn_in=1000))
    assert paper.diagnostics["link_prior"] is None  # the paper's model has no link parameters


def test_linearised_link_terms_give_the_exact_default_posterior():
    """The default sampler predicts the link parameters' effect to first order about the mode;
    against the exact chain walk its offsets' means agree within Monte-Carlo error and their
    standard deviations within 5 %."""
    ds, _, wrong = simulate(IIWA, seed=91, k=80, link_mm=0.2)
    common = dict(registration={"sensor": wrong}, n_draws=4000)
    lin = fit_offsets(IIWA, ds, FitOptions(**common, seed=1))
    exact = fit_offsets(IIWA, ds, FitOptions(**common, seed=2, linearise_links=False))
    ok = lin.identifiable()
    ess = np.array(lin.diagnostics["ess"])[: int(ok.sum())]
    mc = np.hypot(lin.offsets_std_rad[ok], exact.offsets_std_rad[ok]) / np.sqrt(np.maximum(ess, 1))
    assert np.all(np.abs(lin.offsets_rad[ok] - exact.offsets_rad[ok]) < 4 * mc)
    ratio = lin.offsets_std_rad[ok] / exact.offsets_std_rad[ok]
    assert np.all((0.95 <= ratio) & (ratio <= 1.05)), ratio
