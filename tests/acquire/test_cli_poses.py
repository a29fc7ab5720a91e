"""``acquire poses``: the printed plan, the configurations file, and clear errors on bad input."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from acquire.commands import poses as poses_command
from calib.robot.model import load_robot_model
from calib.plan.poses import read_configurations

ROOT = Path(__file__).resolve().parents[2]
KR6 = ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml"
IIWA = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"


@pytest.fixture()
def app():
    """A multi-command app like ``acquire``'s, with only this command registered."""
    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        """remaster"""

    poses_command.register(app)
    return app


def run(app, *args):
    return CliRunner().invoke(app, ["poses", *map(str, args)])


def test_prints_the_plan_and_writes_the_configurations_file(app, tmp_path):
    out = tmp_path / "configs.csv"
    res = run(app, "--robot", KR6, "--sensor-origin", "900,-300,700", "-n", 12, "--seed", 2, "-o", out)
    assert res.exit_code == 0, res.output
    text = res.output
    assert "candidate poses: 12" in text
    n_valid = int(re.search(r"valid poses: (\d+)", text).group(1))
    n_cfg = int(re.search(r"configurations: (\d+)", text).group(1))
    n_drop = int(re.search(r"dropped poses: (\d+)", text).group(1))
    assert n_valid + n_drop == 12 and n_valid >= 2 and n_cfg >= 2 * n_valid
    back = read_configurations(out, load_robot_model(KR6))
    assert len(back.configurations) == n_cfg and back.seed == 2
    # Each configuration row printed in degrees matches the file.
    table = text.split("configurations (deg):")[1].split("dropped poses:")[0].strip().splitlines()[1:]
    assert len(table) == n_cfg
    first = table[0].split()
    np.testing.assert_allclose([float(v) for v in first[-6:]], np.degrees(back.configurations[0].q), atol=0.006)
    assert len(re.findall(r"^\s+pose \d+: ", text.split("dropped poses:\n")[1], flags=re.M)) == n_drop
    assert f"wrote {n_cfg} configurations to {out}" in text


def test_valid_pose_rows_aim_at_the_sensor(app):
    res = run(app, "--robot", KR6, "--sensor-origin", "900,-300,700", "-n", 8, "--seed", 4)
    assert res.exit_code == 0, res.output
    rows = res.output.split("A B C = ZYX Euler deg):")[1].split("configurations (deg):")[0].strip().splitlines()[1:]
    assert rows
    for row in rows:
        _, x, y, z, a, b, c, _n = (float(v) for v in row.split())
        # ZYX Euler: the third column of Rz(a) Ry(b) Rx(c) is the aimed z-axis.
        a, b, c = map(math.radians, (a, b, c))
        z_axis = np.array([
            math.cos(a) * math.sin(b) * math.cos(c) + math.sin(a) * math.sin(c),
            math.sin(a) * math.sin(b) * math.cos(c) - math.cos(a) * math.sin(c),
            math.cos(b) * math.cos(c),
        ])
        to_sensor = np.array([900.0, -300.0, 700.0]) - [x, y, z]
        assert np.dot(z_axis, to_sensor / np.linalg.norm(to_sensor)) > 1 - 1e-4


def test_ranges_in_degrees_and_negative_values_are_accepted(app):
    res = run(app, "--robot", KR6, "--sensor-origin", "-900,300,700", "-n", 6, "--angle", "-45,45", "--roll", "-10,10",
              "--radius", "300,400", "--height", "500,600")
    assert res.exit_code == 0, res.output
    rows = res.output.split("A B C = ZYX Euler deg):")[1].split("configurations (deg):")[0].strip().splitlines()[1:]
    for row in rows:
        _, x, y, z = (float(v) for v in row.split()[:4])
        assert -45.0 - 1e-6 <= math.degrees(math.atan2(y, x)) <= 45.0 + 1e-6
        assert 300 - 1e-6 <= math.hypot(x, y) <= 400 + 1e-6 and 500 <= z <= 600


