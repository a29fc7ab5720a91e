"""Inverse kinematics (calib.ik.ik): every solution, checked against FK and a brute-force search.

* Round trips: FK of thousands of seeded random joint vectors → IK → every row reproduces the
  pose (checked here again with ``Chain.fk``), lies within limits, and the original vector is
  among the rows (7R: at its own arm angle).
* Completeness: on a sample of poses the count of distinct solutions within limits equals what a
  brute-force random-start Levenberg–Marquardt search finds (``calib.ik.ik_numeric``), and every
  numeric solution is one of ours.
* Branch labels against the KUKA meanings computed here from FK alone.
* Out of reach, singular and limit cases give their status and a message; bad input raises.
* 7R arm-angle intervals: inside an interval the configuration is within limits, just outside
  it is not, and a dense sweep of ψ agrees everywhere away from the boundaries.
* Models of the class other than the shipped ones (random sign conventions and offsets) and
  fitted parameter vectors (zero-offsets: exact; full link errors: polished).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from calib.ik import ik
from calib.ik.ik_numeric import solve_numeric
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, robot_model_from_dict
from calib.robot.transforms import homogeneous, rotation_angle

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
SIX = ["kuka_kr6_r900_2", "staubli_tx60"]
SEVEN = ["kuka_iiwa14_r820", "kuka_iiwa7_r800"]


def model(name: str):
    return load_robot_model(ROBOTS / f"{name}.yaml")


def wrap(a):
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * np.pi)


def random_q(m, n, seed, shrink=1.0):
    rng = np.random.default_rng(seed)
    return rng.uniform(m.lower_limits_rad * shrink, m.upper_limits_rad * shrink, (n, m.n_joints))


def assert_reproduces(chain, sols, pose, params=None):
    """Independent check of the solver's promise: every row reproduces the pose."""
    assert sols.q.shape[0] == len(sols.branch)
    if len(sols) == 0:
        return
    t = chain.fk(sols.q, params)
    dp = np.linalg.norm(t[:, :3, 3] - pose[:3, 3], axis=-1)
    dr = rotation_angle(np.swapaxes(t[:, :3, :3], -1, -2) @ pose[:3, :3])
    assert dp.max() <= 1e-6, f"position error {dp.max()} mm"
    assert dr.max() <= 1e-9, f"orientation error {dr.max()} rad"


def contains(rows, q, tol=1e-7):
    return rows.size > 0 and bool(np.any(np.abs(rows - q).max(axis=-1) < tol))


# --- round trips ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SIX + SEVEN)
def test_round_trip_random_poses_every_solution_reproduces_and_original_is_found(name):
    m = model(name)
    chain = Chain(m)
    q = random_q(m, 2000, seed=11)
    poses = chain.fk(q)
    kw = {"arm_angle": ik.arm_angle_of(m, q)} if m.n_joints == 7 else {}
    results = ik.solve_many(m, poses, **kw)
    assert len(results) == len(q)
    missing = []
    for i, r in enumerate(results):
        assert r.status in ("ok", "singular"), r.message
        assert_reproduces(chain, r, poses[i])
        assert np.all(m.within_limits(r.q))
        assert len(set(r.branch)) == len(r.branch), "labels must tell rows apart"
        if not contains(r.q, q[i]):
            missing.append(i)
    assert not missing, f"original joint vector not among the solutions for poses {missing[:10]}"


@pytest.mark.parametrize("name", SIX + SEVEN[:1])
def test_solve_all_matches_solve_many_row_for_row(name):
    m = model(name)
    chain = Chain(m)
    q = random_q(m, 5, seed=3)
    poses = chain.fk(q)
    kw = {"arm_angle": 0.7} if m.n_joints == 7 else {}
    many = ik.solve_many(m, poses, **kw)
    for i in range(5):
        one = ik.solve_all(m, poses[i], **kw)
        assert one.branch == many[i].branch
        # a 6R pose is solved in plain floats (calib.ik.ik_scalar): equal to rounding, not bit for bit
        np.testing.assert_allclose(one.q, many[i].q, rtol=0, atol=1e-12)


