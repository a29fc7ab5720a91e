"""`acquire run` refuses what it cannot finish: an unwritable output folder before any device is
opened, and a run without a result exits non-zero (real fakes on loopback, real files)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from acquire.cli import app
from acquire.plan.schema import load_plan, resolve_configurations
from acquire.run import RunController, RunError

from run_helpers import ROOT, RUN_TIMEOUT_S, fake_controller, small_plan, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest

pytestmark = pytest.mark.timeout(RUN_TIMEOUT_S)


@pytest.fixture
def no_devices(monkeypatch):
    """Fail the test if the run opens any device (fake or real) or the bus."""
    def refuse(*args, **kwargs):
        raise AssertionError("a device or the bus was opened before the output folder was checked")

    monkeypatch.setattr("acquire.run.devices.RunDevices.open", refuse)
    monkeypatch.setattr("drivers.sim.running.SimulatedCell.start", refuse)
    monkeypatch.setattr("acquire.live.bus.Bus.__init__", refuse)


def test_an_output_folder_that_cannot_be_created_exits_2_before_any_device(tmp_path, no_devices):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the runs folder's parent should be")
    plan = small_plan(tmp_path, n=8, output={"folder": str(blocker / "runs")})
    result = CliRunner().invoke(app, ["run", str(plan), "--fake"])
    assert result.exit_code == 2, result.output
    assert f"output folder {blocker / 'runs'}: cannot create it" in result.output
    assert "--out" in result.output and "Traceback" not in result.output


def test_an_out_option_naming_a_file_exits_2_before_any_device(tmp_path, no_devices):
    plan = small_plan(tmp_path, n=8)
    target = tmp_path / "a-file"
    target.write_text("")
    result = CliRunner().invoke(app, ["run", str(plan), "--fake", "--no-bus", "--out", str(target)])
    assert result.exit_code == 2, result.output
    assert f"output folder {target}" in result.output


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder")
def test_a_read_only_output_folder_exits_2_before_any_device(tmp_path, no_devices):
    runs = tmp_path / "runs"
    runs.mkdir()
    runs.chmod(0o500)
    try:
        plan = small_plan(tmp_path, n=8)
        result = CliRunner().invoke(app, ["run", str(plan), "--fake"])
    finally:
        runs.chmod(0o700)
    assert result.exit_code == 2, result.output
    assert f"output folder {runs}: cannot write in it" in result.output


def test_the_controller_refuses_to_start_with_an_unwritable_folder(tmp_path, no_devices):
    blocker = tmp_path / "file"
    blocker.write_text("")
    lp = load_plan(small_plan(tmp_path, n=4))
    ctl = RunController(lp, out_dir=blocker / "runs")  # refused before any cell is needed
    with pytest.raises(RunError, match="cannot create it"):
        ctl.start()  # the daemon's path: raises before its thread opens anything
    assert ctl.status()["state"] == "idle"


def two_configuration_plan(tmp_path: Path, **fit) -> Path:
    """The example plan cut to two of its configurations (explicit joints): too few for the fit."""
    lp = load_plan(ROOT / "fixtures" / "plans" / "example.yaml")
    rows = [np.round(np.degrees(c.q_rad), 4).tolist() for c in resolve_configurations(lp)[:2]]
    doc = yaml.safe_load(small_plan(tmp_path, n=4).read_text())
    doc["poses"] = {"joints": rows}
    doc["fit"].update(fit)
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_a_plan_too_small_for_the_fit_exits_2_before_any_device(tmp_path, no_devices):
    plan = two_configuration_plan(tmp_path)
    result = CliRunner().invoke(app, ["run", str(plan), "--fake"])
    assert result.exit_code == 2, result.output
    first = result.output.strip().splitlines()[-1]
    assert first.startswith(f"error: {plan}:") and ": poses: 2 configuration(s) cannot give a result" in first
    assert "needs at least 10 (given 2; allowed ≥ 10" in first and "--no-fit" in first
    assert not (tmp_path / "runs").exists()
    # The need follows the plan's fit options: one axis with the registration fixed needs 3 (the
    # registration's three points); --dry-run warns instead of refusing.
    small = two_configuration_plan(tmp_path, joints=[2], fix_registration=True)
    dry = CliRunner().invoke(app, ["run", str(small), "--dry-run"])
    assert dry.exit_code == 0, dry.output
    assert "warning: " in dry.output and "the fit of 1 offset(s) with 1 sensor registration(s) needs at least 3" in dry.output


@pytest.mark.slow  # a whole fake run; test_run_fake.py's complete run (default) takes the same path and fits
def test_the_same_plan_with_no_fit_measures_and_finishes_with_exit_0(tmp_path):
    plan = two_configuration_plan(tmp_path)
    result = CliRunner().invoke(app, ["run", str(plan), "--fake", "--no-bus", "--no-fit"])
    assert result.exit_code == 0, result.output
    assert ": finished" in result.output


def blocked_view_plan(tmp_path: Path) -> Path:
    """A plan the fit could use, in a cell where a column stands between the motion-capture bar
    and the robot: every marker is occluded, nothing can be measured."""
    cell = yaml.safe_load((ROOT / "fixtures" / "sim" / "default.yaml").read_text())
    cell["robot"] = str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    cell["occlusion"]["obstacles"] = [{"a_mm": [1500, 0, -3000], "b_mm": [1500, 0, 5000], "radius_mm": 450}]
    (tmp_path / "blocked.yaml").write_text(yaml.safe_dump(cell, sort_keys=False))
    return small_plan(tmp_path, n=8, name="plan.yaml", fake={"sim_config": str(tmp_path / "blocked.yaml")},
                      sequencing={"on_lost_target": "skip", "lost_target_wait_s": 0.2})


@pytest.mark.slow  # ~55 s: 14 configurations moved to and skipped; a failed fit's exit is also tested below
def test_a_run_that_measures_nothing_exits_1_and_says_why(tmp_path):
    plan = blocked_view_plan(tmp_path)
    result = CliRunner().invoke(app, ["run", str(plan), "--fake", "--no-bus"])
    assert result.exit_code == 1, result.output
    assert "failed (no result: none of the 14 configurations was measured (14 skipped, 0 failed))" in result.output
    assert not list((tmp_path / "runs").rglob("result.json"))
    assert len(list((tmp_path / "runs").rglob("*.mcap"))) == 1  # the log is kept


def test_the_controller_reports_a_run_too_small_for_the_fit_as_failed(tmp_path):
    """RunController (the daemon's path) fits what it measured; two configurations cannot give a
    result, so the run ends failed with the fit's reason."""
    lp = load_plan(two_configuration_plan(tmp_path))
    ctl = fake_controller(lp)
    ctl.start()
    summary = wait_for_run(ctl)
    assert summary.state == "failed" and summary.exit_code == 1
    assert summary.reason.startswith("no result:"), summary.reason
    assert summary.measured + summary.skipped + summary.failed == 2
    assert ctl.status()["state"] == "failed" and ctl.status()["reason"] == summary.reason
