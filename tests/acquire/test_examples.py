"""Packaged examples by name: `acquire examples`, `acquire run NAME`, copies that work anywhere."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquire.cli import app
from acquire.commands.examples import copy_plan
from acquire.commands.run import plan_argument
from acquire.plan.schema import load_plan, resolve_plan
from calib.io import resources

ROOT = Path(__file__).resolve().parents[2]


def test_the_packaged_files_are_the_checkouts_fixtures():
    for kind, folder in (("plans", "plans"), ("robots", "robots"), ("sim", "sim")):
        names = [p.name for p in resources.packaged(kind)]
        assert names == sorted(p.name for p in (ROOT / "fixtures" / folder).glob("*.yaml"))
        for p in resources.packaged(kind):
            assert p.read_bytes() == (ROOT / "fixtures" / folder / p.name).read_bytes()
    assert resources.default_sim_config() == (ROOT / "fixtures" / "sim" / "default.yaml").resolve()
    assert not resources.is_packaged(ROOT / "fixtures" / "plans" / "example.yaml")  # a checkout, not an install


def test_a_plan_name_finds_the_packaged_example_and_its_run_goes_to_the_current_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path, packaged = plan_argument(Path("example"))
    assert packaged and path == resources.find("plans", "example") and path.is_file()
    assert plan_argument(Path("paper.yaml"))[0].name == "paper.yaml"
    local = tmp_path / "mine.yaml"
    local.write_text("cell: x\n")
    assert plan_argument(local) == (local, False)
    result = CliRunner().invoke(app, ["run", "example", "--dry-run"])
    assert result.exit_code == 0, result.output
    assert "40 configurations in run order" in result.output
    assert not (tmp_path / "runs").exists()


def test_an_unknown_plan_name_exits_2_listing_the_examples(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["run", "exampel", "--dry-run"])
    assert result.exit_code == 2
    assert "no such plan file" in result.output and "example, paper, tracker" in result.output


def test_examples_lists_every_packaged_file_with_its_path():
    result = CliRunner().invoke(app, ["examples"])
    assert result.exit_code == 0, result.output
    for kind in resources.KINDS:
        for p in resources.packaged(kind):
            assert f"{p.stem:<20} {p}" in result.output


def test_a_copied_example_loads_from_another_folder_and_writes_beside_itself(tmp_path):
    target = copy_plan("example", tmp_path)
    assert target == tmp_path / "example.yaml"
    lp = load_plan(target)
    assert lp.model_path == (ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").resolve()
    assert lp.output_dir == tmp_path / "runs"
    assert lp.sim_config_path == resources.default_sim_config()
    assert len(resolve_plan(lp).configs) == 40
    assert "# the simulated cell" in target.read_text()  # comments kept
    with pytest.raises(FileExistsError):
        copy_plan("example", tmp_path)
    with pytest.raises(ValueError, match=r"allowed: (?=.*\bexample\b)(?=.*\bpaper\b)(?=.*\btracker\b)"):
        copy_plan("nosuch", tmp_path)


def test_robot_models_load_by_packaged_name_when_no_such_file_exists(tmp_path, monkeypatch):
    from calib.robot.model import load_robot_model
    from calib.io.yamlfile import ConfigError

    monkeypatch.chdir(tmp_path)
    assert load_robot_model("kuka_iiwa14_r820").name == "KUKA LBR iiwa 14 R820"
    assert load_robot_model("kuka_kr6_r900_2.yaml").n_joints == 6
    assert load_robot_model("franka_panda").tool.markers[0].name == "ball"
    with pytest.raises(ConfigError, match="no such robot model file .*packaged model: .*kuka_iiwa14_r820"):
        load_robot_model("kuka_iiwa99")
    with pytest.raises(ConfigError, match="no such robot model file"):
        load_robot_model(tmp_path / "models" / "kuka_iiwa14_r820.yaml")  # a path is never swapped for a name
    local = tmp_path / "kuka_iiwa14_r820.yaml"  # a file of that name in the current folder wins
    local.write_text((ROOT / "fixtures" / "robots" / "kuka_iiwa7_r800.yaml").read_text())
    assert load_robot_model("kuka_iiwa14_r820.yaml").name == "KUKA LBR iiwa 7 R800"


def test_examples_lists_the_packaged_foxglove_layout_and_run_help_points_at_it():
    layout = resources.foxglove_layout()
    assert layout.is_file() and layout.read_bytes() == (ROOT / "fixtures" / "foxglove" / "remaster-layout.json").read_bytes()
    result = CliRunner().invoke(app, ["examples"])
    assert result.exit_code == 0, result.output
    assert f"  {layout}" in result.output.splitlines()
    from acquire.commands import run as run_command
    import inspect

    live = inspect.signature(run_command.run).parameters["live"].default
    assert str(layout) in live.help and "fixtures/" not in live.help.replace(str(layout), "")
