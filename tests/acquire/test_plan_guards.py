"""Plan-time guards: units plausibility and the commanders' limit margins, before anything connects."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from acquire.plan.schema import load_plan, resolve_plan
from calib.io.yamlfile import ConfigError
from drivers.errors import LimitError
from drivers.kuka_fri.commander import FriCommander
from drivers.kuka_rsi.commander import RsiCommander
from drivers.protocols import JointLimits

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = ROOT / "fixtures" / "robots"
IIWA = ROBOTS / "kuka_iiwa14_r820.yaml"
KR6 = ROBOTS / "kuka_kr6_r900_2.yaml"
HOME = [0, 30, 0, -60, 0, 45, 0]


def plan_file(tmp_path: Path, poses: dict, *, robot: Path = IIWA, commander: dict | None = None,
              noise_mm: float = 0.03) -> Path:
    doc = {
        "cell": "t1",
        "robot": str(robot),
        "commander": commander or {"driver": "fri", "url": "fri://127.0.0.1:30200"},
        "sensors": [{"name": "mocap", "driver": "natnet", "url": "natnet://127.0.0.1:1510",
                     "markers": {"sir": "ms:tool:sir"}, "noise_mm": noise_mm}],
        "poses": poses,
        "output": {"folder": str(tmp_path / "runs")},
    }
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def refused(path: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load_plan(path)
    return str(info.value)


# --- the commander's margin, asked of the driver -------------------------------------------------
def test_drivers_report_the_margin_their_check_target_keeps():
    from calib.robot.model import load_robot_model

    iiwa = JointLimits.from_model(load_robot_model(IIWA))
    for cls in (FriCommander, RsiCommander):
        margin = cls.limit_margin_for()
        assert margin == pytest.approx(math.radians(0.5))
        assert cls.limit_margin_for({"limit_margin_rad": 0.03}) == 0.03
        cmd = cls(iiwa)  # built, not connected: no socket is opened by the constructor
        assert cmd.limit_margin_rad == margin
        with pytest.raises(ValueError, match="limit_margin_rad"):
            cls.limit_margin_for({"limit_margin_rad": -1})


@pytest.mark.parametrize("a2", [119.3, 119.5, 119.50001, 119.6, 119.8, 120.0, -119.5, -119.7])
def test_the_plan_check_and_the_fri_commander_agree_at_the_margin(tmp_path, a2):
    """Whatever the plan accepts the commander accepts, and the other way round."""
    from calib.robot.model import load_robot_model

    row = [0, a2, 0, -60, 0, 45, 0]
    cmd = FriCommander(JointLimits.from_model(load_robot_model(IIWA)))
    try:
        cmd.check_target(np.radians(row), 0.5)
        commander_ok = True
    except LimitError:
        commander_ok = False
    path = plan_file(tmp_path, {"joints": [HOME, row]})
    try:
        load_plan(path)
        plan_ok = True
    except ConfigError as exc:
        plan_ok = False
        assert f"{path}:" in str(exc) and "poses.joints.1.1" in str(exc)
    assert plan_ok == commander_ok
    assert plan_ok == (abs(a2) <= 119.5)


def test_the_margin_follows_the_commanders_options(tmp_path):
    """A plan that sets the driver's margin is checked against that margin, not a constant."""
    wide = {"driver": "fri", "url": "fri://127.0.0.1:30200", "options": {"limit_margin_rad": math.radians(2)}}
    msg = refused(plan_file(tmp_path, {"joints": [[0, 118.5, 0, -60, 0, 45, 0]]}, commander=wide))
    assert "fri commander's 2° margin" in msg and "allowed [-118, 118]°" in msg
    none = {"driver": "fri", "url": "fri://127.0.0.1:30200", "options": {"limit_margin_rad": 0}}
    load_plan(plan_file(tmp_path, {"joints": [[0, 119.8, 0, -60, 0, 45, 0]]}, commander=none))


def test_the_rsi_commanders_margin_is_checked_too(tmp_path):
    rsi = {"driver": "rsi", "url": "rsi://0.0.0.0:49152"}
    row = [0, -90, 90, 0, 0, 0]
    load_plan(plan_file(tmp_path, {"joints": [row]}, robot=KR6, commander=rsi))
    from calib.robot.model import load_robot_model

    lo, hi = load_robot_model(KR6).joints[0].limits
    row = [hi - 0.2, -90, 90, 0, 0, 0]
    msg = refused(plan_file(tmp_path, {"joints": [row]}, robot=KR6, commander=rsi))
    assert "poses.joints.0.0" in msg and "A1 within the rsi commander's 0.5° margin" in msg


def test_a_configurations_file_inside_the_margin_is_refused_naming_the_config(tmp_path):
    csv = tmp_path / "configs.csv"
    csv.write_text("# robot: KUKA LBR iiwa 14 R820\n# seed: 0\n# sensor_origin_mm: 2000,0,1300\n"
                   "config,pose,branch,q1,q2,q3,q4,q5,q6,q7\n"
                   "1,1,,0,30,0,-60,0,45,0\n"
                   "2,1,,0,-119.9,0,-60,0,45,0\n")
    msg = refused(plan_file(tmp_path, {"joints": {"file": str(csv)}}))
    assert "poses.joints.file" in msg and "config 2: A2 within the fri commander's 0.5° margin" in msg


