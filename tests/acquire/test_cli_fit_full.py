"""`acquire fit --method full`: identification result, corrected model file the tools can load."""

import json

import pytest
from pathlib import Path

from typer.testing import CliRunner

from acquire.cli import app
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model

ROOT = Path(__file__).resolve().parents[2]
ROBOT = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"
CAL = ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"
VAL = ROOT / "fixtures" / "datasets" / "iiwa14_sim_val.csv"


def test_full_identification_writes_result_and_a_loadable_corrected_model(tmp_path):
    out = tmp_path / "full.json"
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--validate", str(VAL), "--method", "full", "-o", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["method"] == "full"
    assert "A1.offset" in doc["excluded"] and "not identifiable" in doc["excluded"]["A1.offset"]
    val = doc["metrics"]["validation"]
    assert val["after"]["EACPE"] < 0.2 * val["before"]["EACPE"]
    assert val["after"]["EACAE"] is None  # no orientation measured
    model = load_robot_model(doc["model_file"])
    identified = {p["name"]: p for p in doc["parameters"]}
    # The corrected model carries the identified link lengths.
    a3 = [j for j in model.joints if j.axis == "A3"][0]
    assert abs(a3.d - identified["A3.d"]["value"]) < 1e-6
    assert Chain(model).n_params == Chain(load_robot_model(ROBOT)).n_params
    # The tool is fitted under its prior and takes what the last link's d, a, α would otherwise take.
    assert doc["tool_prior_mm"] == 10.0
    assert identified["sir.x"]["identified"] and not identified["A7.d"]["identified"]
    assert "sir" in doc["excluded"]["A7.d"] and "does not move any measured marker" in doc["excluded"]["smr.x"]
    assert model.tool.markers[1].xyz == pytest.approx(tuple(identified[f"sir.{c}"]["value"] for c in "xyz"), abs=1e-6)
    assert "reregistered" in val and any("calibration registration" in n for n in doc["metric_notes"])
    assert "re-registered on its own points (optimistic)" in res.output


def test_unknown_method_is_refused():
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--method", "magic"])
    assert res.exit_code != 0 and "fast, paper or full" in res.output


def test_full_identification_writes_a_report_and_lists_its_starts(tmp_path):
    rep = tmp_path / "report.html"
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--validate", str(VAL), "--method", "full",
                                   "--report", str(rep), "--starts", "3", "--seed", "5"])
    assert res.exit_code == 0, res.output
    assert "starts (best first): " in res.output and res.output.count("random start") == 1
    html = rep.read_text()
    for heading in ("Starts of the solve", "Identified parameters", "Kept nominal", "Accuracy before and after",
                    "re-registered on its own points (optimistic)", "with the calibration registration"):
        assert heading in html, heading
    assert html.count("<svg ") == 1 and 'data-logy="1"' in html and "A3.d" in html  # the error on a log scale


def test_full_identification_honours_joints_and_fix_registration(tmp_path):
    out = tmp_path / "full.json"
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--method", "full", "--joints", "2,3,4,5,6",
                                   "--fix-registration", "-o", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    identified = {p["name"]: p for p in doc["parameters"]}
    assert identified["A3.offset"]["identified"] and not identified["A7.offset"]["identified"]
    assert "not in --joints" in doc["excluded"]["A7.offset"]
    sensor = next(iter(doc["registration"]))
    assert "--fix-registration" in doc["excluded"][f"{sensor}.x"]
    free = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--method", "full", "-o", str(tmp_path / "b.json")])
    assert free.exit_code == 0
    assert json.loads((tmp_path / "b.json").read_text())["registration"][sensor] != doc["registration"][sensor]


@pytest.mark.parametrize("option, value, says", [
    ("--link-tolerance", "0.1,0.01", "identifies the link parameters themselves"),
    ("--error", "student", "use --method fast or paper"),
    ("--draws", "200", "only the fast sampler"),
    ("--paper-samples", "4000", "only the paper's Metropolis"),
    ("--random-configs", "50", "scores the measured configurations"),
])
def test_options_full_does_not_use_are_refused_saying_what_to_do(option, value, says):
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--method", "full", option, value])
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and f"{option} does not apply to --method full" in text and says in text, res.output


@pytest.mark.parametrize("method", ["fast", "paper"])
def test_model_out_is_refused_where_the_model_is_not_changed(method, tmp_path):
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--method", method,
                                   "--model-out", str(tmp_path / "m.yaml")])
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2 and f"--model-out does not apply to --method {method}" in text, res.output
    assert not (tmp_path / "m.yaml").exists()


def test_starts_is_refused_for_the_fast_method():
    res = CliRunner().invoke(app, ["fit", str(CAL), "--robot", str(ROBOT), "--method", "fast", "--starts", "4"])
    assert res.exit_code == 2 and "--starts applies to" in " ".join(res.output.replace("│", " ").split())
