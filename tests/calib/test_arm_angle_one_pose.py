"""7R ``solve_all(arm_angle=None)`` on one pose (plain floats, ``calib.ik.ik_arm_angle_scalar``)
against the vectorised path (``arm_angle_intervals_many``, ``solve_many``).

The float path must find the same feasible arm-angle intervals (same count, ends to 1e-9 rad),
pick the same arm angle and return exactly ``solve_many``'s result (status, message, labels in
order, rows to 1e-9 rad). Checked on hundreds of random reachable poses per iiwa (thousands in
the `slow` selection), with and without the limit filter, on poses whose joint vectors lie
beyond the limits ("limits" status),
on models with other sign conventions, zero offsets and limits beyond ±180°, with fitted zero
offsets, and on the edge poses where the float path hands over: singularities, the wrist point
on axis 1, joints at their limits, out of reach, and limits that a joint only grazes as the arm
angle turns (a double root). The random poses must mostly take the float path, or the
comparison would be vacuous.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.optimize import minimize_scalar

from calib.ik import ik
from calib.ik.ik_scalar import FALLBACK_MARGIN
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, robot_model_from_dict
from test_ik_one_pose import assert_same  # tests/calib is on sys.path under pytest

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
SEVEN = ["kuka_iiwa14_r820", "kuka_iiwa7_r800"]


def model(name: str):
    return load_robot_model(ROBOTS / f"{name}.yaml")


def wrap(a):
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * np.pi)


def float_intervals(m, pose, params=None) -> list[tuple[float, float]] | None:
    """The merged feasible intervals from the float path, or None where it hands over."""
    s = ik._solver(m, None if params is None else np.asarray(params, dtype=float))
    (r00, r01, r02, p0), (r10, r11, r12, p1), (r20, r21, r22, p2), _ = np.asarray(pose).tolist()
    one = s.one_pose.arm_angles.pose(((r00, r01, r02), (r10, r11, r12), (r20, r21, r22)), (p0, p1, p2))
    return None if one is None else ik._gap_intervals(one.cuts, one.feasible)


def assert_same_intervals(got, expected, where: str) -> None:
    assert len(got) == len(expected), f"{where}: {got} vs {expected}"
    if expected:
        np.testing.assert_allclose(np.array(got), np.array(expected), rtol=0, atol=1e-9, err_msg=where)


def compare(m, poses, *, within_limits=True, params=None, what=None) -> tuple[int, int]:
    """Float intervals against ``arm_angle_intervals_many`` and ``solve_all(arm_angle=None)``
    against ``solve_many``, pose by pose; returns how many poses took the float path for the
    intervals and for the whole solve."""
    expected_ivs = ik.arm_angle_intervals_many(m, poses, params=params)
    many = ik.solve_many(m, poses, within_limits=within_limits, params=params)
    s = ik._solver(m, None if params is None else np.asarray(params, dtype=float))
    fast_ivs = fast = 0
    for i, pose in enumerate(poses):
        where = f"pose {i}" if what is None else what[i]
        got = float_intervals(m, pose, params)
        if got is not None:
            assert_same_intervals(got, expected_ivs[i], where)
            fast_ivs += 1
        assert_same(ik.solve_all(m, pose, within_limits=within_limits, params=params), many[i], where)
        fast += ik._solve_one(s, pose, within_limits) is not None
    return fast_ivs, fast


#: Poses per comparison: a few hundred in the default selection, the full thousands in `slow`.
QUICK_AND_FULL = [500, pytest.param(3000, marks=pytest.mark.slow)]


@pytest.mark.parametrize("n", QUICK_AND_FULL)
@pytest.mark.parametrize("name", SEVEN)
def test_float_path_equals_vectorised_on_random_reachable_poses(name, n):
    m = model(name)
    q = np.random.default_rng(31).uniform(m.lower_limits_rad, m.upper_limits_rad, (n, 7))
    poses = Chain(m).fk(q)
    fast_ivs, fast = compare(m, poses)
    assert fast_ivs >= 0.98 * len(q), f"only {fast_ivs} of {len(q)} poses took the float path for the intervals"
    assert fast >= 0.95 * len(q), f"only {fast} of {len(q)} poses took the float path for the solve"
    # the picked arm angle is pick_arm_angle's
    for i in range(0, 300, 7):
        r = ik.solve_all(m, poses[i])
        psi = ik.pick_arm_angle(m, poses[i])
        np.testing.assert_allclose(wrap(ik.arm_angle_of(m, r.q) - psi), 0.0, atol=1e-9)


@pytest.mark.parametrize("n", [300, pytest.param(1500, marks=pytest.mark.slow)])
@pytest.mark.parametrize("name", SEVEN)
def test_float_path_equals_vectorised_beyond_the_limits(name, n):
    """Joint vectors up to 30 % beyond the limits: some poses have no feasible arm angle
    ("limits", the vectorised path's message) or lose a configuration to one joint."""
    m = model(name)
    lo, hi = m.lower_limits_rad, m.upper_limits_rad
    q = np.random.default_rng(33).uniform(1.3 * lo, 1.3 * hi, (n, 7))
    poses = Chain(m).fk(q)
    assert any(r.status == "limits" for r in ik.solve_many(m, poses)), "the sample must contain poses with no feasible arm angle"
    fast_ivs, _ = compare(m, poses)
    assert fast_ivs >= 0.95 * len(q)


def varied(name: str, seed: int, wide: bool):
    """The model with random sign conventions and DH angle offsets; ``wide``: A1, A3 and A7
    limits beyond ±180° (their ±360° images count, as for the KR 6's A6)."""
    data = copy.deepcopy(yaml.safe_load((ROBOTS / f"{name}.yaml").read_text()))
    rng = np.random.default_rng(seed)
    for j in data["joints"]:
        j["sign"] = int(rng.choice([-1, 1]))
        j["theta"] = float(j.get("theta", 0.0) + rng.uniform(-60, 60))
    if wide:
        for j, lim in ((0, 185.0), (2, 200.0), (6, 350.0)):
            data["joints"][j]["limits"] = [-lim, lim]
    return robot_model_from_dict(data)


@pytest.mark.parametrize("wide", [False, True])
@pytest.mark.parametrize("seed", [1, pytest.param(2, marks=pytest.mark.slow)])  # a second model: slow selection
def test_float_path_equals_vectorised_for_other_conventions_and_wide_limits(seed, wide):
    m = varied(SEVEN[0], seed, wide)
    q = np.random.default_rng(seed).uniform(m.lower_limits_rad, m.upper_limits_rad, (600, 7))
    poses = Chain(m).fk(q)
    if wide:
        many = ik.solve_many(m, poses)
        assert any("360" in label for r in many for label in r.branch), "the sample must reach ±360° equivalents"
    fast_ivs, fast = compare(m, poses)
    assert fast_ivs >= 0.95 * len(q) and fast >= 0.9 * len(q)


@pytest.mark.parametrize("name", SEVEN)
def test_float_path_equals_vectorised_with_fitted_parameters(name):
    m = model(name)
    chain = Chain(m)
    rng = np.random.default_rng(34)
    q = rng.uniform(m.lower_limits_rad, m.upper_limits_rad, (300, 7))
    offsets = chain.with_offsets(rng.normal(0, 0.01, 7))  # zero offsets only: exact closed form
    fast_ivs, fast = compare(m, chain.fk(q, offsets), params=offsets)
    assert fast_ivs >= 0.95 * len(q) and fast >= 0.9 * len(q)
    links = offsets.copy()
    links[chain.index("a")] += rng.normal(0, 0.5, 7)  # link errors: polished, never the float path
    s = ik._solver(m, links)
    assert s.one_pose is None
    for pose in chain.fk(q[:20], links):
        assert_same(ik.solve_all(m, pose, params=links), ik.solve_many(m, pose[None], params=links)[0], "polished")


def _edge_poses(m) -> list[tuple[str, np.ndarray]]:
    """Poses on and around the singularities and limits, as (what, pose)."""
    chain = Chain(m)
    lo, hi = m.lower_limits_rad, m.upper_limits_rad
    rng = np.random.default_rng(35)
    base_q = np.radians([20.0, 50.0, -30.0, -70.0, 40.0, 60.0, 15.0])
    g = ik._solver(m, None).geometry
    near = [0.0, 1e-7, 1e-5, 0.5 * FALLBACK_MARGIN, 2 * FALLBACK_MARGIN, 1e-2]
    out = []
    for eps in near:
        for sign in (1.0, -1.0):
            for j, what in ((1, "shoulder (A2) singular"), (3, "elbow stretched"), (5, "wrist (A6) singular")):
                q = base_q.copy()
                q[j] = sign * eps
                out.append((f"{what} {sign * eps:+g}", chain.fk(q)))
    w0 = g.axes.omega[0]
    up = w0 if w0[2] > 0 else -w0
    side = np.cross(up, [1.0, 0.0, 0.0])
    wrist_in_flange = (g.axes.home_inv @ np.append(g.wrist_point, 1.0))[:3]
    r = chain.fk(base_q)[:3, :3]
    for eps in near:
        pose = np.eye(4)
        pose[:3, :3] = r
        pose[:3, 3] = g.shoulder + 500.0 * up + eps * side / np.linalg.norm(side) - r @ wrist_in_flange
        out.append((f"wrist point on axis 1 + {eps:g} mm", pose))
    for j in range(7):  # A4 at a limit makes every arm angle borderline
        for lim in (lo[j], hi[j]):
            for eps in (0.0, 1e-12, -1e-12, 1e-10, -1e-10, 1e-8, -1e-8):
                q = rng.uniform(lo * 0.8, hi * 0.8)
                q[j] = lim + eps
                out.append((f"joint {j + 1} at limit {lim:.6f} {eps:+g}", chain.fk(q)))
    far = np.eye(4)
    far[:3, 3] = [3000.0, 0.0, 400.0]
    out.append(("out of reach", far))
    return out


@pytest.mark.parametrize("within_limits", [True, False])
@pytest.mark.parametrize("name", SEVEN)
def test_float_path_equals_vectorised_on_singular_limit_and_edge_poses(name, within_limits):
    m = model(name)
    edges = _edge_poses(m)
    poses = np.array([p for _, p in edges])
    many = ik.solve_many(m, poses, within_limits=within_limits)
    statuses = {r.status for r in many}
    assert {"singular", "unreachable"} <= statuses, f"the edge set must reach the special statuses, got {statuses}"
    compare(m, poses, within_limits=within_limits, what=[w for w, _ in edges])
    s = ik._solver(m, None)
    for (what, pose), expected in zip(edges, many):
        if expected.status != "ok":  # flagged poses never come from the float path
            assert ik._solve_one(s, pose, within_limits) is None, what


def _extreme(m, pose, branch: int, joint: int) -> tuple[float, float]:
    """(ψ, value): where joint ``joint`` of configuration ``branch`` is largest over the arm
    angle (rad), found on a grid and refined; limits off."""
    g = ik._solver(m, None).geometry
    grid = np.linspace(-math.pi, math.pi, 2001)

    def value(psi):
        return g.solve(np.broadcast_to(pose, (np.size(psi), 4, 4)), np.atleast_1d(psi)).q[:, branch, joint]

    vals = value(grid)
    i = int(np.nanargmax(vals))
    res = minimize_scalar(lambda p: -value(p)[0], bounds=(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]),
                          method="bounded", options={"xatol": 1e-13})
    return float(res.x), float(-res.fun)