def test_principal_branches_without_limit_filter_are_wrapped_and_eight():
    m = model("kuka_kr6_r900_2")
    chain = Chain(m)
    q = np.radians([20, -70, 80, 30, 50, 10])
    r = ik.solve_all(m, chain.fk(q), within_limits=False)
    assert r.status == "ok"
    assert len(r) == 8
    assert np.all((r.q > -np.pi) & (r.q <= np.pi))
    assert sorted(r.branch) == sorted(set(r.branch))
    assert_reproduces(chain, r, chain.fk(q))


def test_wrist_equivalents_within_limits_are_returned_and_labelled():
    m = model("kuka_kr6_r900_2")
    chain = Chain(m)
    q = np.radians([20, -70, 80, 30, 50, 10])  # A6 = 10°: A6 − 360 = −350° is also inside ±350°
    r = ik.solve_all(m, chain.fk(q))
    i0 = r.branch.index("shoulder=front elbow=up wrist=noflip")
    i1 = r.branch.index("shoulder=front elbow=up wrist=noflip A6-360")
    np.testing.assert_allclose(r.q[i1] - r.q[i0], [0, 0, 0, 0, 0, -2 * np.pi], atol=1e-12)
    assert np.all(m.within_limits(r.q))
    # and nothing within limits is left out: every principal row's every fitting equivalent is there
    principal = ik.solve_all(m, chain.fk(q), within_limits=False)
    expected = 0
    for row in principal.q:
        for k4 in (-1, 0, 1):
            for k6 in (-1, 0, 1):
                expected += bool(m.within_limits(row + 2 * np.pi * np.array([0, 0, 0, k4, 0, k6])))
    assert len(r) == expected


# --- completeness against a brute-force numeric search ---------------------------------------------
@pytest.mark.parametrize(
    "name,n_poses,n_starts",
    [("kuka_kr6_r900_2", 12, 1000), ("staubli_tx60", 12, 1000),
     pytest.param("kuka_iiwa14_r820", 4, 500, marks=pytest.mark.slow)],  # the 7R case: ~10 s, slow selection
)
def test_solution_count_matches_brute_force_numeric_search(name, n_poses, n_starts):
    m = model(name)
    chain = Chain(m)
    q = random_q(m, n_poses, seed=21)
    for i in range(n_poses):
        pose = chain.fk(q[i])
        psi = float(ik.arm_angle_of(m, q[i])) if m.n_joints == 7 else None
        ours = ik.solve_all(m, pose, arm_angle=psi)
        numeric = solve_numeric(m, pose, n_starts=n_starts, seed=i, arm_angle=psi)
        assert len(numeric) >= 1
        for row in numeric:
            assert contains(ours.q, row, tol=1e-6), f"numeric solution {np.degrees(row)} missing from ours"
        assert len(ours) == len(numeric), (ours.branch, len(numeric))


