"""Registration methods recover known transforms; degenerate input is refused clearly."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from calib.fit.registration import (
    ClusteredRegistration,
    RegistrationResult,
    average_transforms,
    chordal_mean_rotation,
    correction_matrix,
    kmeans,
    refine_annealing,
    register_clustered,
    register_combinatorial,
    register_least_squares,
    register_three_points,
    three_point_frame,
    translation_errors,
    triple_registrations,
)
from calib.robot.transforms import apply, exp_so3, homogeneous, invert, log_so3, pose_to_matrix, rot_z

SIGMA_MM = 0.05  # per-axis measurement noise of the simulated sensor


def true_transform(rng: np.random.Generator) -> np.ndarray:
    """A random base2sensor: any rotation, a translation of about a metre."""
    w = rng.normal(size=3)
    w *= rng.uniform(0.2, 3.0) / np.linalg.norm(w)
    return homogeneous(exp_so3(w), rng.uniform(-1500.0, 1500.0, 3))


def scene(seed: int, n: int, sigma: float = SIGMA_MM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(base2sensor, p_base (n, 3), p_sensor (n, 3)): points in a ±400 mm box, isotropic noise."""
    rng = np.random.default_rng(seed)
    t = true_transform(rng)
    pb = rng.uniform(-400.0, 400.0, (n, 3)) + np.array([600.0, 0.0, 400.0])
    ps = apply(t, pb) + rng.normal(0.0, sigma, (n, 3))
    return t, pb, ps


def model_rms(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray) -> float:
    """RMS over points (mm) of where the estimate puts them versus where the truth does."""
    return float(np.sqrt(np.mean(np.sum((apply(estimate, points) - apply(truth, points)) ** 2, axis=1))))