def test_generated_poses_keep_every_configuration_the_commander_accepts():
    """The paper's plan used to hold three configurations within 0.5° of a limit (refused mid-run)."""
    lp = load_plan(ROOT / "fixtures" / "plans" / "paper.yaml")
    cmd = FriCommander(JointLimits.from_model(lp.model))
    resolved = resolve_plan(lp)
    for c in resolved.configs:
        cmd.check_target(c.q_rad, lp.plan.sequencing.speed)  # raises LimitError if it would refuse
    assert len(resolved.configs) == 162


def test_cartesian_poses_drop_solutions_inside_the_margin(tmp_path):
    """A KR 6 pose whose 12 IK solutions include two with A4 at 184.8° (limit 185°): the RSI
    commander would refuse those two, so the plan visits the other ten."""
    pose = {"xyz_mm": [552.881313577008, -207.37167348343985, 453.4071004523263],
            "zyx_deg": [-166.96616348018745, -1.9224070962364483, -176.865482870011]}
    rsi = {"driver": "rsi", "url": "rsi://0.0.0.0:49152"}
    lp = load_plan(plan_file(tmp_path, {"cartesian": [pose]}, robot=KR6, commander=rsi))
    configs = resolve_plan(lp).configs
    cmd = RsiCommander(JointLimits.from_model(lp.model))
    for c in configs:
        cmd.check_target(c.q_rad, 0.3)
    assert len(configs) == 10
    assert [c.config_id for c in configs] == [f"c00-b{k}" for k in range(10)]
    a4 = np.degrees([c.q_rad[3] for c in configs])
    assert np.all(np.abs(a4) < 184.5) and np.any(np.abs(a4) > 184)  # 184.226° stays: 0.77° inside


# --- units -------------------------------------------------------------------------------------
GEN = {"n": 20, "seed": 1, "sensor_origin_mm": [2000, 0, 1300]}


@pytest.mark.parametrize(
    "poses, noise_mm, field, fragments",
    [
        ({"generated": {**GEN, "sensor_origin_mm": [2.0, 0.0, 1.3]}}, 0.03, "poses.generated.sensor_origin_mm",
         ["looks like metres", "e.g. [2000, 0, 1300]"]),
        ({"generated": {**GEN, "radius_mm": [0.2, 0.5]}}, 0.03, "poses.generated.radius_mm",
         ["looks like metres", "e.g. [200, 500]"]),
        ({"generated": {**GEN, "angle_deg": [0, 6.2832]}}, 0.03, "poses.generated.angle_deg",
         ["looks like radians", "e.g. [0, 360]"]),
        ({"cartesian": [{"xyz_mm": [0.5, 0.0, 0.6], "zyx_deg": [0, 90, 0]}]}, 0.03, "poses.cartesian.0.xyz_mm",
         ["looks like metres", "e.g. [500, 0, 600]"]),
        ({"cartesian": [{"xyz_mm": [500, 0, 600], "zyx_deg": [0, 1.5708, 0]}]}, 0.03, "poses.cartesian.0.zyx_deg",
         ["looks like radians", "e.g. [0, 90, 0]"]),
        ({"joints": [HOME]}, 3e-5, "sensors.0.noise_mm", ["looks like metres", "given 3e-05"]),
        ({"joints": [[0, 0.5236, 0, -1.0472, 0, 0.7854, 0]]}, 0.03, "poses.joints",
         ["look like radians", "e.g. [0, 30, 0, -60, 0, 45, 0]"]),
    ],
)
def test_metres_and_radians_are_refused_with_the_field_and_the_fix(tmp_path, poses, noise_mm, field, fragments):
    path = plan_file(tmp_path, poses, noise_mm=noise_mm)
    msg = refused(path)
    first = next(line for line in msg.splitlines() if f": {field}: " in line)
    assert first.startswith(f"{path}:"), msg
    for fragment in fragments:
        assert fragment in first, (fragment, first)
    assert "given" in first and "allowed" in first


@pytest.mark.parametrize(
    "rows",
    [
        [[0, 0, 0, 0, 0, 0, 0]],  # the home (candle) position is the same in either unit
        [[0, 2, 0, -3, 0, 1, 0], HOME],  # small angles beside a clearly degree-valued one
        [[0, 3.0, 0, -3.0, 0, 3.0, 0], [0, 4, 0, -5, 0, 10, 0]],
    ],
)
def test_plausible_degrees_are_not_taken_for_radians(tmp_path, rows):
    assert len(resolve_plan(load_plan(plan_file(tmp_path, {"joints": rows}))).configs) == len(rows)


def test_radian_like_targets_that_would_leave_the_limits_as_radians_are_not_called_radians(tmp_path):
    # Read as radians, A2 = 2.5 would be 143°, beyond the iiwa's ±120°: not a units mix-up.
    rows = [[0, 2.5, 0, -1, 0, 1, 0]]
    assert len(resolve_plan(load_plan(plan_file(tmp_path, {"joints": rows}))).configs) == 1
