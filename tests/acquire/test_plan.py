"""The plan file: schema, cross-checks with file:line:col errors, and resolution to configurations."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from acquire.plan.schema import (
    JointsFile,
    LoadedPlan,
    Plan,
    SelectionSpec,
    load_plan,
    resolve_configurations,
    resolve_plan,
)
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.plan.poses import PoseRanges, plan_poses, write_configurations
from calib.robot.transforms import pose_to_matrix
from calib.io.yamlfile import ConfigError

ROOT = Path(__file__).resolve().parents[2]
PLANS = ROOT / "fixtures" / "plans"
ROBOTS = ROOT / "fixtures" / "robots"
BAD = Path(__file__).resolve().parent / "bad_plans"
IIWA = ROBOTS / "kuka_iiwa14_r820.yaml"
KR6 = ROBOTS / "kuka_kr6_r900_2.yaml"


def minimal(**sections) -> dict:
    """A valid plan as a dict (iiwa, FRI, one NatNet sensor, one joint configuration)."""
    plan = {
        "cell": "t1",
        "robot": str(IIWA),
        "commander": {"driver": "fri", "url": "fri://127.0.0.1:30200"},
        "sensors": [{"name": "mocap", "driver": "natnet", "url": "natnet://127.0.0.1:1510",
                     "markers": {"sir": "ms:tool:sir"}, "noise_mm": 0.03}],
        "poses": {"joints": [[0, 30, 0, -60, 0, 45, 0]]},
    }
    plan.update(sections)
    return {k: v for k, v in plan.items() if v is not None}


def write(tmp_path: Path, data: dict, name: str = "plan.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def error_of(path: Path) -> str:
    """The plan's errors as ``acquire run --fake`` reports them: the plan, then its fake section
    against the simulated cell it names (``acquire.commands.fake.check_fake_section``)."""
    from acquire.commands.fake import check_fake_section

    with pytest.raises(ConfigError) as info:
        check_fake_section(load_plan(path))
    return str(info.value)


# --- the bundled plans -------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name, n_configs, n_poses, driver",
    [("example", 40, 12, "natnet"), ("paper", 162, 33, "natnet"), ("tracker", 162, 33, "tracker"),
     ("example-emscon", 162, 33, "emscon")],
)
def test_bundled_plans_load_and_resolve_to_the_documented_counts(name, n_configs, n_poses, driver):
    path = PLANS / f"{name}.yaml"
    lp = load_plan(path)
    assert lp.text == path.read_text(encoding="utf-8")
    assert lp.model.name == "KUKA LBR iiwa 14 R820"
    assert lp.model_text == IIWA.read_text(encoding="utf-8")
    assert lp.plan.sensors[0].driver == driver
    resolved = resolve_plan(lp)
    configs = resolved.configs
    assert len(configs) == n_configs
    assert len(resolved.pose_groups) == n_poses
    assert resolved.candidates == lp.plan.poses.generated.n
    assert len(resolved.dropped) == resolved.candidates - n_poses
    ids = [c.config_id for c in configs]
    assert len(set(ids)) == len(ids)
    q = np.stack([c.q_rad for c in configs])
    assert np.all(lp.model.within_limits(q))
    for c in configs:
        assert c.config_id.startswith(c.pose + "-b") and c.pose in resolved.pose_groups
        assert c.branch.startswith("GC2=")
        assert not c.q_rad.flags.writeable
    per_pose = {g: sum(c.pose == g for c in configs) for g in resolved.pose_groups}
    assert min(per_pose.values()) >= lp.plan.poses.generated.min_solutions


def test_example_plan_is_sized_for_a_quick_fake_run():
    lp = load_plan(PLANS / "example.yaml")
    seq = lp.plan.sequencing
    assert seq.speed == 0.5 and seq.samples <= 10
    assert lp.plan.commander.url == "fri://127.0.0.1:30200"
    assert lp.plan.fake is not None and lp.sim_config_path == ROOT / "fixtures" / "sim" / "default.yaml"
    assert lp.output_dir == ROOT / "runs"


def test_paper_and_tracker_plans_visit_the_same_configurations():
    paper = resolve_configurations(load_plan(PLANS / "paper.yaml"))
    tracker_lp = load_plan(PLANS / "tracker.yaml")
    tracker = resolve_configurations(tracker_lp)
    assert [c.config_id for c in paper] == [c.config_id for c in tracker]
    assert np.array_equal(np.stack([c.q_rad for c in paper]), np.stack([c.q_rad for c in tracker]))
    assert tracker_lp.plan.sequencing.on_lost_target == "reacquire"


# --- generated poses ---------------------------------------------------------------------------
def test_generated_configurations_are_plan_poses_with_stable_ids():
    lp = load_plan(PLANS / "example.yaml")
    g = lp.plan.poses.generated
    pp = plan_poses(lp.model, g.sensor_origin_mm, n=g.n, seed=g.seed,
                    ranges=PoseRanges(angle_rad=(0.0, 2 * math.pi), roll_rad=(0.0, 2 * math.pi)))
    configs = resolve_configurations(lp)
    assert len(configs) == len(pp.configurations)
    seen: dict[int, int] = {}
    for ours, theirs in zip(configs, pp.configurations):
        b = seen.get(theirs.pose, 0)
        seen[theirs.pose] = b + 1
        assert ours.config_id == f"p{theirs.pose:02d}-b{b}"
        assert ours.branch == theirs.branch
        np.testing.assert_array_equal(ours.q_rad, theirs.q)


def test_same_seed_same_configurations_other_seed_other_ones(tmp_path):
    first = resolve_configurations(load_plan(PLANS / "example.yaml"))
    again = resolve_configurations(load_plan(PLANS / "example.yaml"))
    assert first == again  # ids, poses, branches and angles
    assert len(set(first) | set(again)) == len(first)  # hashed by id
    nudged = dataclasses.replace(first[0], q_rad=first[0].q_rad + 1e-9)
    assert nudged != first[0] and hash(nudged) == hash(first[0])
    data = yaml.safe_load((PLANS / "example.yaml").read_text())
    data["robot"] = str(IIWA)
    data["output"]["folder"] = str(tmp_path / "runs")
    data["fake"]["sim_config"] = str(ROOT / "fixtures" / "sim" / "default.yaml")
    data["poses"]["generated"]["seed"] = 2
    other = resolve_configurations(load_plan(write(tmp_path, data)))
    q_first = {c.q_rad.tobytes() for c in first}
    assert not any(c.q_rad.tobytes() in q_first for c in other)


def test_generated_ranges_and_margin_are_applied(tmp_path):
    gen = {"n": 12, "seed": 4, "sensor_origin_mm": [2000, 0, 1300], "radius_mm": [400, 400],
           "height_mm": [500, 600], "angle_deg": [90, 180], "limit_margin_deg": 5, "min_solutions": 1}
    lp = load_plan(write(tmp_path, minimal(poses={"generated": gen})))
    configs = resolve_configurations(lp)
    assert configs
    chain = Chain(lp.model)
    flange = chain.fk(np.stack([c.q_rad for c in configs]))[:, :3, 3]
    assert np.allclose(np.hypot(flange[:, 0], flange[:, 1]), 400.0, atol=1e-3)
    assert np.all((flange[:, 2] > 500 - 1e-3) & (flange[:, 2] < 600 + 1e-3))
    angle = np.degrees(np.arctan2(flange[:, 1], flange[:, 0]))
    assert np.all((angle >= 90 - 1e-6) & (angle <= 180 + 1e-6))
    margin = math.radians(5)
    assert np.all(lp.model.within_limits(np.stack([c.q_rad for c in configs]), margin_rad=margin - 1e-9))


def test_extra_arm_angles_add_configurations(tmp_path):
    gen = {"n": 10, "seed": 1, "sensor_origin_mm": [2000, 0, 900]}
    base = resolve_configurations(load_plan(write(tmp_path, minimal(poses={"generated": gen}), "a.yaml")))
    more = resolve_configurations(load_plan(write(tmp_path, minimal(poses={"generated": {**gen, "arm_angles_deg": [180]}}), "b.yaml")))
    assert len(more) > len(base)
    assert any("@ψ=180.0" in c.branch for c in more)


# --- explicit poses ----------------------------------------------------------------------------
def test_cartesian_poses_give_every_solution_within_limits_one_group_each(tmp_path):
    poses = [{"xyz_mm": [500, 100, 600], "zyx_deg": [0, 90, 0], "group": "front"},
             {"xyz_mm": [450, -150, 500], "zyx_deg": [-20, 160, 10]}]
    data = minimal(robot=str(KR6), commander={"driver": "rsi", "url": "rsi://127.0.0.1:49152"},
                   poses={"cartesian": poses})
    lp = load_plan(write(tmp_path, data))
    resolved = resolve_plan(lp)
    assert resolved.pose_groups == ["front", "c01"]
    chain = Chain(lp.model)
    for i, (group, spec) in enumerate(zip(resolved.pose_groups, poses)):
        mine = [c for c in resolved.configs if c.pose == group]
        assert len(mine) >= 5  # a 6R spherical wrist: several of 8 branches plus ±360° twins
        assert [c.config_id for c in mine] == [f"{group}-b{k}" for k in range(len(mine))]
        q = np.stack([c.q_rad for c in mine])
        assert np.all(lp.model.within_limits(q))
        target = pose_to_matrix(np.array(spec["xyz_mm"], float), np.radians(spec["zyx_deg"]))
        assert np.allclose(chain.fk(q), target, atol=1e-6)


def test_cartesian_arm_angle_is_used_on_a_seven_axis_arm(tmp_path):
    from calib.ik.ik import arm_angle_of

    poses = [{"xyz_mm": [500, 100, 600], "zyx_deg": [0, 90, 0], "arm_angle_deg": 20}]
    lp = load_plan(write(tmp_path, minimal(poses={"cartesian": poses})))
    configs = resolve_configurations(lp)
    assert configs
    psi = arm_angle_of(lp.model, np.stack([c.q_rad for c in configs]))
    assert np.allclose(np.degrees(psi), 20.0, atol=1e-6)


def test_joint_lists_are_degrees_with_sequential_ids(tmp_path):
    rows = [[0, 30, 0, -60, 0, 45, 0], [10, -20, 5, 70, -5, -30, 90]]
    lp = load_plan(write(tmp_path, minimal(poses={"joints": rows})))
    configs = resolve_configurations(lp)
    assert [c.config_id for c in configs] == ["j000", "j001"]
    assert all(c.pose == "" and c.branch == "" for c in configs)
    np.testing.assert_allclose(np.stack([c.q_rad for c in configs]), np.radians(rows))


def test_a_configurations_file_keeps_its_numbers_pose_and_branch(tmp_path):
    model = load_robot_model(IIWA)
    pp = plan_poses(model, (2000, 0, 1300), n=6, seed=2)
    write_configurations(pp, tmp_path / "configs.csv")
    lp = load_plan(write(tmp_path, minimal(poses={"joints": {"file": "configs.csv"}})))
    assert isinstance(lp.plan.poses.joints, JointsFile)
    configs = resolve_configurations(lp)
    assert [c.config_id for c in configs] == [f"c{c.config:03d}" for c in pp.configurations]
    assert [c.pose for c in configs] == [f"p{c.pose:02d}" for c in pp.configurations]
    assert [c.branch for c in configs] == [c.branch for c in pp.configurations]
    np.testing.assert_allclose(np.stack([c.q_rad for c in configs]), pp.q_rad, atol=1e-7)


def test_a_configurations_file_outside_limits_is_reported_at_the_file_line(tmp_path):
    model = load_robot_model(IIWA)
    pp = plan_poses(model, (2000, 0, 1300), n=6, seed=2)
    text = write_configurations(pp, tmp_path / "configs.csv").read_text().splitlines()
    last = text[-1].split(",")
    last[4] = "150.000000"  # A2, limited to ±120°
    text[-1] = ",".join(last)
    (tmp_path / "configs.csv").write_text("\n".join(text) + "\n")
    msg = error_of(write(tmp_path, minimal(poses={"joints": {"file": "configs.csv"}})))
    assert "plan.yaml:" in msg and "poses.joints.file:" in msg
    assert f"configs.csv:{len(text)}:" in msg and "A2=150.0°" in msg


# --- selection ---------------------------------------------------------------------------------
def test_selection_keeps_m_configurations_with_their_ids_deterministically():
    lp = load_plan(PLANS / "example.yaml")
    full = resolve_configurations(lp)
    chosen_lp = dataclasses.replace(lp, plan=lp.plan.model_copy(update={"selection": SelectionSpec(m=15, seed=3)}))
    first = resolve_plan(chosen_lp)
    second = resolve_plan(chosen_lp)
    assert len(first.configs) == 15 and first.before_selection == len(full)
    assert [c.config_id for c in first.configs] == [c.config_id for c in second.configs]
    by_id = {c.config_id: c for c in full}
    for c in first.configs:
        np.testing.assert_array_equal(c.q_rad, by_id[c.config_id].q_rad)
    assert first.selection.value >= first.selection.start_value
    assert set(first.pose_groups) == {c.pose for c in first.configs}


# --- sections: defaults, valid and invalid values ----------------------------------------------
def test_defaults_are_the_documented_ones(tmp_path):
    lp = load_plan(write(tmp_path, minimal()))
    s = lp.plan.sequencing
    assert (s.speed, s.settle_window_s, s.settle_tolerance_deg, s.sensor_stable_mm, s.samples, s.retries,
            s.on_lost_target) == (0.3, 0.5, 0.01, 0.05, 20, 2, "reacquire")
    assert lp.plan.selection is None and lp.plan.fake is None
    assert (lp.plan.fit.method, lp.plan.fit.error, lp.plan.fit.joints) == ("auto", "gaussian", None)
    assert lp.output_dir == tmp_path / "runs"
    assert lp.sim_config_path.name == "default.yaml"


def test_relative_paths_are_taken_from_the_plan_folder_not_the_cwd(tmp_path, monkeypatch):
    plan_dir = tmp_path / "cell" / "plans"
    plan_dir.mkdir(parents=True)
    data = minimal(robot="../robot.yaml", output={"folder": "out"})
    (tmp_path / "cell" / "robot.yaml").write_text(IIWA.read_text())
    path = write(plan_dir, data)
    monkeypatch.chdir(tmp_path)
    lp = load_plan(path)
    assert lp.model_path == (tmp_path / "cell" / "robot.yaml").resolve()
    assert lp.output_dir == plan_dir / "out"


@pytest.mark.parametrize(
    "sections, field, fragment",
    [
        ({"cell": "a/b"}, "cell", "allowed text matching"),
        ({"commander": {"driver": "fri", "url": "udp://127.0.0.1:30200"}}, "commander.url", "allowed fri://host:port"),
        ({"commander": {"driver": "fri"}}, "commander.url", "Field required"),
        ({"sensors": []}, "sensors", "allowed at least 1 items"),
        ({"sensors": [{"name": "t", "driver": "tracker", "url": "socket://127.0.0.1:7000",
                       "markers": {"smr": "smr", "sir": "x"}, "noise_mm": 0.02}]}, "sensors.0.markers", "allowed 1"),
        ({"sensors": [{"name": "m", "driver": "natnet", "url": "natnet://127.0.0.1", "markers": {}, "noise_mm": 0.02}]},
         "sensors.0.markers", "at least 1 items"),
        ({"poses": {}}, "poses", "given: none"),
        ({"poses": {"generated": {"n": 0, "seed": 1, "sensor_origin_mm": [1, 2, 3]}}}, "poses.generated.n", "given 0; allowed [1, 10000]"),
        ({"poses": {"generated": {"n": 5, "seed": 1, "sensor_origin_mm": [1, 2]}}}, "poses.generated.sensor_origin_mm",
         "given [1, 2]; allowed 3 numbers [x, y, z]"),
        ({"poses": {"cartesian": [{"xyz_mm": [1, 2, 3], "zyx_deg": [0, 0, 0], "group": "a"},
                                  {"xyz_mm": [1, 2, 3], "zyx_deg": [0, 0, 0], "group": "a"}]}},
         "poses.cartesian.1.group", "pose groups must be unique"),
        ({"poses": {"joints": {"path": "x.csv"}}}, "poses.joints.path", "allowed keys file"),
        ({"selection": {"m": 1, "index": "O7"}}, "selection.index", "'O1', 'O2'"),
        ({"sequencing": {"samples": 0}}, "sequencing.samples", "allowed [1, 10000]"),
        ({"sequencing": {"settle_window_s": 5, "move_timeout_s": 2}}, "sequencing.settle_window_s", "move_timeout_s = 2 s"),
        ({"sequencing": {"retries": -1}}, "sequencing.retries", "allowed [0, 10]"),
        ({"output": {"folder": ""}}, "output.folder", "at least 1 characters"),
        ({"fit": {"method": "mcmc"}}, "fit.method", "allowed 'auto', 'fast' or 'paper'"),
        ({"fit": {"joints": [2, 2]}}, "fit.joints.1", "listed twice"),
        ({"fit": {"validate_fraction": 0.8}}, "fit.validate_fraction", "allowed (0, 0.5]"),
        ({"fake": {"time_scale": 0}}, "fake.time_scale", "allowed (0, 100]"),
        ({"fake": {"sim_config": "nowhere.yaml"}}, "fake.sim_config", "file not found"),
        ({"robot": str(KR6)}, "commander.driver", "allowed rsi"),
        ({"sequencing": {"speed": True}}, "sequencing.speed", "given true; allowed a finite number in (0, 1]"),
        ({"poses": {"joints": "configs.csv"}}, "poses.joints", "allowed lists of joint angles in degrees, or {file:"),
        ({"sensors": {"a": 1}}, "sensors", "allowed a list of mappings with keys name, driver, url"),
        ({"fake": {"seed": -1}}, "fake.seed", "given -1; allowed ≥ 0"),
    ],
)
def test_each_section_names_bad_values(tmp_path, sections, field, fragment):
    path = write(tmp_path, minimal(**sections))
    msg = error_of(path)
    assert f"{path}:" in msg and f": {field}: " in msg, msg
    assert fragment in msg, msg


@pytest.mark.parametrize(
    "sections, check",
    [
        ({"cell": "ok-cell_1"}, lambda p: p.cell == "ok-cell_1"),
        ({"commander": {"driver": "fri", "url": "fri://127.0.0.1:30200", "options": {"max_speed": 0.5}}},
         lambda p: p.commander.options == {"max_speed": 0.5}),
        ({"sensors": [{"name": "t", "driver": "tracker", "url": "socket://127.0.0.1:7000", "markers": {"smr": "smr"},
                       "noise_mm": 0.02, "options": {"reply_timeout": 1.0}}]},
         lambda p: p.sensors[0].markers == {"smr": "smr"} and p.sensors[0].options == {"reply_timeout": 1.0}),
        ({"selection": {"m": 1, "index": "O3", "k": 2.0}}, lambda p: (p.selection.index, p.selection.k) == ("O3", 2.0)),
        ({"sequencing": {"speed": 0.8, "on_lost_target": "ask", "lost_target_wait_s": 0}},
         lambda p: (p.sequencing.speed, p.sequencing.on_lost_target, p.sequencing.samples) == (0.8, "ask", 20)),
        ({"fit": {"method": "paper", "joints": [2, 3, 4, 5, 6, 7], "error": "student", "fix_registration": True,
                  "validate_fraction": 0.25}},
         lambda p: (p.fit.method, p.fit.joints, p.fit.error, p.fit.fix_registration, p.fit.validate_fraction)
         == ("paper", [2, 3, 4, 5, 6, 7], "student", True, 0.25)),
        ({"fake": {"seed": 3, "time_scale": 20}}, lambda p: (p.fake.seed, p.fake.time_scale, p.fake.sim_config) == (3, 20.0, None)),
    ],
)
def test_each_section_accepts_good_values(tmp_path, sections, check):
    lp = load_plan(write(tmp_path, minimal(**sections)))
    assert check(lp.plan)


def test_cross_field_checks_also_run_without_a_file():
    data = minimal(poses={"joints": [[0] * 7], "cartesian": [{"xyz_mm": [1, 2, 3], "zyx_deg": [0, 0, 0]}]})
    data["robot"] = "x.yaml"
    with pytest.raises(ValidationError, match="exactly one pose source"):
        Plan.model_validate(data)


# --- bad plans: every error names file:line:col, the field, what was given and what is allowed ---
BAD_PLANS = [
    ("speed_too_high", 11, 10, "sequencing.speed", ["less than or equal to 1", "given 1.5", "allowed (0, 1]"]),
    ("unknown_key", 11, 9, "sequencing.sped", ["Extra inputs", "given 'sped'", "allowed keys speed, settle_window_s"]),
    ("unknown_driver", 4, 21, "commander.driver", ["unknown driver", "given 'kuka'", "fri, natnet, rsi, socket, tracker"]),
    ("sensor_as_commander", 4, 21, "commander.driver", ["is a sensor, not a commander", "allowed fri, rsi"]),
    ("marker_not_on_tool", 11, 12, "sensors.0.markers.tcp", ["not on the robot's tool", "given 'tcp'", "allowed smr, sir"]),
    ("joints_wrong_length", 10, 7, "poses.joints.1", ["given 6", "allowed 7: A1, A2"]),
    ("joint_outside_limits", 10, 11, "poses.joints.1.1", ["A2 outside its limits", "given 130°", "allowed [-120, 120]°"]),
    ("robot_missing", 3, 8, "robot", ["not found", "no_such_robot.yaml", "kuka_iiwa14_r820.yaml"]),
    ("selection_too_large", 12, 6, "selection.m", ["given 5", "allowed 1…2"]),
    ("bad_on_lost_target", 11, 19, "sequencing.on_lost_target", ["given 'retry'", "'wait', 'reacquire', 'ask' or 'skip'"]),
    ("bad_cell_id", 2, 7, "cell", ["given 'Lab 1'", "^[a-z0-9_-]+$"]),
    ("two_pose_sources", 8, 3, "poses", ["exactly one", "given: generated, joints"]),
    ("bad_selector", 9, 20, "sensors.0.markers.sir", ["given 'marker7'", "'lm:<model id>:<marker id>'"]),
    ("configurations_file_missing", 8, 18, "poses.joints.file", ["not found", "no_such_configs.csv"]),
    ("fit_axis_out_of_range", 11, 18, "fit.joints.2", ["given 8", "allowed 1…7"]),
    ("duplicate_sensor_names", 7, 12, "sensors.1.name", ["must be unique", "given 'mocap' again"]),
    ("arm_angles_on_6axis", 12, 21, "poses.generated.arm_angles_deg", ["7-axis arms", "has 6 axes"]),
    ("missing_commander", 2, 1, "commander", ["Field required", "keys driver, url, options"]),
    ("range_reversed", 12, 16, "poses.generated.radius_mm", ["given [500, 200]", "low ≤ high"]),
    ("wrong_controller", 4, 21, "commander.driver", ["'sunrise' controller", "given 'rsi'", "allowed fri"]),
    ("fake_sensor_not_in_cell", 6, 12, "sensors.0.name", ["given 'camera2'", "allowed mocap, tracker"]),
    ("bad_numbers", 6, 108, "sensors.0.noise_mm", ["greater than 0", "given -0.03", "allowed (0, 100]"]),
    # inputs that would move the robot wrongly (acquire/plan/guards.py)
    ("sensor_origin_in_metres", 11, 23, "poses.generated.sensor_origin_mm",
     ["looks like metres", "given [2, 0, 1.3]", "allowed mm", "e.g. [2000, 0, 1300]"]),
    ("joints_in_radians", 9, 5, "poses.joints",
     ["look like radians", "given [0, 0.5236, 0, -1.0472, 0, 0.7854, 0]", "allowed degrees, e.g. [0, 30, 0, -60, 0, 45, 0]"]),
    ("joint_inside_commander_margin", 11, 11, "poses.joints.1.1",
     ["A2 within the fri commander's 0.5° margin", "given 119.8°", "allowed [-119.5, 119.5]°"]),
    ("tool_in_metres", 3, 8, "robot",
     ["units are wrong", "tool_in_metres.robot.yaml:18:24: tool.markers.1.xyz: marker 'sir'", "look like metres",
      "given [-0.1, 0, 0.02]", "e.g. [-100, 0, 20]"]),
]


@pytest.mark.parametrize("name, line, col, field, fragments", BAD_PLANS, ids=[b[0] for b in BAD_PLANS])
def test_bad_plans_name_file_line_column_field_given_and_allowed(name, line, col, field, fragments):
    path = BAD / f"{name}.yaml"
    msg = error_of(path)
    assert msg.startswith(f"{path}:{line}:{col}: {field}: "), msg
    first = msg.splitlines()[0]
    for fragment in fragments:
        assert fragment in msg, (fragment, msg)
    assert "given" in first and "allowed" in first, first


def test_every_problem_of_a_file_is_listed_in_line_order():
    path = BAD / "bad_numbers.yaml"
    lines = error_of(path).splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"{path}:6:108: sensors.0.noise_mm:")
    assert lines[1].startswith(f"{path}:11:12: sequencing.samples:") and "given 'many'" in lines[1]
    assert "allowed an integer in [1, 10000]" in lines[1]


@pytest.mark.parametrize(
    "name, line, col, field, fragment",
    [
        ("selection_exceeds_generated", 11, 6, "selection.m", "given 500; allowed 1…2"),
        ("cartesian_unreachable", 10, 7, "poses.cartesian.1", "out of reach"),
    ],
)
def test_problems_found_while_resolving_point_at_the_plan_line(name, line, col, field, fragment):
    path = BAD / f"{name}.yaml"
    lp = load_plan(path)  # the schema and cross-checks pass; the poses decide
    with pytest.raises(ConfigError) as info:
        resolve_configurations(lp)
    msg = str(info.value)
    assert msg.startswith(f"{path}:{line}:{col}: {field}: ") and fragment in msg, msg


def test_a_robot_model_with_errors_is_reported_under_the_robot_line(tmp_path):
    bad_robot = tmp_path / "robot.yaml"
    bad_robot.write_text(IIWA.read_text().replace("limits: [-120, 120], max_speed: 85", "limits: [120, -120], max_speed: 85"))
    path = write(tmp_path, minimal(robot="robot.yaml"))
    msg = error_of(path)
    assert msg.startswith(f"{path}:2:8: robot: the robot model is not valid")
    assert f"{bad_robot}:" in msg and "joints.1.limits" in msg


def test_yaml_syntax_errors_and_non_mappings_name_the_line(tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("cell: a\nrobot: [unclosed\n")
    assert error_of(broken).startswith(f"{broken}:")
    listed = tmp_path / "list.yaml"
    listed.write_text("- cell: a\n")
    msg = error_of(listed)
    assert msg.startswith(f"{listed}:1:1:") and "allowed keys cell, robot" in msg


def test_loaded_plan_error_helper_points_at_a_field():
    lp: LoadedPlan = load_plan(PLANS / "example.yaml")
    err = lp.error(("sequencing", "speed"), "too fast for this cell (given 0.5; allowed ≤ 0.3)")
    text = (PLANS / "example.yaml").read_text().splitlines()
    line = next(i for i, t in enumerate(text, 1) if t.strip().startswith("speed:"))
    assert str(err).startswith(f"{PLANS / 'example.yaml'}:{line}:10: sequencing.speed: too fast")


def test_the_format_documented_in_the_module_docstring_is_a_valid_plan(tmp_path):
    import acquire.plan.schema

    block = acquire.plan.schema.__doc__.split("commented example)::\n\n", 1)[1].split("\n\nErrors:", 1)[0]
    data = yaml.safe_load("\n".join(line[4:] for line in block.splitlines()))
    # socket: the alternative to poses (socket calibration), documented commented out
    assert set(data) | {"socket"} == set(Plan.model_fields)
    assert "    # socket:" in block
    data["robot"] = str(IIWA)  # the documented paths are relative to fixtures/plans
    data["fake"]["sim_config"] = str(ROOT / "fixtures" / "sim" / "default.yaml")
    lp = load_plan(write(tmp_path, data))
    resolved = resolve_plan(lp)
    assert len(resolved.configs) == data["selection"]["m"] and resolved.before_selection > data["selection"]["m"]


@pytest.mark.parametrize("selector", ["sk:robot:link6", "sk:3:7", "ms:robot:sir", "rb:tool", "lm:2:1"])
def test_natnet_selectors_for_bones_and_asset_markers_are_accepted(tmp_path, selector):
    sensors = [{"name": "mocap", "driver": "natnet", "url": "natnet://127.0.0.1:1510",
                "markers": {"sir": selector}, "noise_mm": 0.03}]
    lp = load_plan(write(tmp_path, minimal(sensors=sensors)))
    assert lp.plan.sensors[0].markers == {"sir": selector}


@pytest.mark.parametrize("selector", ["sk:robot", "sk::link6", "sk:70000:1", "sk:robot:", "bone:robot:link6"])
def test_bad_natnet_bone_selectors_name_the_marker_given_and_allowed(tmp_path, selector):
    sensors = [{"name": "mocap", "driver": "natnet", "url": "natnet://127.0.0.1:1510",
                "markers": {"sir": selector}, "noise_mm": 0.03}]
    msg = error_of(write(tmp_path, minimal(sensors=sensors)))
    assert "sensors.0.markers.sir" in msg and f"given {selector!r}" in msg, msg
    assert "'sk:<skeleton id or name>:<bone id or name>'" in msg and "'ms:<asset name>:<marker name>'" in msg, msg


# --- laser trackers: air and reflector ------------------------------------------------------------
def _tracker_sensor(driver: str = "emscon", **extra) -> dict:
    url = {"emscon": "emscon://127.0.0.1:700", "tracker": "socket://127.0.0.1:7000"}.get(driver, "natnet://127.0.0.1:1510")
    return {"name": "tracker", "driver": driver, "url": url, "markers": {"smr": "smr"}, "noise_mm": 0.02, **extra}


@pytest.mark.parametrize("driver", ["emscon", "tracker"])
def test_tracker_air_and_reflector_reach_the_driver_the_same_way(tmp_path, driver):
    env = {"temperature_c": 21.5, "pressure_hpa": 1002.0, "humidity_pct": 40}
    lp = load_plan(write(tmp_path, minimal(sensors=[_tracker_sensor(
        driver, environment=env, reflector={"type": "RRR15", "offset_mm": 19.05})])))
    s = lp.plan.sensors[0]
    assert s.environment.driver_value() == env
    assert s.reflector.model_dump() == {"type": "RRR15", "offset_mm": 19.05}
    station = load_plan(write(tmp_path, minimal(sensors=[_tracker_sensor(driver, environment={"source": "station"})]),
                              "station.yaml"))
    assert station.plan.sensors[0].environment.driver_value() == {"source": "station"}


@pytest.mark.parametrize(
    "sensor, fragments",
    [
        (_tracker_sensor(environment={"temperature_c": 21.5}), ["sensors.0.environment", "pressure_hpa, humidity_pct missing"]),
        (_tracker_sensor(environment={"source": "station", "temperature_c": 20}), ["source station takes no"]),
        (_tracker_sensor(environment={"temperature_c": 95, "pressure_hpa": 1000, "humidity_pct": 5}),
         ["environment.temperature_c", "given 95"]),
        (_tracker_sensor("natnet", reflector={"type": "RRR15"}) | {"markers": {"sir": "ms:tool:sir"}},
         ["sensors.0.reflector", "applies to laser trackers", "allowed drivers tracker, emscon"]),
        (_tracker_sensor(url="socket://127.0.0.1:700"), ["sensors.0.url", "emscon://"]),
        (_tracker_sensor(markers={"smr": "smr", "sir": "sir"}), ["sensors.0.markers", "one reflector"]),
    ],
)
def test_bad_tracker_settings_name_the_field(tmp_path, sensor, fragments):
    text = error_of(write(tmp_path, minimal(sensors=[sensor])))
    for fragment in fragments:
        assert fragment in text, (fragment, text)