# --- branch labels mean what they say -----------------------------------------------------------------
def test_kr6_labels_follow_kuka_status_bits_computed_from_fk():
    m = model("kuka_kr6_r900_2")
    chain = Chain(m)
    q = random_q(m, 400, seed=5)
    # stay clear of the singular boundaries, where a label is a matter of rounding
    home = np.array([0, -np.pi / 2, np.pi / 2, 0, 0, 0])
    grid = np.linspace(-np.pi, np.pi, 20001)
    probe = np.tile(home, (grid.size, 1))
    probe[:, 2] = grid
    wc = chain.fk(probe)[:, :3, 3] - 90.0 * chain.fk(probe)[:, :3, 2]
    a2_axis = np.array([25.0, 400.0])  # A2 axis at A1 = 0: x = 25, z = 400
    reach = np.hypot(wc[:, 0] - a2_axis[0], wc[:, 2] - a2_axis[1])
    stretched = grid[np.argmax(reach)]
    for row in q:
        t = chain.fk(row)
        wc = t[:3, 3] - 90.0 * t[:3, 2]
        facing = chain.fk(np.array([row[0], -np.pi / 2, np.pi / 2, 0, 0, 0]))[:3, 3]
        along = facing[:2] @ wc[:2] / np.linalg.norm(facing[:2])
        bend = math.sin(row[2] - stretched)
        if abs(along) < 5 or abs(bend) < 0.05 or abs(math.sin(row[4])) < 0.05:
            continue
        r = ik.solve_all(m, t)
        label = r.branch[int(np.argmin(np.abs(r.q - row).max(-1)))]
        assert ("shoulder=front" in label) == (along > 0), (np.degrees(row), label)
        assert ("elbow=up" in label) == (bend > 0), (np.degrees(row), label)
        assert ("wrist=noflip" in label) == (row[4] > 0), (np.degrees(row), label)


def test_tx60_labels_front_and_wrist_follow_geometry_and_j5_sign():
    m = model("staubli_tx60")
    chain = Chain(m)
    q = random_q(m, 300, seed=12)
    q = q[(np.abs(np.sin(q[:, 4])) > 0.05) & (np.abs(np.sin(q[:, 2])) > 0.05)]
    res = ik.solve_many(m, chain.fk(q))
    checked = 0
    for row, r in zip(q, res):
        t = chain.fk(row)
        wc = t[:3, 3] - 70.0 * t[:3, 2]  # wrist centre: 70 mm behind the flange
        facing = np.array([math.cos(row[0]), math.sin(row[0])])  # the arm faces +x at J1 = 0
        along = facing @ wc[:2]
        if abs(along) < 5:
            continue
        label = r.branch[int(np.argmin(np.abs(r.q - row).max(-1)))]
        assert ("shoulder=front" in label) == (along > 0), (np.degrees(row), label)
        assert ("wrist=noflip" in label) == (row[4] > 0), (np.degrees(row), label)
        checked += 1
    assert checked > 150


def test_iiwa_labels_are_the_signs_of_a2_a4_a6():
    m = model("kuka_iiwa14_r820")
    chain = Chain(m)
    q = random_q(m, 300, seed=8)
    q = q[np.all(np.abs(q[:, [1, 3, 5]]) > 1e-3, axis=1)]
    res = ik.solve_many(m, chain.fk(q), arm_angle=ik.arm_angle_of(m, q))
    for row, r in zip(q, res):
        label = r.branch[int(np.argmin(np.abs(r.q - row).max(-1)))]
        want = "GC2={:+d} GC4={:+d} GC6={:+d}".format(*(int(np.sign(row[j])) for j in (1, 3, 5)))
        assert label == want


def test_every_seven_axis_solution_has_the_requested_arm_angle():
    m = model("kuka_iiwa7_r800")
    chain = Chain(m)
    q = random_q(m, 50, seed=9)
    for psi in (-2.5, 0.0, 1.3):
        for r in ik.solve_many(m, chain.fk(q), arm_angle=psi, within_limits=False):
            assert len(r) == 8
            np.testing.assert_allclose(wrap(ik.arm_angle_of(m, r.q) - psi), 0, atol=1e-9)


# --- statuses -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SIX + SEVEN[:1])
def test_pose_beyond_reach_is_unreachable_with_distances_in_the_message(name):
    m = model(name)
    r = ik.solve_all(m, homogeneous(np.eye(3), np.array([2500.0, 100.0, 300.0])))
    assert r.status == "unreachable"
    assert r.q.shape == (0, m.n_joints) and r.branch == []
    assert "out of reach" in r.message and "mm" in r.message