@pytest.mark.parametrize("joint", [0, 1, pytest.param(4, marks=pytest.mark.slow), 5, 6])  # A5: 12 s, slow selection
def test_limits_a_joint_only_grazes_are_handed_over_or_decided_alike(joint):
    """A limit set at (or a hair's breadth from) a joint's largest value over the arm angle is
    a double root of its crossing equation: the float path hands such poses over (a root pair
    within the ratio margin) or decides them exactly as the vectorised path."""
    base = model(SEVEN[0])
    chain = Chain(base)
    rng = np.random.default_rng(36 + joint)
    data = yaml.safe_load((ROBOTS / f"{SEVEN[0]}.yaml").read_text())
    fast = handed_over = trials = 0
    for trial in range(40):
        q = rng.uniform(base.lower_limits_rad * 0.7, base.upper_limits_rad * 0.7)
        pose = chain.fk(q)
        branch = int(rng.integers(8))
        _, top = _extreme(base, pose, branch, joint)
        if not 0.2 < top < math.pi - 0.2:
            continue  # (a maximum at ±π is the wrap, not a tangency)
        trials += 1
        if trials > 3:
            break
        for eps in (0.0, 1e-13, -1e-13, 1e-10, -1e-10, 1e-6, -1e-6, 1e-3):
            d = copy.deepcopy(data)
            d["joints"][joint]["limits"] = [-179.0, math.degrees(top + eps)]
            m = robot_model_from_dict(d)
            got = float_intervals(m, pose)
            if got is None:
                handed_over += 1
            else:
                fast += 1
            compare(m, pose[None], what=[f"joint {joint + 1} grazing its limit {eps:+g} (trial {trial})"])
    assert fast and handed_over, f"both cases must occur (float path {fast}, handed over {handed_over})"


