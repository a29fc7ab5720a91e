"""``solve_all`` on one pose (plain floats, ``calib.ik.ik_scalar``) against the vectorised ``solve_many``.

The one-pose path (6R; 7R at a given arm angle) must return exactly ``solve_many``'s result:
same status and message, same labels in the same order, rows equal to 1e-9 rad. Checked on
thousands of random reachable poses per shipped robot (6R also from joint vectors beyond the
limits, so "limits" and ±360° cases occur; 7R at each pose's own arm angle and at random ones),
with and without the limit filter, with fitted parameter vectors, and on the edge poses where
the one-pose path hands over to ``solve_many``: wrist, shoulder and elbow singularities (exact,
inside the flag's 1e-6, inside the hand-over margin, just outside it), the 7R wrist point on
axis 1, joints exactly at and next to their limits, angles at ±π, out of reach. The random
poses must mostly take the float path, or the comparison would be vacuous.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.ik import ik
from calib.ik.ik_scalar import FALLBACK_MARGIN
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
SIX = ["kuka_kr6_r900_2", "staubli_tx60"]
SEVEN = ["kuka_iiwa14_r820", "kuka_iiwa7_r800"]
#: The slowest equivalence checks (~5 s a model) run one model in the default selection and the
#: other in the slow one.
SIX_FAST_ONE = [SIX[0], pytest.param(SIX[1], marks=pytest.mark.slow)]
SEVEN_FAST_ONE = [SEVEN[0], pytest.param(SEVEN[1], marks=pytest.mark.slow)]


def model(name: str):
    return load_robot_model(ROBOTS / f"{name}.yaml")


def assert_same(one: ik.IkSolutions, many: ik.IkSolutions, where: str) -> None:
    assert one.status == many.status, f"{where}: {one.status} vs {many.status} ({many.message})"
    assert one.message == many.message, where
    assert one.branch == many.branch, where
    assert one.q.shape == many.q.shape, where
    if len(many):
        np.testing.assert_allclose(one.q, many.q, rtol=0, atol=1e-9, err_msg=where)


def compare(m, poses, *, within_limits=True, params=None, psi=None) -> int:
    """solve_all per pose against one solve_many call (7R: at arm angles psi (k,) rad);
    returns how many took the float path."""
    many = ik.solve_many(m, poses, within_limits=within_limits, params=params, arm_angle=psi)
    s = ik._solver(m, None if params is None else np.asarray(params, dtype=float))
    fast = 0
    for i, pose in enumerate(poses):
        angle = None if psi is None else float(psi[i])
        one = ik.solve_all(m, pose, within_limits=within_limits, params=params, arm_angle=angle)
        assert_same(one, many[i], f"pose {i}")
        fast += ik._solve_one(s, pose, within_limits, angle) is not None
    return fast


@pytest.mark.parametrize("within_limits", [True, False])
@pytest.mark.parametrize("name", SIX)
def test_one_pose_path_equals_vectorised_on_random_reachable_poses(name, within_limits):
    m = model(name)
    q = np.random.default_rng(5).uniform(m.lower_limits_rad, m.upper_limits_rad, (3000, 6))
    fast = compare(m, Chain(m).fk(q), within_limits=within_limits)
    assert fast >= 0.95 * len(q), f"only {fast} of {len(q)} poses took the float path"


@pytest.mark.parametrize("name", SIX_FAST_ONE)
def test_one_pose_path_equals_vectorised_beyond_the_limits(name):
    """Joint vectors up to 40 % beyond the limits (A1 kept inside the reach of a real arm):
    poses whose solutions are all outside the limits give "limits" with the same message."""
    m = model(name)
    lo, hi = m.lower_limits_rad, m.upper_limits_rad
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    q = np.random.default_rng(6).uniform(mid - 1.4 * half, mid + 1.4 * half, (1500, 6))
    many = ik.solve_many(m, Chain(m).fk(q))
    assert any(r.status == "limits" for r in many), "the sample must contain poses with no solution within limits"
    compare(m, Chain(m).fk(q))


@pytest.mark.parametrize("name", SIX)
def test_one_pose_path_equals_vectorised_with_fitted_parameters(name):
    m = model(name)
    chain = Chain(m)
    rng = np.random.default_rng(7)
    q = rng.uniform(m.lower_limits_rad, m.upper_limits_rad, (300, 6))
    offsets = chain.with_offsets(rng.normal(0, 0.01, 6))  # zero-offsets only: exact closed form
    assert compare(m, chain.fk(q, offsets), params=offsets) >= 0.9 * len(q)
    links = offsets.copy()
    links[chain.index("a")] += rng.normal(0, 0.5, 6)  # link errors: polished, never the float path
    links[chain.index("alpha")] += rng.normal(0, 1e-3, 6)
    assert compare(m, chain.fk(q[:50], links), params=links) == 0


def _wrist_centre_in_flange(m) -> np.ndarray:
    s = ik._solver(m, None)
    g = s.geometry
    return (g.axes.home_inv @ np.append(g.wrist_centre, 1.0))[:3]


def _edge_poses(m) -> list[tuple[str, np.ndarray]]:
    """Poses on and around the 6R singularities, limits and ±π, as (what, pose)."""
    chain = Chain(m)
    lo, hi = m.lower_limits_rad, m.upper_limits_rad
    rng = np.random.default_rng(8)
    base_q = np.radians([20.0, -60.0, 70.0, 30.0, 40.0, 15.0])
    g = ik._solver(m, None).geometry
    out: list[tuple[str, np.ndarray]] = []
    near = [0.0, 1e-7, 1e-5, 0.5 * FALLBACK_MARGIN, 2 * FALLBACK_MARGIN, 1e-2, 5e-2]
    # wrist singular: A5 at its singular angle (axis 6 on axis 4), and near it
    for eps in near:
        for sign in (1.0, -1.0):
            q = base_q.copy()
            q[4] = g.wrist.aligned + sign * eps
            out.append((f"wrist singular + {sign * eps:g}", chain.fk(q)))
    # elbow stretched / folded: A3 at an extreme of the wrist centre's distance from axis 2
    scalar = ik._solver(m, None).one_pose.closed_form
    for extreme in (0.0, math.pi):
        q3 = math.atan2(scalar.el_b, scalar.el_a) + extreme
        for eps in near:
            q = base_q.copy()
            q[2] = math.pi - (math.pi - (q3 + eps)) % (2 * math.pi)
            out.append((f"elbow extreme {extreme:g} + {eps:g}", chain.fk(q)))
    # shoulder singular: the wrist centre on axis 1 (or on the surface its lateral offset makes)
    c_f = _wrist_centre_in_flange(m)
    w0, p0, w1 = g.axes.omega[0], g.axes.points[0], g.axes.omega[1]
    up = w0 if w0[2] > 0 else -w0
    r = chain.fk(np.radians([0.0, -45.0, 45.0, 0.0, -45.0, 0.0]))[:3, :3]
    for height in (300.0, 700.0):
        for eps in near:
            pose = np.eye(4)
            pose[:3, :3] = r
            pose[:3, 3] = p0 + height * up + (g.lateral + eps) * w1 - r @ c_f
            out.append((f"shoulder singular at {height:g} mm + {eps:g} mm", pose))
    # joints exactly at, just inside and just outside their limits, and at ±π
    for j in range(6):
        for lim in (lo[j], hi[j]):
            for eps in (0.0, 1e-12, -1e-12, 1e-10, -1e-10, 1e-8, -1e-8):
                q = rng.uniform(lo * 0.8, hi * 0.8)
                q[j] = lim + eps
                out.append((f"joint {j + 1} at limit {lim:.6f} {eps:+g}", chain.fk(q)))
        for angle in (math.pi, -math.pi, math.pi - 1e-12, math.nextafter(-math.pi, 0.0)):
            q = rng.uniform(lo * 0.8, hi * 0.8)
            q[j] = angle
            out.append((f"joint {j + 1} at {angle:.15f}", chain.fk(q)))
    # out of reach, and the arm folded onto its base
    far = np.eye(4)
    far[:3, 3] = [5000.0, 0.0, 400.0]
    out.append(("out of reach", far))
    out.append(("home", chain.fk(np.zeros(6))))
    return out


@pytest.mark.parametrize("within_limits", [True, False])
@pytest.mark.parametrize("name", SIX)
def test_one_pose_path_equals_vectorised_on_singular_limit_and_edge_poses(name, within_limits):
    m = model(name)
    edges = _edge_poses(m)
    many = ik.solve_many(m, np.array([p for _, p in edges]), within_limits=within_limits)
    statuses = {r.status for r in many}
    assert {"singular", "unreachable"} <= statuses, f"the edge set must reach the special statuses, got {statuses}"
    for (what, pose), expected in zip(edges, many):
        assert_same(ik.solve_all(m, pose, within_limits=within_limits), expected, what)
    # the hand-over works as documented: flagged poses never come from the float path
    s = ik._solver(m, None)
    for (what, pose), expected in zip(edges, many):
        if expected.status != "ok":
            assert ik._solve_one(s, pose, within_limits) is None, what


def test_one_pose_path_refuses_what_solve_many_refuses():
    m = model("kuka_kr6_r900_2")
    bad = np.eye(4)
    bad[0, 0] = 1.1
    with pytest.raises(ValueError, match="not a rigid transform"):
        ik.solve_all(m, bad)
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="not a rigid transform"):
        ik.solve_all(m, mirrored)
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ik.solve_all(m, nan)
    with pytest.raises(ValueError, match="arm_angle applies to 7-joint arms"):
        ik.solve_all(m, np.eye(4), arm_angle=0.1)


@pytest.mark.parametrize("name", SIX + SEVEN)
def test_one_pose_path_rejects_closed_form_rows_that_miss_the_pose(name, monkeypatch):
    """The FK check is real: a closed-form row off by 1e-7 rad in any one joint (a flange error of
    ~1e-4 mm or ~1e-7 rad, far above the tolerances) makes the float path hand the pose over, and
    solve_all still returns solve_many's solutions. Also for the second row of a branch pair,
    whose first joints the check walks only once when they equal the first row's."""
    m = model(name)
    n = m.n_joints
    q = np.radians([20.0, -50.0, 30.0, 40.0, 35.0, -25.0, 15.0][:n])
    pose = Chain(m).fk(q)
    psi = float(ik.arm_angle_of(m, q)) if n == 7 else None
    s = ik._solver(m, None)
    closed_form = s.one_pose.closed_form
    honest = closed_form.solve
    expected = ik.solve_many(m, pose[None], within_limits=False, arm_angle=psi)[0]
    expected_within = ik.solve_many(m, pose[None], arm_angle=psi)[0]
    assert ik._solve_one(s, pose, False, psi) is not None, "the clean pose must take the float path"
    rot, pos = tuple(map(tuple, pose[:3, :3].tolist())), tuple(pose[:3, 3].tolist())
    branches = honest(rot, pos) if psi is None else honest(rot, pos, psi)
    for b in (i for i, row in enumerate(branches) if row is not None):
        for j in range(n):

            def corrupted(*args, b=b, j=j, **kwargs):
                rows = honest(*args, **kwargs)
                rows[b] = list(rows[b])
                rows[b][j] += 1e-7
                return rows

            monkeypatch.setattr(closed_form, "solve", corrupted)
            assert ik._solve_one(s, pose, False, psi) is None, f"branch {b} joint {j + 1} off by 1e-7 rad was accepted"
            assert_same(ik.solve_all(m, pose, within_limits=False, arm_angle=psi), expected, f"branch {b} joint {j + 1}")
            # within limits too (a row the corruption takes outside them is dropped, as solve_many drops the true one)
            assert_same(ik.solve_all(m, pose, arm_angle=psi), expected_within, f"branch {b} joint {j + 1}, limits")
    monkeypatch.setattr(closed_form, "solve", honest)