def test_tx60_wrist_centre_on_axis_1_is_unreachable_because_of_the_shoulder_offset():
    m = model("staubli_tx60")
    r = ik.solve_all(m, homogeneous(np.eye(3), np.array([0.0, 0.0, 1000.0])))
    assert r.status == "unreachable"
    assert "lateral offset" in r.message and "J1" in r.message


def test_wrist_singular_pose_returns_representatives_and_says_sum():
    m = model("kuka_kr6_r900_2")
    chain = Chain(m)
    q = np.radians([10, -80, 70, 30, 0, 20])
    pose = chain.fk(q)
    r = ik.solve_all(m, pose)
    assert r.status == "singular"
    assert "A4 + A6" in r.message and "sum" in r.message
    assert_reproduces(chain, r, pose)
    # the arm configuration of q is there, with A4 + A6 (A5 = 0: both axes turn the same way)
    same_arm = r.q[np.abs(r.q[:, :3] - q[:3]).max(-1) < 1e-7]
    assert len(same_arm) >= 1
    np.testing.assert_allclose(wrap(same_arm[:, 3] + same_arm[:, 5] - q[3] - q[5]), 0, atol=1e-7)


def test_shoulder_singular_pose_kr6_wrist_centre_on_axis_1():
    m = model("kuka_kr6_r900_2")
    chain = Chain(m)
    pose = homogeneous(np.eye(3), np.array([0.0, 0.0, 1290.0]))  # wrist centre 90 mm below: on A1
    r = ik.solve_all(m, pose)
    assert r.status == "singular"
    assert "shoulder singular" in r.message and "A1" in r.message
    assert len(r) > 0
    assert_reproduces(chain, r, pose)


def test_stretched_elbow_is_flagged_singular():
    m = model("staubli_tx60")
    chain = Chain(m)
    pose = chain.fk(np.radians([10, 20, 0, 30, 40, 20]))
    r = ik.solve_all(m, pose)
    assert r.status == "singular" and "elbow singular" in r.message
    assert_reproduces(chain, r, pose)


def test_iiwa_shoulder_singular_pose_is_flagged():
    m = model("kuka_iiwa14_r820")
    chain = Chain(m)
    q = np.radians([10, 0, 20, 50, 20, 30, 10])
    pose = chain.fk(q)
    r = ik.solve_all(m, pose, arm_angle=float(ik.arm_angle_of(m, q)))
    assert r.status == "singular" and "A2" in r.message and "A1 and A3" in r.message
    assert_reproduces(chain, r, pose)


def test_solutions_only_outside_limits_give_status_limits_naming_the_axis():
    m = model("kuka_kr6_r900_2")
    chain = Chain(m)
    pose = chain.fk(np.radians([0, -90, 90, 0, 0, 0]))
    pose[:3, 3] = [30.0, 0.0, 420.0]  # folded back onto the base: needs A3 beyond its limit
    r = ik.solve_all(m, pose)
    assert r.status == "limits"
    assert len(r) == 0 and "none is within the joint limits" in r.message and "A3" in r.message
    unfiltered = ik.solve_all(m, pose, within_limits=False)
    assert len(unfiltered) > 0 and not np.any(m.within_limits(unfiltered.q))


def test_iiwa_elbow_beyond_limit_has_no_feasible_arm_angle():
    m = model("kuka_iiwa14_r820")
    chain = Chain(m)
    pose = chain.fk(np.radians([10, 30, 20, 125, 20, 30, 10]))  # |A4| = 125° > 120° for every ψ
    assert ik.arm_angle_intervals(m, pose) == []
    with pytest.raises(ik.NoFeasibleArmAngle, match="within limits"):
        ik.pick_arm_angle(m, pose)
    r = ik.solve_all(m, pose)
    assert r.status == "limits" and len(r) == 0


