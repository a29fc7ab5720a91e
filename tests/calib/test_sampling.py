"""Samplers and diagnostics on known targets; the fast sampler against the paper's reference."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.measure.dataset import from_arrays
from calib.fit.offsets import FitOptions, fit_offsets
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.fit.sampling import effective_sample_size, independence_mh, paper_metropolis, split_rhat
from calib.robot.transforms import apply, pose_to_matrix

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")


def gaussian(mean: np.ndarray, cov: np.ndarray):
    prec = np.linalg.inv(cov)

    def log_density(x: np.ndarray) -> np.ndarray:
        d = np.asarray(x) - mean
        return -0.5 * np.einsum("...i,ij,...j->...", d, prec, d)

    return log_density


def test_independence_sampler_reproduces_a_correlated_gaussian_even_from_a_wrong_proposal():
    mean = np.array([1.0, -2.0, 0.5])
    cov = np.array([[1.0, 0.6, 0.0], [0.6, 2.0, -0.3], [0.0, -0.3, 0.5]])
    # Proposal centred off the mode with the wrong scale: the MH correction must fix it.
    ch = independence_mh(gaussian(mean, cov), mean + 0.3, cov * 0.7, n_chains=4, n_draws=4000, seed=1)
    flat = ch.flat
    np.testing.assert_allclose(flat.mean(axis=0), mean, atol=0.08)
    np.testing.assert_allclose(np.cov(flat.T), cov, atol=0.12)
    assert ch.samples.shape == (4, 4000, 3)
    assert np.all((ch.acceptance > 0.2) & (ch.acceptance < 1.0))
    assert split_rhat(ch.samples).max() < 1.02


def test_paper_metropolis_reproduces_a_gaussian_in_the_papers_units():
    # Internal unit rad, the paper's proposal ±0.0125 acts in degrees.
    sd_rad = math.radians(0.02)
    log_density = gaussian(np.array([math.radians(0.1)]), np.array([[sd_rad**2]]))
    ch = paper_metropolis(log_density, np.zeros(1), unit_scale=np.array([180 / math.pi]), n_samples=60_000, burn_in=5_000, seed=2)
    draws = np.degrees(ch.flat[:, 0])
    ess = effective_sample_size(ch.samples)[0]
    assert ch.samples.shape == (1, 55_000, 1)
    assert abs(draws.mean() - 0.1) < 4 * 0.02 / math.sqrt(ess)
    assert abs(draws.std() - 0.02) < 0.15 * 0.02
    # Too small a step for the target: strongly autocorrelated, far fewer effective draws.
    assert ess < 55_000 / 5


def test_paper_metropolis_rejects_a_bad_burn_in_and_a_dead_start():
    with pytest.raises(ValueError, match="burn_in"):
        paper_metropolis(lambda x: np.array(0.0), np.zeros(1), unit_scale=np.ones(1), n_samples=10, burn_in=10)
    with pytest.raises(ValueError, match="zero posterior density"):
        paper_metropolis(lambda x: np.array(-np.inf), np.zeros(1), unit_scale=np.ones(1), n_samples=10, burn_in=0)


def test_split_rhat_flags_chains_that_disagree():
    rng = np.random.default_rng(3)
    same = rng.normal(size=(4, 1000, 2))
    assert np.all(np.abs(split_rhat(same) - 1.0) < 0.01)
    shifted = same.copy()
    shifted[0] += 1.0
    assert split_rhat(shifted)[0] > 1.1
    drifting = same + np.linspace(0, 3, 1000)[None, :, None]  # each chain trends: halves disagree
    assert np.all(split_rhat(drifting) > 1.1)
    with pytest.raises(ValueError, match="at least 4 draws"):
        split_rhat(same[:, :3])


def test_effective_sample_size_of_iid_and_ar1_draws():
    rng = np.random.default_rng(4)
    iid = rng.normal(size=(4, 5000, 1))
    assert 0.85 * 20_000 < effective_sample_size(iid)[0] < 1.15 * 20_000
    rho = 0.8
    x = np.zeros((4, 5000))
    e = rng.normal(size=(4, 5000))
    for t in range(1, 5000):
        x[:, t] = rho * x[:, t - 1] + e[:, t]
    expected = 20_000 * (1 - rho) / (1 + rho)  # AR(1) integrated autocorrelation
    assert 0.75 * expected < effective_sample_size(x[..., None])[0] < 1.25 * expected


@pytest.mark.slow  # a statistical study: two samplers' posteriors compared
def test_fast_method_agrees_with_the_papers_sampler():
    """A small problem the reference can run long enough: two offsets and σ, registration known."""
    rng = np.random.default_rng(7)
    chain = Chain(IIWA)
    b2s = pose_to_matrix(np.array([2000.0, 0.0, -400.0]), np.radians([180.0, 0.0, 0.0]))
    q = rng.uniform(IIWA.lower_limits_rad * 0.8, IIWA.upper_limits_rad * 0.8, size=(60, 7))
    truth = np.radians([0, -0.19, 0.14, 0, 0, 0, 0])
    pos = chain.marker_positions(q, chain.with_offsets(truth))[:, 0]
    xyz = apply(b2s, pos) + rng.normal(0.0, 0.6, pos.shape)
    ds = from_arrays(q, xyz, marker="smr")
    # The paper's model on both sides (no link-parameter priors), so both sample one posterior.
    common = dict(joints=(2, 3), registration={"sensor": b2s}, fix_registration=True, seed=5, link_tolerance=None,
                  tool_prior_mm=0)
    fast = fit_offsets(IIWA, ds, FitOptions(method="fast", n_draws=2000, **common))
    ref = fit_offsets(IIWA, ds, FitOptions(method="paper", paper_samples=40_000, paper_burn_in=8_000, **common))
    f_draws = np.concatenate([np.degrees(fast.offset_samples_rad[:, 1:3]), np.exp(fast.chains.flat[:, -1:])], 1)
    r_draws = np.concatenate([np.degrees(ref.offset_samples_rad[:, 1:3]), np.exp(ref.chains.flat[:, -1:])], 1)
    ess_f = effective_sample_size(fast.chains.samples)
    ess_r = effective_sample_size(ref.chains.samples)
    assert ess_r.min() > 100, f"the reference chain is too short: ESS {ess_r}"
    se = np.sqrt(f_draws.var(axis=0) / ess_f + r_draws.var(axis=0) / ess_r)  # Monte-Carlo error of the difference
    diff = f_draws.mean(axis=0) - r_draws.mean(axis=0)
    assert np.all(np.abs(diff) < 4 * se), f"means differ: {diff} vs MC error {se}"
    ratio = f_draws.std(axis=0) / r_draws.std(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.2), f"std ratio fast/paper {ratio}"
    # Both recover the truth.
    assert np.all(np.abs(f_draws.mean(axis=0)[:2] - np.degrees(truth[1:3])) < 4 * f_draws.std(axis=0)[:2])