def test_rotations_written_out_per_coordinate_axis_equal_the_general_formulas():
    """``calib.ik.ik_scalar._axis_ops``: the per-axis rotation and subproblem 1 for ±x, ±y, ±z (to
    1e-15, as DH axes are) agree with Rodrigues and the general subproblem; other axes use those."""
    from calib.ik.ik_scalar import _angle_about, _axis_ops, _rotate

    rng = np.random.default_rng(11)
    tilted = rng.normal(size=3)
    axes = [tuple(float(x) for x in sign * np.eye(3)[k]) for k in range(3) for sign in (1.0, -1.0)]
    axes += [(6.123233995736766e-17, 1.0, 6.123233995736766e-17), tuple((tilted / np.linalg.norm(tilted)).tolist())]
    for w in axes:
        rotate, angle_about = _axis_ops(w)
        for _ in range(20):
            v, p, q = (tuple(rng.normal(size=3).tolist()) for _ in range(3))
            angle = float(rng.uniform(-4.0, 4.0))
            np.testing.assert_allclose(rotate(angle, v), _rotate(w, angle, v), rtol=0, atol=1e-14, err_msg=str(w))
            assert abs(angle_about(p, q) - _angle_about(w, p, q)) < 1e-14, w


# --- 7R at a given arm angle ---------------------------------------------------------------------
@pytest.mark.parametrize("within_limits", [True, False])
@pytest.mark.parametrize("name", SEVEN_FAST_ONE)
def test_one_pose_path_equals_vectorised_7r_at_own_and_random_arm_angles(name, within_limits):
    m = model(name)
    rng = np.random.default_rng(9)
    q = rng.uniform(m.lower_limits_rad, m.upper_limits_rad, (3000, 7))
    poses = Chain(m).fk(q)
    fast = compare(m, poses, within_limits=within_limits, psi=ik.arm_angle_of(m, q))
    assert fast >= 0.95 * len(q), f"only {fast} of {len(q)} poses took the float path"
    psi = rng.uniform(-math.pi, math.pi, 1000)
    fast = compare(m, poses[:1000], within_limits=within_limits, psi=psi)
    if not within_limits:  # (within limits, a random arm angle often leaves no row: "limits", handed over)
        assert fast >= 0.95 * 1000