# --- 7R arm-angle intervals -----------------------------------------------------------------------------
def test_arm_angle_intervals_inside_within_limits_just_outside_not():
    m = model("kuka_iiwa14_r820")
    chain = Chain(m)
    q = random_q(m, 25, seed=13)
    checked = 0
    for row in q:
        pose = chain.fk(row)
        per = ik.arm_angle_intervals_by_configuration(m, pose)
        assert set(per) == set(ik.branch_labels(m))
        probes = []  # (label, ψ, expected within limits)
        for label, ivs in per.items():
            for lo, hi in ivs:
                assert -np.pi <= lo < hi <= np.pi
                for psi, inside in ((lo + 1e-7, True), (hi - 1e-7, True), (lo - 1e-7, False), (hi + 1e-7, False)):
                    if abs(abs(psi) - np.pi) < 1e-6 or not -np.pi < psi <= np.pi:
                        continue  # ±π is the same arm angle: the interval continues on the other side
                    if not inside and any(a - 1e-6 <= psi <= b + 1e-6 for a, b in ivs if (a, b) != (lo, hi)):
                        continue
                    probes.append((label, psi, inside))
        if not probes:
            continue
        psis = np.array([p[1] for p in probes])
        res = ik.solve_many(m, np.broadcast_to(pose, (len(psis), 4, 4)), arm_angle=psis, within_limits=False)
        for (label, psi, inside), r in zip(probes, res):
            row_q = r.q[r.branch.index(label)]
            assert bool(m.within_limits(row_q)) == inside, (label, psi)
            checked += 1
    assert checked > 50


def test_arm_angle_intervals_agree_with_a_dense_sweep():
    m = model("kuka_iiwa7_r800")
    chain = Chain(m)
    grid = np.linspace(-np.pi, np.pi, 3001)
    for row in random_q(m, 6, seed=17):
        pose = chain.fk(row)
        merged = ik.arm_angle_intervals(m, pose)
        res = ik.solve_many(m, np.broadcast_to(pose, (grid.size, 4, 4)), arm_angle=grid)
        feasible = np.array([len(r) > 0 for r in res])
        inside = np.zeros(grid.size, dtype=bool)
        near = np.zeros(grid.size, dtype=bool)
        for lo, hi in merged:
            inside |= (grid >= lo) & (grid <= hi)
            near |= (np.abs(grid - lo) < 1e-9) | (np.abs(grid - hi) < 1e-9)
        assert np.array_equal(inside[~near], feasible[~near])
        # the pose's own arm angle is feasible (row is within limits)
        psi = float(ik.arm_angle_of(m, row))
        assert any(lo <= psi <= hi for lo, hi in merged)


def test_arm_angle_intervals_many_equals_one_by_one():
    m = model("kuka_iiwa14_r820")
    chain = Chain(m)
    poses = chain.fk(random_q(m, 12, seed=23))
    poses[3, :3, 3] = [2000.0, 0.0, 0.0]  # out of reach: no interval
    many = ik.arm_angle_intervals_many(m, poses)
    assert many[3] == []
    for i in range(len(poses)):
        assert many[i] == ik.arm_angle_intervals(m, poses[i])


def test_pick_arm_angle_centre_and_closest_to_preference():
    m = model("kuka_iiwa14_r820")
    chain = Chain(m)
    for row in random_q(m, 10, seed=19):
        pose = chain.fk(row)
        ivs = ik.arm_angle_intervals(m, pose)
        psi = ik.pick_arm_angle(m, pose)
        assert any(lo <= psi <= hi for lo, hi in ivs)
        assert len(ik.solve_all(m, pose, arm_angle=psi)) > 0
        default = ik.solve_all(m, pose)  # arm_angle None: picks the same ψ
        assert default.status == "ok" and len(default) > 0
        np.testing.assert_allclose(wrap(ik.arm_angle_of(m, default.q) - psi), 0, atol=1e-9)
        for prefer in (-3.0, -1.0, 0.5, 2.9):
            got = ik.pick_arm_angle(m, pose, prefer=prefer)
            assert any(lo <= got <= hi for lo, hi in ivs)
            if any(lo <= prefer <= hi for lo, hi in ivs):
                assert got == pytest.approx(prefer)
            else:  # nothing feasible lies closer to the preference
                probe = wrap(prefer + np.linspace(-1, 1, 2001) * abs(wrap(got - prefer)) * 0.999)
                assert not any(lo <= p <= hi for p in probe for lo, hi in ivs)


