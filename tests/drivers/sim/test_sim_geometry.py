"""Segment distances, sight lines and cones of the simulated cell, checked against brute force
and hand-built cases."""

import numpy as np
import pytest

from drivers.sim import geometry


def brute_segment_distance(p0, p1, q0, q1, k=201):
    s = np.linspace(0, 1, k)
    a = p0 + s[:, None] * (p1 - p0)
    b = q0 + s[:, None] * (q1 - q0)
    return np.min(np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1))


def test_segment_distance_matches_brute_force_on_random_segments():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-100, 100, size=(60, 4, 3))
    exact = geometry.segment_segment_distance(pts[:, 0], pts[:, 1], pts[:, 2], pts[:, 3])
    assert exact.shape == (60,)
    for i, (p0, p1, q0, q1) in enumerate(pts):
        brute = brute_segment_distance(p0, p1, q0, q1)
        step = (np.linalg.norm(p1 - p0) + np.linalg.norm(q1 - q0)) / 200
        # The grid minimum can only be larger than the true one, by at most the grid step.
        assert exact[i] <= brute + 1e-9
        assert exact[i] >= brute - step


@pytest.mark.parametrize(
    "p0, p1, q0, q1, expected",
    [
        ((0, 0, 0), (10, 0, 0), (5, 3, 0), (20, 3, 0), 3.0),  # parallel, overlapping
        ((0, 0, 0), (1, 0, 0), (3, 0, 0), (4, 0, 0), 2.0),  # collinear, disjoint
        ((0, 0, 0), (10, 0, 0), (5, -5, 5), (5, 5, 5), 5.0),  # skew, perpendicular
        ((-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), 0.0),  # crossing
        ((0, 0, 0), (0, 0, 0), (3, 4, 0), (3, 4, 0), 5.0),  # two points
        ((0, 0, 0), (0, 0, 0), (-5, 2, 0), (5, 2, 0), 2.0),  # point and segment
        ((0, 0, 0), (10, 0, 0), (13, 4, 0), (20, 4, 0), 5.0),  # end to end (3-4-5)
    ],
)
def test_segment_distance_special_cases(p0, p1, q0, q1, expected):
    got = geometry.segment_segment_distance(*(np.array(x, float) for x in (p0, p1, q0, q1)))
    assert got == pytest.approx(expected, abs=1e-9)
    swapped = geometry.segment_segment_distance(*(np.array(x, float) for x in (q0, q1, p0, p1)))
    assert swapped == pytest.approx(expected, abs=1e-9)


def test_point_segment_distance_clamps_to_the_ends():
    a, b = np.zeros(3), np.array([10.0, 0, 0])
    pts = np.array([[5, 2, 0], [-3, 4, 0], [13, 0, 4]], float)
    assert geometry.point_segment_distance(pts, a, b) == pytest.approx([2.0, 5.0, 5.0])


def test_sight_blocked_only_by_capsules_that_cross_the_line():
    sensor = np.array([0.0, 0, 0])
    targets = np.array([[1000.0, 0, 0], [1000.0, 300, 0]])
    # A vertical post of radius 50 at x = 500 on the first sight line; the second line passes
    # it at 150 mm. A second post holds the second target inside it (its own mount).
    cap_a = np.array([[500.0, 0, -200], [1000.0, 300, -100]])
    cap_b = np.array([[500.0, 0, 200], [1000.0, 300, 100]])
    radii = np.array([50.0, 30.0])
    blockers = geometry.sight_blockers(sensor, targets, cap_a, cap_b, radii)
    assert blockers.tolist() == [[True, False], [False, False]]
    assert geometry.line_of_sight(sensor, targets, cap_a, cap_b, radii).tolist() == [False, True]
    # Thinner post: the first line grazes past it.
    assert geometry.line_of_sight(sensor, targets, cap_a, cap_b, np.array([0.0, 30.0])).tolist() == [True, True]


def test_sight_lines_batch_over_configurations():
    rng = np.random.default_rng(2)
    k, m, c = 50, 2, 4
    sensor = np.array([0.0, 0, 0])
    targets = rng.uniform(-500, 500, (k, m, 3))
    cap_a = rng.uniform(-500, 500, (k, c, 3))
    cap_b = rng.uniform(-500, 500, (k, c, 3))
    radii = np.full(c, 60.0)
    batch = geometry.sight_blockers(sensor, targets, cap_a, cap_b, radii)
    assert batch.shape == (k, m, c)
    one_by_one = np.array([geometry.sight_blockers(sensor, targets[i], cap_a[i], cap_b[i], radii) for i in range(k)])
    assert np.array_equal(batch, one_by_one)
    assert 0 < batch.sum() < batch.size  # the random scene has both cases


def test_cone_accepts_inside_and_rejects_outside_the_half_angle():
    axis = np.array([0.0, 0, 1])
    angles = np.radians([0, 29, 31, 90, 179])
    dirs = np.stack([np.sin(angles), np.zeros(5), np.cos(angles)], -1) * 123.0
    assert geometry.within_cone(axis, dirs, np.radians(30)).tolist() == [True, True, False, False, False]
    assert geometry.within_cone(axis, dirs, np.pi).all()
    assert geometry.angle_between(axis, dirs) == pytest.approx(angles)


def test_look_at_frame_points_z_at_the_target_with_horizontal_x():
    origin, target = np.array([2000.0, 500, 1300]), np.array([0.0, 0, 600])
    t = geometry.look_at_frame(origin, target)
    r = t[:3, :3]
    assert r.T @ r == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert r[:, 2] == pytest.approx((target - origin) / np.linalg.norm(target - origin))
    assert r[2, 0] == pytest.approx(0.0, abs=1e-12)
    assert t[:3, 3] == pytest.approx(origin)


@pytest.mark.parametrize("target", [(0, 0, 0), (0, 0, 500)])
def test_look_at_frame_rejects_degenerate_views(target):
    with pytest.raises(ValueError, match="look at its own origin|parallel to up"):
        geometry.look_at_frame(np.zeros(3), np.array(target, float))