@pytest.mark.parametrize("name", SEVEN)
def test_one_pose_path_equals_vectorised_7r_with_fitted_parameters(name):
    m = model(name)
    chain = Chain(m)
    rng = np.random.default_rng(10)
    q = rng.uniform(m.lower_limits_rad, m.upper_limits_rad, (300, 7))
    offsets = chain.with_offsets(rng.normal(0, 0.01, 7))
    psi = ik.arm_angle_of(m, q, params=offsets)
    assert compare(m, chain.fk(q, offsets), params=offsets, psi=psi) >= 0.9 * len(q)
    links = offsets.copy()
    links[chain.index("a")] += rng.normal(0, 0.5, 7)
    assert compare(m, chain.fk(q[:30], links), params=links, psi=psi[:30]) == 0


def _edge_poses_7r(m) -> list[tuple[str, np.ndarray, float]]:
    """7R poses on and around the singularities, limits and ±π, as (what, pose, ψ)."""
    chain = Chain(m)
    lo, hi = m.lower_limits_rad, m.upper_limits_rad
    rng = np.random.default_rng(11)
    base_q = np.radians([20.0, 50.0, -30.0, -70.0, 40.0, 60.0, 15.0])
    g = ik._solver(m, None).geometry
    near = [0.0, 1e-7, 1e-5, 0.5 * FALLBACK_MARGIN, 2 * FALLBACK_MARGIN, 1e-2, 5e-2]
    out = []

    def add(what, q):
        out.append((what, chain.fk(q), float(ik.arm_angle_of(m, q))))

    for eps in near:
        for sign in (1.0, -1.0):
            for j, what in ((1, "shoulder (A2) singular"), (3, "elbow stretched"), (5, "wrist (A6) singular")):
                q = base_q.copy()
                q[j] = sign * eps
                add(f"{what} {sign * eps:+g}", q)
    # the wrist point on axis 1 (reference plane undefined), and near it
    w0 = g.axes.omega[0]
    up = w0 if w0[2] > 0 else -w0
    wrist_in_flange = (g.axes.home_inv @ np.append(g.wrist_point, 1.0))[:3]
    r = chain.fk(base_q)[:3, :3]
    for eps in near:
        pose = np.eye(4)
        pose[:3, :3] = r
        side = np.cross(up, [1.0, 0.0, 0.0])
        pose[:3, 3] = g.shoulder + 500.0 * up + eps * side / np.linalg.norm(side) - r @ wrist_in_flange
        out.append((f"wrist point on axis 1 + {eps:g} mm", pose, 0.3))
    for j in range(7):
        for lim in (lo[j], hi[j]):
            for eps in (0.0, 1e-12, -1e-12, 1e-10, -1e-10, 1e-8, -1e-8):
                q = rng.uniform(lo * 0.8, hi * 0.8)
                q[j] = lim + eps
                add(f"joint {j + 1} at limit {lim:.6f} {eps:+g}", q)
    for angle in (math.pi, -math.pi, math.pi - 1e-12):
        q = rng.uniform(lo * 0.8, hi * 0.8)
        add(f"arm angle {angle:.15f}", q)
        out[-1] = (out[-1][0], out[-1][1], angle)
    far = np.eye(4)
    far[:3, 3] = [3000.0, 0.0, 400.0]
    out.append(("out of reach", far, 0.0))
    return out


@pytest.mark.parametrize("within_limits", [True, False])
@pytest.mark.parametrize("name", SEVEN)
def test_one_pose_path_equals_vectorised_7r_on_singular_limit_and_edge_poses(name, within_limits):
    m = model(name)
    edges = _edge_poses_7r(m)
    poses = np.array([p for _, p, _ in edges])
    psi = np.array([a for _, _, a in edges])
    many = ik.solve_many(m, poses, within_limits=within_limits, arm_angle=psi)
    statuses = {r.status for r in many}
    assert {"singular", "unreachable"} <= statuses, f"the edge set must reach the special statuses, got {statuses}"
    s = ik._solver(m, None)
    for (what, pose, angle), expected in zip(edges, many):
        assert_same(ik.solve_all(m, pose, within_limits=within_limits, arm_angle=angle), expected, what)
        if expected.status != "ok":
            assert ik._solve_one(s, pose, within_limits, angle) is None, what