# --- other models of the class, fitted parameters ---------------------------------------------------------
def varied(name: str, seed: int):
    """The model with random controller sign conventions and DH angle offsets (same geometry class)."""
    data = yaml.safe_load((ROBOTS / f"{name}.yaml").read_text())
    rng = np.random.default_rng(seed)
    data = copy.deepcopy(data)
    for j in data["joints"]:
        j["sign"] = int(rng.choice([-1, 1]))
        j["theta"] = float(j.get("theta", 0.0) + rng.uniform(-60, 60))
    return robot_model_from_dict(data)


@pytest.mark.parametrize("name", SIX + SEVEN[:1])
@pytest.mark.parametrize("seed", [1, 2])
def test_any_model_of_the_class_sign_conventions_and_offsets(name, seed):
    m = varied(name, seed)
    chain = Chain(m)
    q = random_q(m, 300, seed=seed)
    poses = chain.fk(q)
    kw = {"arm_angle": ik.arm_angle_of(m, q)} if m.n_joints == 7 else {}
    for i, r in enumerate(ik.solve_many(m, poses, **kw)):
        assert_reproduces(chain, r, poses[i])
        assert contains(r.q, q[i])


def test_models_outside_the_class_are_rejected_with_the_reason():
    data = yaml.safe_load((ROBOTS / "staubli_tx60.yaml").read_text())
    data["joints"][4]["d"] = 30.0  # J5 offset: wrist axes no longer meet
    with pytest.raises(ValueError, match="not a 6R arm with a spherical wrist.*miss a common point"):
        ik.solve_all(robot_model_from_dict(data), np.eye(4))
    data = yaml.safe_load((ROBOTS / "kuka_kr6_r900_2.yaml").read_text())
    data["joints"][1]["alpha"] = 10.0  # A2 ∦ A3
    with pytest.raises(ValueError, match="A2 and A3 are at .* not parallel"):
        ik.solve_all(robot_model_from_dict(data), np.eye(4))
    data = yaml.safe_load((ROBOTS / "kuka_iiwa14_r820.yaml").read_text())
    data["joints"][1]["d"] = 50.0  # shoulder axes no longer meet
    with pytest.raises(ValueError, match="not a 7R S-R-S arm"):
        ik.solve_all(robot_model_from_dict(data), np.eye(4), arm_angle=0.0)
    data["joints"] = data["joints"][:5]
    with pytest.raises(ValueError, match="5 joints"):
        ik.solve_all(robot_model_from_dict(data), np.eye(4))


@pytest.mark.parametrize("name", SIX + SEVEN[:1])
def test_fitted_zero_offsets_are_solved_exactly(name):
    m = model(name)
    chain = Chain(m)
    rng = np.random.default_rng(4)
    params = chain.with_offsets(rng.normal(0, 0.02, m.n_joints))
    q = random_q(m, 300, seed=4)
    poses = chain.fk(q, params)
    kw = {"arm_angle": ik.arm_angle_of(m, q, params=params)} if m.n_joints == 7 else {}
    for i, r in enumerate(ik.solve_many(m, poses, params=params, **kw)):
        assert_reproduces(chain, r, poses[i], params)
        assert contains(r.q, q[i])


