"""`acquire fit --method full` on 6-DoF rows (a CSV with orientation columns): attitude accuracy
(EACAE / EMCAE, degrees) beside position accuracy in the summary, result.json and the report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from acquire.cli import app
from calib.measure.dataset import write_csv
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import exp_so3

from tests.calib.pose_sim import BASE2SENSOR, PoseCell, measure_poses, perturb

ROBOT = Path(__file__).resolve().parents[2] / "fixtures" / "robots" / "staubli_tx60.yaml"


def test_pose_csv_reports_attitude_accuracy_before_and_after(tmp_path):
    model = load_robot_model(ROBOT)
    chain = Chain(model)
    rng = np.random.default_rng(7)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (70, 6))
    names = [n for n in chain.param_names if n.split(".")[0] in model.axis_names and not n.endswith(".beta")]
    truth = perturb(chain, names, rng, 0.3, 0.05)
    data = measure_poses(chain, q, PoseCell(truth, exp_so3(np.radians([1.0, 2.0, 30.0])), BASE2SENSOR, 0.02, 0.01), rng)
    cal, val = data.subset(np.arange(70) < 40), data.subset(np.arange(70) >= 40)
    write_csv(cal, tmp_path / "cal.csv")
    write_csv(val, tmp_path / "val.csv")
    out = tmp_path / "r.json"
    res = CliRunner().invoke(app, ["fit", str(tmp_path / "cal.csv"), "--robot", str(ROBOT), "--validate", str(tmp_path / "val.csv"),
                                   "--method", "full", "--starts", "2", "-o", str(out), "--report", str(tmp_path / "r.html")])
    assert res.exit_code == 0, res.output
    assert "EACAE" in res.output and "°" in res.output
    doc = json.loads(out.read_text())
    v = doc["metrics"]["validation"]
    assert v["before"]["EACAE"] > 0.05 and v["after"]["EACAE"] < 0.3 * v["before"]["EACAE"]
    assert v["after"]["EACAE"] < 0.05 and v["after"]["EMCAE"] >= v["after"]["EACAE"]
    assert v["after"]["EACPE"] < 0.3 * v["before"]["EACPE"]
    assert doc["attitude_weight"]["how"].startswith("σ_position")
    assert doc["tool_frames"]["smr"]["rpy_deg"][2] == pytest_approx(30.0, 0.5)
    html = (tmp_path / "r.html").read_text()
    assert "EACAE (mean, °)" in html


def pytest_approx(v, tol):
    import pytest

    return pytest.approx(v, abs=tol)


def test_select_on_position_and_attitude_rows(tmp_path):
    from tests.acquire.test_cli_select import ROBOT as TX60, write_candidates

    cand = tmp_path / "cand.csv"
    write_candidates(cand)
    args = ["select", "--robot", str(TX60), "--candidates", str(cand), "-m", "20"]
    pos = CliRunner().invoke(app, args)
    pose = CliRunner().invoke(app, args + ["--orientation", "0.024,0.01"])
    assert pos.exit_code == 0 and pose.exit_code == 0, pose.output
    n = [int(r.output.split(" candidates, ")[1].split()[0]) for r in (pos, pose)]
    assert n[1] > n[0] and "position + attitude rows" in pose.output  # the target's frame and more are seen
    bad = CliRunner().invoke(app, args + ["--orientation", "0.024"])
    assert bad.exit_code == 2 and "SIGMA_MM,SIGMA_DEG" in bad.output


def test_the_default_fit_uses_the_attitude_rows_and_reports_attitude_accuracy(tmp_path):
    """`acquire fit` (default: the model chosen by cross-validation, zero-offset family) on 6-DoF
    rows fits positions and attitudes together and prints and writes EACAE / EMCAE."""
    model = load_robot_model(ROBOT)
    chain = Chain(model)
    rng = np.random.default_rng(8)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (60, 6))
    truth = chain.with_offsets(np.radians(rng.normal(0.0, 0.05, 6)))
    data = measure_poses(chain, q, PoseCell(truth, exp_so3(np.radians([1.0, 2.0, 30.0])), BASE2SENSOR, 0.02, 0.01), rng)
    cal, val = data.subset(np.arange(60) < 40), data.subset(np.arange(60) >= 40)
    write_csv(cal, tmp_path / "cal.csv")
    write_csv(val, tmp_path / "val.csv")
    out = tmp_path / "r.json"
    res = CliRunner().invoke(app, ["fit", str(tmp_path / "cal.csv"), "--robot", str(ROBOT), "--validate", str(tmp_path / "val.csv"),
                                   "--model", "offsets+tool", "--draws", "300", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "fitted on their positions and attitudes together" in res.output
    assert "validation (position and attitude)" in res.output and "EACAE" in res.output
    doc = json.loads(out.read_text())
    v = doc["pose_metrics"]["validation"]
    assert v["after"]["EACAE"] < 0.3 * v["before"]["EACAE"] and v["after"]["EACPE"] < 0.3 * v["before"]["EACPE"]
    assert doc["attitude_weight"]["how"].startswith("σ_position")
