"""Accuracy metrics (eqs. 17, 18, Sec. V-C) on small examples computed by hand."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.measure.dataset import from_arrays
from calib.robot.kinematics import Chain
from calib.fit.metrics import (
    absolute_errors,
    accuracy_metrics,
    before_after,
    predicted_base,
    random_configurations,
    relative_errors,
    summarize,
    theoretical_errors,
)
from calib.robot.model import load_robot_model
from calib.robot.transforms import apply, pose_to_matrix

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
CHAIN = Chain(IIWA)


def points_dataset(xyz: np.ndarray, pose: list[str], sensor: list[str] | None = None):
    k = len(xyz)
    return from_arrays(np.zeros((k, 7)), xyz, marker="smr", pose=np.array(pose), sensor=np.array(sensor or ["s"] * k))


def test_summarize_mean_percentiles_max():
    s = summarize(np.array([4.0, 1.0, 3.0, 2.0]))
    # numpy's linear percentile: position 0.025·3 = 0.075 → 1.075; 0.975·3 = 2.925 → 3.925.
    assert (s.mean, s.p2_5, s.p97_5, s.max, s.count) == pytest.approx((2.5, 1.075, 3.925, 4.0, 4))
    empty = summarize(np.zeros(0))
    assert empty.count == 0 and math.isnan(empty.mean)
    assert set(s.to_dict()) == {"mean", "p2_5", "p97_5", "max", "count"}


def test_relative_error_eq17_by_hand():
    measured = np.array([[0, 0, 0], [3, 4, 0], [0, 0, 10], [50, 50, 50], [7, 7, 7], [1, 2, 3]], dtype=float)
    robot = np.array([[1, 1, 1], [1, 1, 6], [1, 1, 13], [0, 0, 0], [9, 9, 9], [0, 0, 0]], dtype=float)
    # rows 0-2: pose "a" (three pairs); row 3: pose "b" alone (no pair); row 4: pose "a" but
    # another sensor (no partner); row 5: no pose group.
    ds = points_dataset(measured, ["a", "a", "a", "b", "a", ""], ["s", "s", "s", "s", "t", "s"])
    d = relative_errors(ds, robot)
    # measured distances 5, 10, √125; robot distances 5, 12, 7.
    np.testing.assert_allclose(d, [0.0, 2.0, math.sqrt(125) - 7.0])


def test_relative_error_is_frame_independent():
    rng = np.random.default_rng(0)
    robot = rng.uniform(-500, 500, size=(8, 3))
    t = pose_to_matrix(np.array([1000.0, -20.0, 300.0]), np.array([0.3, -0.2, 1.1]))
    ds = points_dataset(apply(t, robot), ["p"] * 4 + ["q"] * 4)
    d = relative_errors(ds, robot)
    assert d.shape == (12,) and d.max() < 1e-9


def test_absolute_error_eq18_by_hand():
    # Square corners scaled by 1 % about their centroid: no rigid motion can absorb a scale,
    # and by symmetry the best rigid fit is the identity, so each error is 0.01·|p| = 1.41421 mm.
    robot = np.array([[100, 100, 0], [-100, 100, 0], [-100, -100, 0], [100, -100, 0]], dtype=float)
    ds = points_dataset(robot * 1.01, [""] * 4)
    np.testing.assert_allclose(absolute_errors(ds, robot), 0.01 * math.sqrt(2) * 100, rtol=1e-9)
    # A rigid motion alone leaves no error; two sensors are registered separately.
    t1 = pose_to_matrix(np.array([10.0, 20.0, 30.0]), np.array([0.1, 0.2, 0.3]))
    t2 = pose_to_matrix(np.array([-500.0, 0.0, 0.0]), np.array([2.0, 0.0, -0.4]))
    both = points_dataset(np.concatenate([apply(t1, robot), apply(t2, robot)]), [""] * 8, ["s"] * 4 + ["t"] * 4)
    assert absolute_errors(both, np.concatenate([robot, robot])).max() < 1e-9


def test_theoretical_error_of_a_first_axis_offset_is_a_chord():
    rng = np.random.default_rng(1)
    q = random_configurations(CHAIN, 30, rng)
    draws = np.zeros((40, 7))
    draws[:, 0] = np.radians(rng.uniform(-1, 1, 40))
    e = theoretical_errors(CHAIN, q, np.zeros(7), draws, None, rng=np.random.default_rng(2), n_draws=40).reshape(40, 30)
    _, tcp = CHAIN.flange_pose(q)
    r = np.linalg.norm(tcp[:, :2], axis=1)  # distance of the flange from the base z axis
    pick = np.random.default_rng(2).choice(40, size=40, replace=False)  # the function's subset
    chord = 2 * r[None, :] * np.abs(np.sin(draws[pick, 0][:, None] / 2))
    np.testing.assert_allclose(e, chord, atol=1e-9)


def test_theoretical_error_of_sigma_alone_follows_the_chi_distribution():
    q = random_configurations(CHAIN, 50, np.random.default_rng(3))
    e = theoretical_errors(CHAIN, q, np.zeros(7), np.zeros((2000, 7)), 0.5, rng=np.random.default_rng(4))
    assert e.size == 100_000
    # |N(0, σ² I₃)| has mean 2σ√(2/π) and mean square 3σ².
    assert e.mean() == pytest.approx(0.5 * 2 * math.sqrt(2 / math.pi), rel=0.01)
    assert np.mean(e**2) == pytest.approx(3 * 0.25, rel=0.02)


def test_random_configurations_span_the_joint_limits():
    q = random_configurations(CHAIN, 4000, np.random.default_rng(5))
    assert q.shape == (4000, 7)
    assert IIWA.within_limits(q).all()
    mid = (IIWA.lower_limits_rad + IIWA.upper_limits_rad) / 2
    span = IIWA.upper_limits_rad - IIWA.lower_limits_rad
    np.testing.assert_allclose(q.mean(axis=0), mid, atol=0.05 * span.max())
    np.testing.assert_allclose(q.max(axis=0) - q.min(axis=0), span, rtol=0.01)


def _exact_dataset(offsets_rad: np.ndarray, k: int = 24):
    rng = np.random.default_rng(6)
    q = random_configurations(CHAIN, k, rng) * 0.7
    b2s = pose_to_matrix(np.array([1500.0, 0.0, 0.0]), np.radians([180.0, 0.0, 0.0]))
    pos = CHAIN.marker_positions(q, CHAIN.with_offsets(offsets_rad))[:, 0]
    return from_arrays(q, apply(b2s, pos), marker="smr", pose=np.repeat(np.arange(k // 4), 4).astype(str))


def test_predicted_base_picks_each_rows_marker():
    ds = _exact_dataset(np.zeros(7), k=4)
    ds2 = from_arrays(ds.q_rad, ds.xyz_mm, marker=np.array(["smr", "sir", "sir", "smr"]))
    p = predicted_base(CHAIN, ds2, np.zeros(7))
    full = CHAIN.marker_positions(ds.q_rad)
    np.testing.assert_allclose(p, full[np.arange(4), [0, 1, 1, 0]])


def test_before_after_and_all_metrics_on_noise_free_data():
    truth = np.radians([0.0, -0.2, 0.15, 0.1, 0.4, -0.1, 0.9])
    cal, val = _exact_dataset(truth), _exact_dataset(truth, k=12)
    ba = before_after(CHAIN, cal, truth)
    assert ba["absolute"]["after"]["max"] < 1e-6 and ba["relative"]["after"]["max"] < 1e-6
    assert ba["absolute"]["before"]["mean"] > 0.5 and ba["relative"]["before"]["mean"] > 0.5
    draws = truth + np.radians(0.01) * np.random.default_rng(7).standard_normal((500, 7))
    m = accuracy_metrics(CHAIN, cal, truth, draws, 0.3, validation=val, n_random=50, n_draws=200, mc_se_mm=None, seed=1)
    expected = {
        "relative", "absolute", "theoretical_measured", "theoretical_measured_offsets_only", "theoretical_workspace",
        "theoretical_workspace_offsets_only", "validation_relative", "validation_absolute", "validation_absolute_reregistered", "offsets_share",
        "settings", "notes",
    }
    assert set(m) == expected
    assert m["validation_absolute"]["after"]["max"] < 1e-6
    # Re-registered on the validation points themselves: eq. 18 on them (named so; the honest
    # figure uses the calibration registration, test_tool_unknowns).
    assert m["validation_absolute_reregistered"]["before"]["mean"] == pytest.approx(
        before_after(CHAIN, val, truth)["absolute"]["before"]["mean"])
    assert m["validation_absolute"]["before"]["mean"] > m["validation_absolute_reregistered"]["before"]["mean"]
    # Offsets alone after the fit: 0.01° spread ≈ 0.01° × ~1 m ≈ 0.1–0.3 mm; before: the whole offset.
    after_only = m["theoretical_workspace_offsets_only"]["after"]["mean"]
    assert 0.05 < after_only < 0.5
    assert m["theoretical_workspace_offsets_only"]["before"]["mean"] > 5 * after_only
    # With σ = 0.3 mm added the error grows and the offsets explain only a share of it.
    assert m["theoretical_workspace"]["after"]["mean"] > after_only
    assert m["offsets_share"]["after"] == pytest.approx(after_only / m["theoretical_workspace"]["after"]["mean"])
    assert m["offsets_share"]["before"] > 0.9 > m["offsets_share"]["after"]
    assert m["settings"]["n_random_configurations"] == 50 and m["settings"]["n_draws"] == 200
    assert m["settings"]["draws_measured"] == m["settings"]["draws_workspace"] == 200  # mc_se_mm=None: all of them
    for key in expected - {"offsets_share", "settings", "notes"}:
        for when in ("before", "after"):
            stated = {"mc_se"} if key.startswith("theoretical") else set()  # Monte-Carlo estimates carry their error
            assert set(m[key][when]) == {"mean", "p2_5", "p97_5", "max", "count"} | stated


def _theoretical(seed: int, **kw) -> dict:
    """Theoretical metrics with a fresh posterior sample per seed (the draws are Monte-Carlo too)."""
    truth = np.radians([0.0, -0.2, 0.15, 0.1, 0.4, -0.1, 0.9])
    draws = truth + np.radians(0.01) * np.random.default_rng(100 + seed).standard_normal((2000, 7))
    return accuracy_metrics(CHAIN, _exact_dataset(truth), truth, draws, 0.3, n_random=40, seed=seed, **kw)


def test_theoretical_draws_stop_at_the_stated_precision_and_not_much_later():
    """At the measured configurations (a fixed set) the mean's error is the draws' alone: the draws
    stop once every mean's error is within the target, or at the cap; and not far past the point
    where the spread says the target is met."""
    full = _theoretical(0, mc_se_mm=None, n_draws=1500)
    assert full["settings"]["draws_measured"] == full["settings"]["draws_workspace"] == 1500
    used = {}
    for target in (0.01, 0.001):
        m = _theoretical(0, mc_se_mm=target)
        d = used[target] = m["settings"]["draws_measured"]
        assert m["settings"]["mc_se_target_mm"] == target and 100 <= d <= 1000
        se = [m[key][when]["mc_se"] for key in ("theoretical_measured", "theoretical_measured_offsets_only")
              for when in ("before", "after")]
        if d < 1000:
            assert max(se) <= target * 1.0001
        if d > 100:  # grown past the minimum: to about what the spread asks for
            assert d <= 1.3 * d * (max(se) / target) ** 2 + 1
        for key in ("theoretical_measured", "theoretical_workspace"):
            for when in ("before", "after"):
                assert m[key][when]["count"] == m["settings"][f"draws_{key.split('_')[1]}"] * m["settings"][
                    f"n_{'random' if 'workspace' in key else 'measured'}_configurations"]
                assert m[key][when]["mean"] == pytest.approx(full[key][when]["mean"],
                                                             abs=4 * math.hypot(m[key][when]["mc_se"], full[key][when]["mc_se"]))
    assert used[0.01] < used[0.001]
    truth = np.radians([0.0, -0.2, 0.15, 0.1, 0.4, -0.1, 0.9])
    one = accuracy_metrics(CHAIN, _exact_dataset(truth), truth, truth[None], 0.3, n_random=10)  # a single posterior draw
    assert one["settings"]["draws_measured"] == 1 and one["theoretical_workspace"]["after"]["mc_se"] > 0


def test_the_stated_standard_error_is_the_spread_over_seeds():
    """The mean's stated Monte-Carlo error against its actual spread over 24 seeds (a new
    posterior sample, new ε, new random configurations): the two agree within the sampling error
    of a std."""
    runs = [_theoretical(seed, mc_se_mm=0.002) for seed in range(24)]
    for key in ("theoretical_measured", "theoretical_workspace", "theoretical_workspace_offsets_only"):
        for when in ("before", "after"):
            means = np.array([r[key][when]["mean"] for r in runs])
            stated = np.mean([r[key][when]["mc_se"] for r in runs])
            assert 0.6 < means.std(ddof=1) / stated < 1.6, (key, when, means.std(ddof=1), stated)