@pytest.mark.parametrize("name", SIX + SEVEN[:1])
def test_full_parameter_errors_are_polished_onto_the_fitted_model(name):
    m = model(name)
    chain = Chain(m)
    rng = np.random.default_rng(6)
    n = m.n_joints
    params = chain.nominal.copy()
    params[:n] += rng.normal(0, 0.01, n)
    params[n : 3 * n] += rng.normal(0, 0.3, 2 * n)  # d, a: 0.3 mm
    params[3 * n : 5 * n] += rng.normal(0, 1e-3, 2 * n)  # α, β: 1 mrad
    q = random_q(m, 200, seed=6, shrink=0.9)
    # away from singularities, where branches of the perturbed model are those of the nominal one
    if n == 6:
        q = q[(np.abs(np.sin(q[:, 4])) > 0.2) & (np.abs(np.sin(q[:, 2])) > 0.2)]
    else:
        q = q[np.all(np.abs(np.sin(q[:, [1, 3, 5]])) > 0.2, axis=1)]
    poses = chain.fk(q, params)
    kw = {"arm_angle": ik.arm_angle_of(m, q, params=params)} if n == 7 else {}
    results = ik.solve_many(m, poses, params=params, **kw)
    found = 0
    for i, r in enumerate(results):
        assert r.status in ("ok", "singular")
        assert_reproduces(chain, r, poses[i], params)
        nominal = ik.solve_all(m, poses[i], **({"arm_angle": float(kw["arm_angle"][i])} if kw else {}))
        assert len(nominal) == 0 or not contains(r.q, nominal.q[0], tol=1e-9), "params were ignored"
        found += contains(r.q, q[i], tol=1e-6)
    assert found == len(q)


# --- bad input --------------------------------------------------------------------------------------------
def test_bad_input_raises_value_error_saying_what_is_allowed():
    m6, m7 = model("kuka_kr6_r900_2"), model("kuka_iiwa14_r820")
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        ik.solve_all(m6, np.eye(3))
    with pytest.raises(ValueError, match=r"\(k, 4, 4\)"):
        ik.solve_many(m6, np.eye(4))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="not a rigid transform"):
        ik.solve_all(m6, bad)
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ik.solve_all(m6, nan)
    with pytest.raises(ValueError, match="shape"):
        ik.solve_all(m6, np.eye(4), params=np.zeros(3))
    with pytest.raises(ValueError, match="7-joint"):
        ik.solve_all(m6, np.eye(4), arm_angle=0.5)
    with pytest.raises(ValueError, match="7-joint"):
        ik.arm_angle_intervals(m6, np.eye(4))
    with pytest.raises(ValueError, match="finite"):
        ik.solve_all(m7, np.eye(4), arm_angle=float("nan"))
    with pytest.raises(ValueError, match=r"one per pose \(shape \(2,\)\)"):
        ik.solve_many(m7, np.stack([np.eye(4)] * 2), arm_angle=np.zeros(3))
    with pytest.raises(TypeError, match="RobotModel"):
        ik.solve_all({"joints": []}, np.eye(4))


def test_solvers_live_and_die_with_their_model():
    """The solver cache holds no model alive (a daemon loads a model per run), and a copy of a
    model with other geometry gets its own solver, not the original's."""
    import gc
    import weakref

    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    q = np.radians([10.0, -80.0, 80.0, 5.0, 60.0, -20.0])
    pose = Chain(model).fk(q)
    assert any(np.allclose(s, q, atol=1e-9) for s in ik.solve_all(model, pose).q)
    ref = weakref.ref(model)
    del model
    gc.collect()
    assert ref() is None, "a solved model must not outlive its last user"

    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    ik.solve_all(model, pose)
    joints = [j.model_copy(update={"d": j.d + 5.0}) if i == 0 else j for i, j in enumerate(model.joints)]
    longer = model.model_copy(update={"joints": joints})
    pose_longer = Chain(longer).fk(q)
    assert any(np.allclose(s, q, atol=1e-9) for s in ik.solve_all(longer, pose_longer).q)
    assert not any(np.allclose(s, q, atol=1e-6) for s in ik.solve_all(model, pose_longer).q)
