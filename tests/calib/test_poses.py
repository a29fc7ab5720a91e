"""The paper's pose plan (calib.plan.poses): Latin-hypercube sampling, aiming (eqs. 2–5), every IK
solution per pose with limit and FK filtering, dropped poses with reasons, the configurations
file."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.plan.poses import (
    PoseRanges,
    aim_rotations,
    candidate_poses,
    format_configurations,
    latin_hypercube,
    plan_poses,
    read_configurations,
    write_configurations,
)
from calib.robot.transforms import euler_zyx_to_matrix, rot_z
from calib.io.yamlfile import ConfigError

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
SENSOR = np.array([1500.0, 200.0, 600.0])


@pytest.fixture(scope="module")
def kr6():
    return load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")


@pytest.fixture(scope="module")
def iiwa():
    return load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml")


@dataclass(frozen=True)
class _Solutions:
    q: np.ndarray
    branch: list
    status: str
    message: str


@pytest.fixture(scope="module")
def solver():
    from calib.ik import ik

    return ik


# --- sampling and aiming -------------------------------------------------------------------
def test_latin_hypercube_puts_one_sample_in_every_stratum_of_every_dimension():
    n = 37
    ranges = PoseRanges(radius_mm=(200, 500), height_mm=(400, 800), angle_rad=(0, 2 * math.pi), roll_rad=(-1, 1))
    s = latin_hypercube(n, ranges, seed=3)
    lo, hi = ranges.bounds()
    strata = np.floor((s - lo) / (hi - lo) * n).astype(int)
    for d in range(4):
        assert sorted(strata[:, d]) == list(range(n)), f"dimension {d} is not a Latin hypercube"


def test_same_seed_same_candidates_other_seed_other_candidates():
    a = candidate_poses(20, SENSOR, seed=7)
    b = candidate_poses(20, SENSOR, seed=7)
    c = candidate_poses(20, SENSOR, seed=8)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert np.abs(a.samples - c.samples).max() > 1.0


def test_candidates_lie_in_the_paper_volume_and_aim_their_z_axis_at_the_sensor():
    c = candidate_poses(60, SENSOR, seed=1)
    xyz = c.xyz_mm
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    assert np.all((r >= 200 - 1e-9) & (r <= 500 + 1e-9))
    assert np.all((xyz[:, 2] >= 400) & (xyz[:, 2] <= 800))
    to_sensor = SENSOR - xyz
    to_sensor /= np.linalg.norm(to_sensor, axis=1, keepdims=True)
    np.testing.assert_allclose(c.poses[:, :3, 2], to_sensor, atol=1e-12)  # eq. 2
    rot = c.poses[:, :3, :3]
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_x_axis_is_z_cross_base_z_before_the_extra_roll_and_the_roll_is_the_sampled_one():
    c = candidate_poses(25, SENSOR, seed=2)
    rot = c.poses[:, :3, :3]
    roll = c.samples[:, 3]
    unrolled = rot @ rot_z(-roll)
    z = rot[:, :, 2]
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    np.testing.assert_allclose(unrolled[:, :, 0], x, atol=1e-12)  # eq. 3
    np.testing.assert_allclose(unrolled[:, :, 1], np.cross(z, x), atol=1e-12)  # eq. 4
    # eq. 5: the roll is the angle from the unrolled x to the final x about z.
    got = np.arctan2(np.einsum("ij,ij->i", np.cross(unrolled[:, :, 0], rot[:, :, 0]), z), np.einsum("ij,ij->i", unrolled[:, :, 0], rot[:, :, 0]))
    np.testing.assert_allclose(np.mod(got - roll + np.pi, 2 * np.pi) - np.pi, 0.0, atol=1e-12)


def test_zyx_euler_angles_rebuild_each_rotation():
    c = candidate_poses(30, SENSOR, seed=4)
    zyx = c.zyx_rad
    np.testing.assert_allclose(euler_zyx_to_matrix(zyx[:, 0], zyx[:, 1], zyx[:, 2]), c.poses[:, :3, :3], atol=1e-12)


@pytest.mark.parametrize("lateral", [0.0, 1e-7])
def test_z_parallel_to_base_z_falls_back_to_another_axis(lateral):
    # Sensor straight above the pose (and a hair off it): z × Z_base vanishes.
    p = np.array([[0.0, 0.0, 500.0]])
    rot = aim_rotations(p, [lateral, 0.0, 2000.0], np.array([0.0]))[0]
    assert np.all(np.isfinite(rot))
    np.testing.assert_allclose(rot[:, 2], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rot[:, 0], np.cross([0, 0, 1], [1, 0, 0]), atol=1e-9)  # z × fallback X


def test_sensor_straight_below_is_handled_too():
    rot = aim_rotations(np.array([[0.0, 0.0, 500.0]]), [0.0, 0.0, -100.0], np.array([0.3]))[0]
    np.testing.assert_allclose(rot[:, 2], [0, 0, -1], atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)


def test_a_pose_on_the_sensor_origin_is_refused():
    ranges = PoseRanges(radius_mm=(300, 300), height_mm=(500, 500), angle_rad=(0, 0), roll_rad=(0, 1))
    with pytest.raises(ValueError, match="coincide with the sensor origin"):
        candidate_poses(3, [300.0, 0.0, 500.0], seed=1, ranges=ranges)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"radius_mm": (500, 200)}, "radius_mm: low 500.0 must not exceed high 200.0"),
        ({"height_mm": (1, float("nan"))}, "height_mm must be finite"),
        ({"radius_mm": (-10, 200)}, "radius_mm must be ≥ 0"),
        ({"roll_rad": (1, 2, 3)}, "roll_rad must be \\(low, high\\)"),
    ],
)
def test_bad_ranges_say_which_and_what(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PoseRanges(**kwargs)


@pytest.mark.parametrize("n", [0, -3, 2.5])
def test_bad_candidate_count_is_refused(n):
    with pytest.raises(ValueError, match="positive integer"):
        candidate_poses(n, SENSOR, seed=1)


@pytest.mark.parametrize("origin", [[1, 2], [1, 2, float("inf")], "abc"])
def test_bad_sensor_origin_is_refused(origin):
    with pytest.raises(ValueError, match="sensor origin must be three finite numbers"):
        candidate_poses(5, origin, seed=1)


# --- the plan with the real IK ------------------------------------------------------------
def _check_plan(model, plan, min_solutions=2):
    chain = Chain(model)
    assert sorted(plan.valid + [d.pose for d in plan.dropped]) == list(range(plan.candidates.n))
    assert [c.config for c in plan.configurations] == list(range(len(plan.configurations)))
    q = plan.q_rad
    assert np.all(model.within_limits(q))
    poses = plan.candidates.poses[[c.pose for c in plan.configurations]]
    t = chain.fk(q)
    np.testing.assert_allclose(t[:, :3, 3], poses[:, :3, 3], atol=1e-3)
    np.testing.assert_allclose(t[:, :3, :3], poses[:, :3, :3], atol=1e-6)
    counts = np.bincount([c.pose for c in plan.configurations], minlength=plan.candidates.n)
    assert np.all(counts[plan.valid] >= min_solutions)
    assert np.all(counts[[d.pose for d in plan.dropped]] == 0)
    # Distinct configurations per pose.
    for k in plan.valid:
        qs = q[[i for i, c in enumerate(plan.configurations) if c.pose == k]]
        diff = qs[:, None, :] - qs[None, :, :]
        gaps = np.abs(np.mod(diff + np.pi, 2 * np.pi) - np.pi).max(-1) + np.eye(len(qs)) * 10
        assert gaps.min() > 1e-6


def test_kr6_plan_keeps_every_feasible_ik_solution_and_reports_the_rest(kr6, solver):
    plan = plan_poses(kr6, [900.0, -300.0, 700.0], n=20, seed=1, solver=solver)
    _check_plan(kr6, plan)
    assert len(plan.valid) >= 5, [d.reason for d in plan.dropped]
    assert len(plan.configurations) > 2 * len(plan.valid)  # a 6R spherical wrist has up to 8
    for d in plan.dropped:
        assert d.reason


def test_iiwa_plan_at_the_picked_arm_angle(iiwa, solver):
    plan = plan_poses(iiwa, SENSOR, n=12, seed=1, solver=solver)
    _check_plan(iiwa, plan)
    assert len(plan.valid) >= 4, [d.reason for d in plan.dropped]
    assert all(len(plan.arm_angles_rad[k]) == 1 for k in plan.valid)
    for d in plan.dropped:  # a pose no arm angle can serve says so
        assert plan.arm_angles_rad[d.pose] or d.reason.startswith("no feasible IK solution (no arm angle: ")


def test_same_seed_same_plan(kr6, solver):
    a = plan_poses(kr6, [900.0, -300.0, 700.0], n=8, seed=5, solver=solver)
    b = plan_poses(kr6, [900.0, -300.0, 700.0], n=8, seed=5, solver=solver)
    assert a.valid == b.valid and [d.reason for d in a.dropped] == [d.reason for d in b.dropped]
    np.testing.assert_array_equal(a.q_rad, b.q_rad)


def test_limit_margin_keeps_configurations_inside_the_shrunk_limits(kr6, solver):
    margin = math.radians(15)
    plan = plan_poses(kr6, [900.0, -300.0, 700.0], n=10, seed=1, solver=solver, limit_margin_rad=margin)
    assert np.all(kr6.within_limits(plan.q_rad, margin_rad=margin))
    loose = plan_poses(kr6, [900.0, -300.0, 700.0], n=10, seed=1, solver=solver)
    assert len(plan.configurations) <= len(loose.configurations)


def test_arm_angles_only_for_seven_axis_arms(kr6, solver):
    with pytest.raises(ValueError, match="7-joint arms"):
        plan_poses(kr6, SENSOR, n=3, seed=1, solver=solver, extra_arm_angles_rad=[0.5])


def test_bad_min_solutions_and_margin_are_refused(kr6, solver):
    with pytest.raises(ValueError, match="min_solutions"):
        plan_poses(kr6, SENSOR, n=3, seed=1, solver=solver, min_solutions=0)
    with pytest.raises(ValueError, match="limit_margin_rad"):
        plan_poses(kr6, SENSOR, n=3, seed=1, solver=solver, limit_margin_rad=-0.1)


# --- plan logic with a doctored solver --------------------------------------------------------
class _Doctored:
    """The real IK, with its answers edited per pose to exercise every drop path."""

    def __init__(self, inner, model, edit):
        self.inner, self.model, self.edit, self.calls = inner, model, edit, []

    def pick_arm_angle(self, model, pose, **kw):
        return self.inner.pick_arm_angle(model, pose, **kw)

    def solve_all(self, model, pose, **kw):
        self.calls.append(kw)
        sol = self.inner.solve_all(model, pose, **kw)
        return self.edit(len(self.calls) - 1, sol, kw)


def _hopeless(model, q):
    """Rows of q (k, n) that no whole turn of any joint brings inside the limits."""
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    turns = 2 * np.pi * np.arange(-2, 3)[:, None, None]
    fits = ((q + turns >= lo) & (q + turns <= hi)).any(axis=0)  # (k, n)
    return ~fits.all(axis=1)


def _turned(q):
    out = q.copy()
    out[5] += -2 * np.pi if out[5] > 0 else 2 * np.pi
    return out


def _edit(index, sol, model, targets):
    """Edit the IK answer for the poses in ``targets`` = (none, hopeless, wrong, twin)."""
    q, branch = np.asarray(sol.q).reshape(-1, model.n_joints), list(sol.branch)
    if index == targets[0]:  # nothing at all
        return _Solutions(np.zeros((0, model.n_joints)), [], "unreachable", "wrist centre 2.1 m away")
    if index not in targets:
        return sol
    ok = np.flatnonzero(model.within_limits(q))
    good, label = q[ok[0]], branch[ok[0]]
    if index == targets[1]:  # one feasible solution and one that no whole turn saves
        bad = np.flatnonzero(_hopeless(model, q))[0]
        return _Solutions(np.stack([good, q[bad]]), [label, branch[bad]], "ok", "")
    if index == targets[2]:  # one good, one that misses the pose
        return _Solutions(np.stack([good, good + 0.01]), [label, "wrong"], "ok", "")
    # one good and its twin with A6 a whole turn further
    return _Solutions(np.stack([good, _turned(good)]), [label, "twin"], "ok", "")


def test_every_drop_reason_is_reported(kr6, solver):
    origin = [900.0, -300.0, 700.0]
    honest = plan_poses(kr6, origin, n=16, seed=1, solver=solver)
    first_q = {c.pose: c.q for c in reversed(honest.configurations)}  # first config per pose
    answers = {k: solver.solve_all(kr6, honest.candidates.poses[k], within_limits=False) for k in honest.valid}
    with_hopeless = [k for k in honest.valid if _hopeless(kr6, answers[k].q).any()]
    twinable = [k for k in honest.valid if kr6.within_limits(_turned(first_q[k]))]
    assert with_hopeless and twinable and len(honest.valid) >= 4
    t1 = with_hopeless[0]
    t3 = next(k for k in twinable if k != t1)
    t0, t2 = [k for k in honest.valid if k not in (t1, t3)][:2]
    targets = (t0, t1, t2, t3)
    doctored = _Doctored(solver, kr6, lambda i, s, kw: _edit(i, s, kr6, targets))
    plan = plan_poses(kr6, origin, n=16, seed=1, solver=doctored)
    reasons = {d.pose: d.reason for d in plan.dropped}
    assert reasons[t0] == "no feasible IK solution (unreachable: wrist centre 2.1 m away)"
    assert re.fullmatch(r"1 feasible of 2 IK solutions \(need ≥ 2\); 1 outside joint limits: .+: A\d=-?[\d.]+° "
                        r"outside \[-?[\d.]+, -?[\d.]+\]°", reasons[t1]), reasons[t1]
    assert reasons[t2] == "1 feasible of 2 IK solutions (need ≥ 2); 1 failed the FK check"
    assert reasons[t3] == "1 feasible of 2 IK solutions (need ≥ 2); 1 duplicates (equal up to whole turns)"
    assert set(plan.valid) == set(honest.valid) - set(targets)
    assert all(kw.get("within_limits") is False for kw in doctored.calls)
    _check_plan(kr6, plan)
    # With min_solutions=1 they survive with exactly their one good configuration.
    lenient = plan_poses(kr6, origin, n=16, seed=1, min_solutions=1,
                         solver=_Doctored(solver, kr6, lambda i, s, kw: _edit(i, s, kr6, targets)))
    assert set(targets[1:]) <= set(lenient.valid)
    assert sum(c.pose == t3 for c in lenient.configurations) == 1
    # Asked for, whole-turn twins are planned as separate configurations.
    twins = plan_poses(kr6, origin, n=16, seed=1, whole_turn_twins=True,
                       solver=_Doctored(solver, kr6, lambda i, s, kw: _edit(i, s, kr6, targets)))
    assert t3 in twins.valid
    labels = [c.branch for c in twins.configurations if c.pose == t3]
    assert len(labels) == 2 and any(re.search(r" A6[+-]360$", b) for b in labels)


def test_angles_are_turned_into_the_limits_when_a_whole_turn_allows(kr6, solver):
    """KR 6 A2 has limits [−190°, 45°]: a wrapped 175° must be planned as −185°."""
    plan = plan_poses(kr6, [900.0, -300.0, 700.0], n=40, seed=2, solver=solver)
    q = plan.q_rad
    assert np.all(kr6.within_limits(q))
    assert np.all(np.abs(q) <= np.radians(190) + 1e-12)
    # Every planned angle is the one nearest zero among its whole-turn equivalents that fit.
    for row in q:
        for j, x in enumerate(row):
            lo, hi = kr6.lower_limits_rad[j], kr6.upper_limits_rad[j]
            others = [x + 2 * np.pi * k for k in (-2, -1, 1, 2) if lo <= x + 2 * np.pi * k <= hi]
            assert all(abs(x) <= abs(o) for o in others)


def test_extra_arm_angles_are_solved_and_labelled(iiwa, solver):
    doctored = _Doctored(solver, iiwa, lambda i, s, kw: s)
    plan = plan_poses(iiwa, SENSOR, n=6, seed=1, solver=doctored, extra_arm_angles_rad=[0.6, -0.6])
    psis = [kw["arm_angle"] for kw in doctored.calls]
    assert psis == [psi for k in range(6) for psi in plan.arm_angles_rad[k]]
    assert all(plan.arm_angles_rad[k][-2:] == [0.6, -0.6] for k in range(6))
    labels = {c.branch.rsplit("@ψ=", 1)[1] for c in plan.configurations}
    assert {"34.4", "-34.4"} <= labels
    _check_plan(iiwa, plan)
    single = plan_poses(iiwa, SENSOR, n=6, seed=1, solver=solver)
    assert len(plan.configurations) > len(single.configurations)


# --- configurations file ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def kr6_plan(kr6, solver):
    return plan_poses(kr6, [900.0, -300.0, 700.0], n=10, seed=3, solver=solver)


def test_configurations_file_round_trips(kr6, kr6_plan, tmp_path):
    path = write_configurations(kr6_plan, tmp_path / "c.csv")
    back = read_configurations(path, kr6)
    assert back.robot == kr6.name and back.seed == 3
    np.testing.assert_allclose(back.sensor_origin_mm, [900.0, -300.0, 700.0])
    np.testing.assert_allclose(back.q_rad, kr6_plan.q_rad, atol=math.radians(1e-6))
    assert [(c.config, c.pose, c.branch) for c in back.configurations] == [
        (c.config, c.pose, c.branch) for c in kr6_plan.configurations
    ]
    text = path.read_text(encoding="utf-8").splitlines()
    assert text[0] == "# remaster configurations v1"
    assert "config,pose,branch,q1,q2,q3,q4,q5,q6" in text
    assert sum(line.startswith("# pose ") for line in text) == len(kr6_plan.valid)


def _break(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new, 1)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda t: _break(t, "# seed: 3\n", ""), r"c.csv: missing header comment '# seed: ...'"),
        (lambda t: _break(t, "# seed: 3", "# seed: three"), r"c.csv: seed must be an integer, given 'three'"),
        (lambda t: _break(t, "config,pose,branch,q1", "cfg,pose,branch,q1"), r"c.csv:\d+: column header must be"),
        (lambda t: _break(t, ",q6\n", "\n"), r"c.csv:\d+: file has 5 joint columns, KUKA KR 6 R900-2 has 6 joints"),
    ],
)
def test_bad_configurations_files_name_file_and_problem(kr6_plan, kr6, tmp_path, mutate, match):
    path = tmp_path / "c.csv"
    path.write_text(mutate(format_configurations(kr6_plan)), encoding="utf-8")
    with pytest.raises(ConfigError, match=match):
        read_configurations(path, kr6)


def test_bad_rows_name_their_line(kr6_plan, kr6, tmp_path):
    text = format_configurations(kr6_plan).splitlines()
    head = next(i for i, line in enumerate(text) if line.startswith("config,"))
    row = text[head + 2].split(",")
    cases = {
        "outside the joint limits: A5=150.0°": row[:7] + ["150.0"] + row[8:],
        "joint angles must be numbers": row[:3] + ["x"] + row[4:],
        "expected 9 fields, given 8": row[:-1],
    }
    for match, bad in cases.items():
        lines = list(text)
        lines[head + 2] = ",".join(bad)
        path = tmp_path / "c.csv"
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        with pytest.raises(ConfigError, match=f"c.csv:{head + 3}: .*{match}"):
            read_configurations(path, kr6)


def test_missing_file_says_so(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        read_configurations(tmp_path / "nope.csv")


def test_reading_without_a_model_skips_model_checks(kr6_plan, tmp_path):
    path = write_configurations(replace(kr6_plan), tmp_path / "c.csv")
    back = read_configurations(path)
    assert back.q_rad.shape == kr6_plan.q_rad.shape