def assert_rigid(t: np.ndarray) -> None:
    r = t[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(t[3], [0.0, 0.0, 0.0, 1.0])


# ------------------------------------------------------------------------------- the H(·) operator


def test_three_point_frame_follows_eqs_2_to_5() -> None:
    p = np.array([[10.0, 20.0, 30.0], [110.0, 20.0, 30.0], [10.0, 70.0, 30.0]])
    h = three_point_frame(p)
    assert_rigid(h)
    np.testing.assert_allclose(h[:3, 3], p[0])  # origin at p1
    np.testing.assert_allclose(h[:3, 0], [1.0, 0.0, 0.0], atol=1e-15)  # x̂ along p2 − p1
    np.testing.assert_allclose(h[:3, 1], [0.0, 0.0, 1.0], atol=1e-15)  # ŷ = x̂ × (p3 − p1), normalised
    np.testing.assert_allclose(h[:3, 2], [0.0, -1.0, 0.0], atol=1e-15)  # ẑ = x̂ × ŷ


@pytest.mark.parametrize("seed", range(5))
def test_three_points_recover_transform_exactly_without_noise(seed: int) -> None:
    t, pb, ps = scene(seed, 3, sigma=0.0)
    res = register_three_points(pb, ps)
    assert isinstance(res, RegistrationResult)
    assert res.method == "three_point" and res.n_triples == 1
    assert_rigid(res.base2sensor)
    np.testing.assert_allclose(res.base2sensor, t, atol=1e-9)
    assert res.rms_mm < 1e-9


def test_three_points_with_noise_stay_within_a_noise_derived_bound() -> None:
    # The first point is matched exactly, so its full noise (|ε| ≈ √3 σ) moves the origin;
    # the direction errors are ≈ σ/(300 mm) rad, moving points 400 mm away by ≈ 1.3 σ more.
    # 10 σ over a 2× wider box is a generous but noise-scaled bound.
    errs = []
    for seed in range(20):
        t, pb, ps = scene(100 + seed, 3)
        errs.append(model_rms(register_three_points(pb, ps).base2sensor, t, pb))
    assert np.median(errs) < 10 * SIGMA_MM
    assert max(errs) > 0.1 * SIGMA_MM  # noise really went in


# -------------------------------------------------------------------------------- least squares


@pytest.mark.parametrize("seed", range(5))
def test_least_squares_recovers_transform_within_chi_square_bound(seed: int) -> None:
    # With isotropic noise σ the fitted model moves the n points by a projection of the noise
    # onto the 6-dimensional tangent space: Σ|Δ|²/σ² ~ χ²(6). Bound it at the 99.9 % quantile.
    n = 30
    t, pb, ps = scene(seed, n)
    res = register_least_squares(pb, ps)
    assert_rigid(res.base2sensor)
    bound = SIGMA_MM * math.sqrt(stats.chi2.ppf(0.999, 6) / n)
    assert model_rms(res.base2sensor, t, pb) < bound
    # and it is the least-squares optimum: no worse on its own points than the truth
    assert res.rms_mm <= float(np.sqrt(np.mean(translation_errors(t, pb, ps) ** 2))) + 1e-12


def test_least_squares_never_returns_a_reflection() -> None:
    # Mirror-image data: the best orthogonal matrix would be a reflection; we must stay in SO(3).
    rng = np.random.default_rng(7)
    pb = rng.uniform(-100, 100, (10, 3))
    ps = pb * np.array([1.0, 1.0, -1.0])
    assert_rigid(register_least_squares(pb, ps).base2sensor)


def test_least_squares_weights_ignore_a_zero_weighted_outlier() -> None:
    t, pb, ps = scene(3, 12, sigma=0.0)
    ps = ps.copy()
    ps[5] += [50.0, -30.0, 20.0]
    w = np.ones(12)
    w[5] = 0.0
    np.testing.assert_allclose(register_least_squares(pb, ps, weights=w).base2sensor, t, atol=1e-9)
    assert model_rms(register_least_squares(pb, ps).base2sensor, t, pb) > 1.0


# ------------------------------------------------------------------------- combinatorial averaging


def test_chordal_mean_is_a_rotation_where_the_elementwise_mean_is_not() -> None:
    rs = rot_z(np.array([1.0, -1.0]))
    elementwise = rs.mean(axis=0)
    assert abs(np.linalg.det(elementwise) - 1.0) > 0.5  # eq. (6) as written: not a rotation
    np.testing.assert_allclose(chordal_mean_rotation(rs), np.eye(3), atol=1e-12)


def test_chordal_mean_of_symmetric_perturbations_is_the_centre() -> None:
    rng = np.random.default_rng(11)
    r0 = exp_so3(rng.normal(size=3))
    w = rng.normal(scale=0.2, size=(6, 3))
    rs = np.concatenate([r0 @ exp_so3(w), r0 @ exp_so3(-w)])
    np.testing.assert_allclose(chordal_mean_rotation(rs), r0, atol=1e-12)
    t = average_transforms(homogeneous(rs, np.arange(36.0).reshape(12, 3)))
    np.testing.assert_allclose(t[:3, 3], np.arange(36.0).reshape(12, 3).mean(axis=0))


def test_combinatorial_uses_every_triple_and_is_exact_without_noise() -> None:
    t, pb, ps = scene(5, 7, sigma=0.0)
    res = register_combinatorial(pb, ps)
    assert res.n_triples == math.comb(7, 3) and res.method == "combinatorial"
    np.testing.assert_allclose(res.base2sensor, t, atol=1e-9)


def test_combinatorial_average_is_proper_under_large_noise() -> None:
    # 20 mm noise on 60 mm spacing: the triple rotations scatter by tens of degrees, so an
    # element-wise average would be visibly non-orthogonal.
    rng = np.random.default_rng(2)
    t = true_transform(rng)
    pb = rng.uniform(-30, 30, (6, 3))
    ps = apply(t, pb) + rng.normal(0, 20.0, (6, 3))
    h, valid = triple_registrations(pb, ps, np.array([(0, 1, 2), (0, 1, 3), (0, 2, 4), (1, 3, 5), (2, 4, 5)]))
    elementwise = h[valid, :3, :3].mean(axis=0)
    assert np.abs(elementwise.T @ elementwise - np.eye(3)).max() > 0.05
    assert_rigid(register_combinatorial(pb, ps).base2sensor)


def test_combinatorial_beats_a_single_three_point_registration_on_average() -> None:
    worse = []
    for seed in range(30):
        t, pb, ps = scene(200 + seed, 8, sigma=0.2)
        check = np.random.default_rng(seed).uniform(-400, 400, (200, 3)) + np.array([600.0, 0.0, 400.0])
        e3 = model_rms(register_three_points(pb[:3], ps[:3]).base2sensor, t, check)
        ec = model_rms(register_combinatorial(pb, ps).base2sensor, t, check)
        worse.append((e3, ec))
    e3s, ecs = np.array(worse).T
    assert ecs.mean() < 0.5 * e3s.mean()
    assert (ecs < e3s).mean() > 0.8


def test_combinatorial_leaves_collinear_triples_out() -> None:
    t, pb, ps = scene(9, 5, sigma=0.0)
    pb = pb.copy()
    pb[2] = 0.5 * (pb[0] + pb[1])  # points 0, 1, 2 on one line
    ps = apply(t, pb)
    res = register_combinatorial(pb, ps)
    assert res.n_triples == math.comb(5, 3) - 1
    np.testing.assert_allclose(res.base2sensor, t, atol=1e-9)


def test_combinatorial_random_subset_is_seeded() -> None:
    t, pb, ps = scene(12, 12, sigma=0.3)
    a = register_combinatorial(pb, ps, max_triples=40, rng=1)
    b = register_combinatorial(pb, ps, max_triples=40, rng=1)
    c = register_combinatorial(pb, ps, max_triples=40, rng=2)
    assert a.n_triples == 40
    np.testing.assert_array_equal(a.base2sensor, b.base2sensor)
    assert not np.array_equal(a.base2sensor, c.base2sensor)
    assert register_combinatorial(pb, ps, max_triples=1000).n_triples == math.comb(12, 3)


# --------------------------------------------------------------------------- simulated annealing


def test_correction_matrix_is_zyx_euler_of_theta() -> None:
    th = np.array([1.0, 2.0, 3.0, 0.1, -0.2, 0.3])  # x y z α β γ
    expected = pose_to_matrix(th[:3], np.array([0.3, -0.2, 0.1]))  # (yaw=γ, pitch=β, roll=α)
    np.testing.assert_allclose(correction_matrix(th), expected, atol=1e-15)


@pytest.mark.parametrize("start", ["least_squares", "three_point", "far"])
def test_annealing_never_returns_worse_than_its_start(start: str) -> None:
    t, pb, ps = scene(21, 10, sigma=0.1)
    initial = {
        "least_squares": register_least_squares(pb, ps).base2sensor,  # the optimum: nothing to gain
        "three_point": register_three_points(pb[:3], ps[:3]).base2sensor,
        "far": t @ pose_to_matrix(np.array([3.0, -2.0, 1.0]), np.array([0.01, 0.0, -0.01])),
    }[start]
    out = refine_annealing(pb, ps, initial, rng=4, n_iterations=3000)
    start_cost = float(np.sum(translation_errors(initial, pb, ps) ** 2))
    got_cost = float(np.sum(out.registration.residuals_mm**2))
    assert out.initial_cost_mm2 == pytest.approx(start_cost, rel=1e-12)
    assert got_cost == pytest.approx(out.best_cost_mm2, rel=1e-9)  # reported cost is the real one
    assert got_cost <= start_cost
    assert_rigid(out.registration.base2sensor)


def test_annealing_refines_a_three_point_start_to_the_least_squares_optimum() -> None:
    gains = []
    for seed in range(6):
        t, pb, ps = scene(300 + seed, 10, sigma=0.1)
        start = register_three_points(pb[:3], ps[:3])
        out = refine_annealing(pb, ps, start, rng=seed)  # paper defaults, 20 000 iterations
        ls_cost = float(np.sum(register_least_squares(pb, ps).residuals_mm ** 2))
        assert out.best_cost_mm2 >= ls_cost * (1 - 1e-9)  # cannot beat the global minimum of (9)
        assert out.best_cost_mm2 < 1.2 * ls_cost
        gains.append(model_rms(start.base2sensor, t, pb) / model_rms(out.registration.base2sensor, t, pb))
    assert np.mean(gains) > 2.0


def test_annealing_is_reproducible_from_its_seed() -> None:
    t, pb, ps = scene(31, 8, sigma=0.1)
    start = register_three_points(pb[:3], ps[:3])
    a = refine_annealing(pb, ps, start, rng=5, n_iterations=500)
    b = refine_annealing(pb, ps, start, rng=5, n_iterations=500)
    c = refine_annealing(pb, ps, start, rng=6, n_iterations=500)
    np.testing.assert_array_equal(a.theta, b.theta)
    assert not np.array_equal(a.theta, c.theta)
    assert 0.0 < a.acceptance_rate <= 1.0


# ---------------------------------------------------------------------------------- clustering


def two_region_scene(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two far-apart work regions seen through slightly different transforms (a locally
    distorted sensor): (t_a, t_b, p_base (16, 3), p_sensor (16, 3), region (16,))."""
    rng = np.random.default_rng(seed)
    t_a = true_transform(rng)
    t_b = t_a @ pose_to_matrix(np.array([0.8, -0.5, 0.3]), np.radians([0.3, -0.2, 0.25]))
    region = np.repeat([0, 1], 8)
    centres = np.array([[300.0, -500.0, 200.0], [300.0, 500.0, 200.0]])
    pb = centres[region] + rng.uniform(-80, 80, (16, 3))
    ps = np.where(region[:, None] == 0, apply(t_a, pb), apply(t_b, pb)) + rng.normal(0, 0.01, (16, 3))
    return t_a, t_b, pb, ps, region


def test_kmeans_finds_separated_blobs_and_is_seeded() -> None:
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0, 0], [1000, 0, 0], [0, 1000, 0]])
    p = np.repeat(centres, 10, axis=0) + rng.normal(0, 10, (30, 3))
    c, labels = kmeans(p, 3, rng=3)
    for j in range(3):
        assert len(set(labels[10 * j : 10 * j + 10])) == 1
    np.testing.assert_allclose(np.sort(c[:, 0]), [0.0, 0.0, 1000.0], atol=15)
    c2, labels2 = kmeans(p, 3, rng=3)
    np.testing.assert_array_equal(labels, labels2)


def test_clustered_kernels_capture_local_transforms_better_than_one_global() -> None:
    t_a, t_b, pb, ps, region = two_region_scene(41)
    cl = register_clustered(pb, ps, 2, rng=0)
    assert isinstance(cl, ClusteredRegistration)
    assert not cl.full_set.any()
    assert set(zip(region.tolist(), cl.labels.tolist())) in ({(0, 0), (1, 1)}, {(0, 1), (1, 0)})
    np.testing.assert_array_equal(cl.n_triples, [math.comb(8, 2)] * 2)
    for c in range(2):
        assert_rigid(cl.base2sensor[c])
    glob = register_combinatorial(pb, ps)
    assert cl.rms_mm < 0.25 * glob.rms_mm
    # the seed's use: for a target in the sensor frame, where must the robot go?
    rng = np.random.default_rng(1)
    targets_base = np.array([[300.0, -500.0, 200.0], [300.0, 500.0, 200.0]])[region] + rng.uniform(-60, 60, (16, 3))
    targets_sensor = np.where(region[:, None] == 0, apply(t_a, targets_base), apply(t_b, targets_base))
    err_cluster = np.linalg.norm(cl.sensor_to_base(targets_sensor) - targets_base, axis=1)
    err_global = np.linalg.norm(apply(invert(glob.base2sensor), targets_sensor) - targets_base, axis=1)
    assert err_cluster.mean() < 0.25 * err_global.mean()
    np.testing.assert_allclose(cl.base_to_sensor(targets_base), targets_sensor, atol=5 * err_cluster.max() + 0.1)


def test_clustering_uses_the_whole_set_when_points_are_few() -> None:
    # The seed: "if M ≤ 3k ... the entire registration set may be used" (its own 4-point, 2-cluster case).
    t, pb, ps = scene(50, 6, sigma=0.0)
    cl = register_clustered(pb, ps, 2, rng=0)
    assert cl.full_set.all()
    np.testing.assert_array_equal(cl.n_triples, [math.comb(6, 3)] * 2)
    np.testing.assert_allclose(cl.base2sensor[0], t, atol=1e-9)


# ----------------------------------------------------------------------------- degenerate input


def test_collinear_and_coincident_points_are_refused_with_the_reason() -> None:
    line = np.array([[0.0, 0, 0], [100, 0, 0], [250, 0, 0]])
    with pytest.raises(ValueError, match="collinear.*tol_mm"):
        three_point_frame(line)
    with pytest.raises(ValueError, match="coincide"):
        three_point_frame(np.array([[1.0, 2, 3], [1.0, 2, 3], [0, 5, 0]]))
    good = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 0]])
    with pytest.raises(ValueError, match="p_sensor: points are collinear"):
        register_three_points(good, line)
    with pytest.raises(ValueError, match="p_base: points are collinear"):
        register_three_points(line, good)
    many = np.c_[np.linspace(0, 500, 6), np.linspace(0, 100, 6), np.zeros(6)]
    with pytest.raises(ValueError, match="collinear"):
        register_least_squares(many, many)
    with pytest.raises(ValueError, match="collinear"):
        register_combinatorial(many, many)


def test_a_point_just_off_the_line_is_accepted_above_the_stated_tolerance() -> None:
    p = np.array([[0.0, 0, 0], [100, 0, 0], [50, 1e-3, 0]])
    three_point_frame(p)  # 1 µm off the line, tolerance 1e-6 mm
    with pytest.raises(ValueError, match="collinear"):
        three_point_frame(p, tol_mm=1e-2)


@pytest.mark.parametrize(
    "fn", [register_least_squares, register_combinatorial, lambda b, s: register_clustered(b, s, 1)]
)
def test_bad_point_arrays_are_refused(fn) -> None:
    _, pb, ps = scene(60, 6)
    with pytest.raises(ValueError, match="at least 3 points; got 2"):
        fn(pb[:2], ps[:2])
    with pytest.raises(ValueError, match=r"same shape.*\(6, 3\) and \(5, 3\)"):
        fn(pb, ps[:5])
    bad = ps.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match=r"p_sensor holds non-finite values.*\[4\]"):
        fn(pb, bad)
    with pytest.raises(ValueError, match=r"shape \(n, 3\).*\(6, 2\)"):
        fn(pb[:, :2], ps[:, :2])


def test_three_point_registration_takes_exactly_three_points() -> None:
    _, pb, ps = scene(61, 4)
    with pytest.raises(ValueError, match="exactly 3 points; got 4"):
        register_three_points(pb, ps)


def test_bad_parameters_are_refused() -> None:
    _, pb, ps = scene(62, 6)
    with pytest.raises(ValueError, match="rigid transform"):
        refine_annealing(pb, ps, np.diag([2.0, 1, 1, 1]), rng=0)
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        refine_annealing(pb, ps, np.eye(3), rng=0)
    with pytest.raises(ValueError, match="n_iterations"):
        refine_annealing(pb, ps, np.eye(4), rng=0, n_iterations=0)
    with pytest.raises(ValueError, match="cooling_c"):
        refine_annealing(pb, ps, np.eye(4), rng=0, cooling_c=-2.0)
    with pytest.raises(ValueError, match="n_clusters"):
        register_clustered(pb, ps, 7)
    with pytest.raises(ValueError, match="max_triples"):
        register_combinatorial(pb, ps, max_triples=0)
    with pytest.raises(ValueError, match="weights must have shape"):
        register_least_squares(pb, ps, weights=np.ones(5))
    with pytest.raises(ValueError, match="at least 3 weights"):
        register_least_squares(pb, ps, weights=np.array([1.0, 1, 0, 0, 0, 0]))


def test_rotation_error_of_least_squares_matches_its_covariance() -> None:
    # Small-angle theory: the rotation error ω (sensor frame) has covariance σ² J⁻¹ with J the
    # inertia tensor Σ(|r|²I − rrᵀ) of the centred points, so ωᵀJω/σ² ~ χ²(3).
    limit = stats.chi2.ppf(0.999, 3)
    for seed in range(5):
        t, pb, ps = scene(70 + seed, 40)
        r = apply(t, pb) - apply(t, pb).mean(axis=0)
        j = np.sum(r**2) * np.eye(3) - r.T @ r
        for res, factor in ((register_least_squares(pb, ps), 1.0), (register_combinatorial(pb, ps, 300, 0), 25.0)):
            w = log_so3(res.base2sensor[:3, :3] @ t[:3, :3].T)
            assert w @ j @ w / SIGMA_MM**2 < factor * limit


def test_combinatorial_draws_random_triples_when_there_are_too_many_to_list() -> None:
    # C(250, 3) ≈ 2.57 million triples: more than are enumerated, so distinct ones are drawn.
    t, pb, ps = scene(80, 250, sigma=0.0)
    res = register_combinatorial(pb, ps, max_triples=200, rng=0)
    assert res.n_triples == 200
    np.testing.assert_allclose(res.base2sensor, t, atol=1e-8)