def test_seven_axis_arm_with_extra_arm_angles(app):
    res = run(app, "--robot", IIWA, "--sensor-origin", "1500,200,600", "-n", 4, "--arm-angle", 30, "--arm-angle", -30)
    assert res.exit_code == 0, res.output
    assert "@ψ=30.0" in res.output and "@ψ=-30.0" in res.output


@pytest.mark.parametrize(
    "args, expect",
    [
        (["--sensor-origin", "1,2"], r"--sensor-origin.*expected X,Y,Z in mm \(three numbers\), given '1,2'"),
        (["--sensor-origin", "a,b,c"], r"--sensor-origin.*given 'a,b,c'"),
        (["--sensor-origin", "1,2,3", "--radius", "500,200"], r"--radius.*LOW must not exceed HIGH, given '500,200'"),
        (["--sensor-origin", "1,2,3", "--radius", "-5,200"], r"--radius.*a radius must be ≥ 0"),
        (["--sensor-origin", "1,2,3", "--height", "400"], r"--height.*expected LOW,HIGH in mm \(two numbers\), given '400'"),
        (["--sensor-origin", "1,2,3", "--angle", "0,nan"], r"--angle.*given '0,nan'"),
        (["--sensor-origin", "1,2,3", "-n", "0"], r"-n.*must be at least 1, given 0"),
        (["--sensor-origin", "1,2,3", "--min-solutions", "0"], r"--min-solutions.*must be at least 1"),
        (["--sensor-origin", "1,2,3", "--margin", "-1"], r"--margin.*must be ≥ 0 degrees"),
        (["--sensor-origin", "1,2,3", "--arm-angle", "10"], r"--arm-angle.*arm angles apply to 7-axis arms; KUKA KR 6 R900-2 has 6"),
    ],
)
def test_bad_arguments_exit_non_zero_with_a_clear_message(app, args, expect):
    res = run(app, "--robot", KR6, *args)
    assert res.exit_code == 2, res.output
    flat = re.sub(r"[\s│╭╮╰╯─]+", " ", res.output)
    assert re.search(expect, flat), flat


def test_bad_robot_file_names_file_line_and_field(app, tmp_path):
    bad = tmp_path / "robot.yaml"
    bad.write_text(KR6.read_text(encoding="utf-8").replace("name: KUKA KR 6 R900-2", "nam: KUKA KR 6 R900-2"), encoding="utf-8")
    res = run(app, "--robot", bad, "--sensor-origin", "1,2,3")
    assert res.exit_code == 2
    flat = re.sub(r"[\s│╭╮╰╯─]+", "", res.output)
    assert "robot.yaml" in flat and "name" in flat
    missing = run(app, "--robot", tmp_path / "none.yaml", "--sensor-origin", "1,2,3")
    assert missing.exit_code == 2 and "cannotread" in re.sub(r"[\s│╭╮╰╯─]+", "", missing.output)


def test_the_installed_entry_point_lists_the_command():
    res = subprocess.run([sys.executable, "-m", "acquire.cli", "--help"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert "poses" in res.stdout or "--sensor-origin" in res.stdout


def test_a_sensor_inside_the_sampled_volume_is_reported(app):
    res = run(app, "--robot", KR6, "--sensor-origin", "300,0,500", "-n", 3, "--radius", "300,300",
              "--height", "500,500", "--angle", "0,0")
    assert res.exit_code == 2
    assert "coincide with the sensor origin" in re.sub(r"[\s│╭╮╰╯─]+", " ", res.output)


def test_whole_turn_twins_add_configurations_for_the_kr6(app):
    base = run(app, "--robot", KR6, "--sensor-origin", "900,-300,700", "-n", 6, "--seed", 3)
    twins = run(app, "--robot", KR6, "--sensor-origin", "900,-300,700", "-n", 6, "--seed", 3, "--whole-turn-twins")
    assert base.exit_code == 0 and twins.exit_code == 0
    count = lambda out: int(re.search(r"configurations: (\d+)", out).group(1))  # noqa: E731
    assert count(twins.output) > count(base.output)
    assert re.search(r" A6[+-]360", twins.output) and not re.search(r" A6[+-]360", base.output)