# --- the tie rule of the pick ------------------------------------------------------------------
def test_widest_arc_ties_go_to_the_centre_nearest_zero_then_the_positive_one():
    assert ik._widest_centre([(-3.0, -2.0), (0.5, 1.5)]) == pytest.approx(1.0)  # equal widths
    assert ik._widest_centre([(-2.0, -0.5), (1.0, 2.5 - 1e-12)]) == pytest.approx(-1.25)  # ψ + π symmetric: nearer 0
    assert ik._widest_centre([(-2.0, -1.0), (1.0, 2.0)]) == pytest.approx(1.5)  # ±c: the positive one
    assert ik._widest_centre([(-2.0, -1.0), (1.0, 2.0 + 1e-6)]) == pytest.approx(1.5 + 5e-7)  # clearly wider wins
    assert ik._widest_centre([(-3.0, -1.0 + 1e-6), (1.0, 3.0)]) == pytest.approx(-2.0 + 5e-7)
    assert ik._widest_centre([(-math.pi, -3.0), (2.0, math.pi)]) == pytest.approx(2.0 + 0.5 * (2 * math.pi - 5.0))  # one arc through ±π
    # the guard: a width or a distance from 0 near a tie threshold is left undecided
    assert ik._widest_centre([(-2.0, -1.0), (1.0, 2.0 + 1e-9)], guard=5e-10) is None
    assert ik._widest_centre([(-2.0, -1.0), (1.0, 2.0 + 3e-9)], guard=5e-10) == pytest.approx(1.5)
    assert ik._widest_centre([(-2.0 - 1e-9, -1.0 - 1e-9), (1.0, 2.0)], guard=5e-10) is None
    assert ik._widest_centre([(-2.0, -1.0), (1.0, 2.0)], guard=5e-10) == pytest.approx(1.5)
