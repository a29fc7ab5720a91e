"""``acquire fit``: summary, result.json, report.html, and a non-zero exit on bad input."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from acquire.commands import fit as fit_command
from calib.measure.dataset import from_arrays, read_csv, write_csv
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import apply, pose_to_matrix

ROOT = Path(__file__).resolve().parents[2]
IIWA = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"
KR6 = ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml"
CAL = ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"
VAL = ROOT / "fixtures" / "datasets" / "iiwa14_sim_val.csv"
TRUE_OFFSETS_DEG = [0.477, -0.192, 0.139, 0.099, 0.392, -0.114, 0.936]  # make_sim.py: Table I
QUICK = ["--draws", "300", "--random-configs", "100"]


@pytest.fixture()
def app():
    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        """remaster"""

    fit_command.register(app)
    return app


def run(app, *args):
    return CliRunner().invoke(app, ["fit", *map(str, args)])


def flat(text: str) -> str:
    """Error panels wrap lines and draw boxes: compare without either."""
    return re.sub(r"[\s│╭╮╰╯─]+", "", text)


def test_fit_prints_summary_writes_result_and_report(app, tmp_path):
    out, rep = tmp_path / "result.json", tmp_path / "report.html"
    res = run(app, CAL, "--robot", IIWA, "--validate", VAL, "-o", out, "--report", rep, "--seed", 3, *QUICK)
    assert res.exit_code == 0, res.output
    text = res.output
    doc = json.loads(out.read_text())
    # Summary: each joint, its status, σ, diagnostics, metrics, values to enter.
    assert re.search(r"^A1\s+—\s+—\s+—\s+undetermined: ", text, flags=re.M)
    for j in doc["joint_offsets"][1:6]:
        value = re.escape(f"{j['value_deg']:+.4f}")
        assert re.search(rf"^{j['joint']}\s+{value}\s+{j['std_deg']:.4f}\s+\[.*\]\s+fitted$", text, flags=re.M)
    assert re.search(r"sensor mocap: σ = 0\.\d{3} ± 0\.\d{3} mm", text)
    # The default: the data choose the model (the table, the choice), and the Laplace posterior checked by PSIS.
    assert re.search(r"^model choice: 5-fold cross-validation by pose group", text, flags=re.M)
    assert re.search(r"^  offsets\s+\d+\s+\d\.\d{4}\s+\d\.\d{4} ± \d\.\d{4}", text, flags=re.M)
    assert re.search(r"Pareto k̂ -?\d\.\d\d \(< 0\.7: used\), effective draws \d+", text)
    assert "validation_absolute" in text and "theoretical_workspace_offsets_only" in text
    assert "values to enter (sunrise):" in text and "leave unchanged" in text
    # The fitted offsets are close to the simulated truth (link errors and sag bias them a little).
    fitted = np.array([j["value_deg"] for j in doc["joint_offsets"][1:6]])
    np.testing.assert_allclose(fitted, TRUE_OFFSETS_DEG[1:6], atol=0.05)
    # The tool is fitted by default (±10 mm prior): A7 cannot be told from a turn of the tool.
    assert re.search(r"^A7\s+—\s+—\s+—\s+undetermined: not separable from the tool", text, flags=re.M)
    assert re.search(r"^tool marker sir \(flange frame\): x [+-]\d+\.\d{3} ± 0\.\d{3} mm \(model -100\.0\)", text, flags=re.M)
    assert doc["tool"]["prior_mm"] == 10.0 and doc["tool"]["markers"][0]["marker"] == "sir"
    # result.json: the sections of issue 3.
    assert set(doc) >= {"joint_offsets", "registration", "sigma_mm", "diagnostics", "identifiability", "metrics", "controller"}
    assert doc["joint_offsets"][0]["value_deg"] is None and doc["joint_offsets"][0]["identifiable"] is False
    m = doc["metrics"]
    for key in ("relative", "absolute", "theoretical_workspace", "validation_relative", "validation_absolute"):
        assert m[key]["after"]["mean"] < m[key]["before"]["mean"] / 2, key
    assert m["settings"]["n_random_configurations"] == 100
    assert doc["diagnostics"]["method"] == "laplace" and doc["diagnostics"]["importance"]["k_hat"] < 0.7
    choice = doc["model_choice"]
    assert choice["chosen"] in {c["model"] for c in choice["candidates"]} and choice["grouped_by"] == "pose group"
    chosen = next(c for c in choice["candidates"] if c["model"] == choice["chosen"])
    assert chosen["cv_mean_mm"] < choice["nominal"]["cv_mean_mm"] / 10
    assert [a["action"] for a in doc["controller"]["axes"]] == ["leave unchanged"] + ["enter"] * 5 + ["leave unchanged"]
    # report.html: self-contained (inline SVG figures, nothing fetched).
    html = rep.read_text()
    assert html.count("<svg ") == 6  # TCP cloud (Fig. 5) per configuration, traces, errors two ways
    assert html.count('aria-label="TCP cloud') == 3 and "id=summary" in html and "<img" not in html
    assert not re.search(r'(src|href)="(http|//)', html)
    for heading in ("Values to enter", "Zero-offsets", "Tool markers (flange frame, mm)", "Accuracy before and after", "Identifiability", "Sampler diagnostics"):
        assert heading in html
    assert f"wrote {out}" in text and f"wrote {rep}" in text


def test_an_exact_tool_on_request_fits_the_last_offset_and_bad_priors_are_refused(app, tmp_path):
    out = tmp_path / "exact.json"
    res = run(app, CAL, "--robot", IIWA, "-o", out, "--tool-prior-mm", 0, *QUICK)
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["tool"] == {"prior_mm": 0.0, "markers": [], "degeneracies": []}
    assert "the model's positions taken as exact" in res.output
    last = doc["joint_offsets"][6]
    assert last["status"] == "fitted" and abs(last["value_deg"] - TRUE_OFFSETS_DEG[6]) < 0.05
    bad = run(app, CAL, "--robot", IIWA, "--tool-prior-mm", -3, *QUICK)
    assert bad.exit_code == 2 and "0≤MM≤100" in flat(bad.output) and "--tool-prior-mm" in flat(bad.output)


def test_validation_rows_in_the_same_file_are_used(app, tmp_path):
    model = load_robot_model(IIWA)
    both = read_csv(CAL, model).concat(read_csv(VAL, model))
    path = tmp_path / "both.csv"
    write_csv(both, path)
    out = tmp_path / "r.json"
    res = run(app, path, "--robot", IIWA, "-o", out, *QUICK)
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["data"]["n_measurements"] == len(both.calibration())
    assert "validation_absolute" in doc["metrics"]


def test_paper_method_fixed_registration_and_joint_selection(app, tmp_path):
    out = tmp_path / "r.json"
    res = run(app, CAL, "--robot", IIWA, "--method", "paper", "--paper-samples", 4000, "--joints", "1,2,3",
              "--fix-registration", "--error", "student", "-o", out, "--random-configs", 50)
    # 4000 paper samples cannot converge, and three offsets cannot explain this data: the values
    # are written but marked "do not enter", and the exit status says so.
    assert res.exit_code == 1, res.output
    doc = json.loads(out.read_text())
    assert doc["diagnostics"]["sampler"] == "paper" and doc["diagnostics"]["n_draws"] == 500
    assert any("has not converged" in r for r in doc["do_not_enter"])
    statuses = [j["status"] for j in doc["joint_offsets"]]
    # With the registration fixed, A1 is no longer confounded: it is fitted (and refused with the others).
    assert statuses[:3] == ["do not enter"] * 3 and statuses[3:] == ["fixed"] * 4
    assert {a["action"] for a in doc["controller"]["axes"]} == {"leave unchanged"}
    assert all(not c["free"] for c in doc["registration"]["mocap"]["corrections"].values())


def _simulated_csv(tmp_path: Path, k: int, scale: float = 1.0) -> Path:
    model = load_robot_model(IIWA)
    chain = Chain(model)
    q = np.random.default_rng(0).uniform(model.lower_limits_rad * 0.8, model.upper_limits_rad * 0.8, size=(k, 7))
    b2s = pose_to_matrix(np.array([2000.0, 0.0, 0.0]), np.radians([180.0, 0.0, 0.0]))
    path = tmp_path / f"sim{k}.csv"
    write_csv(from_arrays(q, apply(b2s, chain.marker_positions(q)[:, 0]) * scale, marker="smr"), path)
    return path


def _broken_copy(tmp_path: Path, line: int, edit) -> Path:
    lines = CAL.read_text().splitlines()
    lines[line - 1] = edit(lines[line - 1])
    path = tmp_path / "broken.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "case, expected",
    [
        ("nan", "broken.csv:9:column'x':'nan'isnotafinitenumber"),
        ("columns", "broken.csv:10:18columns,theheaderhas17"),
        ("joints", "7jointcolumns(q1…q7)buttherobotmodel'KUKAKR6R900-2'has6joints"),
        ("metres", "positionslooklikemetres"),
        ("too-few", "8measurementsgive24coordinatesfor14freeparameters;measureatleast10"),
        ("suffix", "noloaderfor'.txt';known:['.csv','.mcap']"),
        ("joints-option", "axisnumbersmustliein1…7,given'2,9'"),
        ("robot", "--robot"),
    ],
)
def test_bad_input_exits_non_zero_with_a_clear_message(app, tmp_path, case, expected):
    args = [CAL, "--robot", IIWA]
    if case == "nan":
        args[0] = _broken_copy(tmp_path, 9, lambda s: ",".join(s.split(",")[:9] + ["nan"] + s.split(",")[10:]))
    elif case == "columns":
        args[0] = _broken_copy(tmp_path, 10, lambda s: s + ",1")
    elif case == "joints":
        args[2] = KR6
    elif case == "metres":
        args[0] = _simulated_csv(tmp_path, 30, scale=0.001)
    elif case == "too-few":
        args[0] = _simulated_csv(tmp_path, 8)
    elif case == "suffix":
        txt = tmp_path / "data.txt"
        txt.write_text(CAL.read_text())
        args[0] = txt
    elif case == "joints-option":
        args += ["--joints", "2,9"]
    elif case == "robot":
        args[2] = tmp_path / "missing.yaml"
    res = run(app, *args, *QUICK)
    assert res.exit_code != 0
    assert expected in flat(res.output), res.output


def test_fit_is_a_subcommand_of_acquire():
    res = subprocess.run([sys.executable, "-m", "acquire.cli", "fit", "--help"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    for option in ("--robot", "--validate", "--method", "--joints", "--fix-registration", "--error", "--seed", "--report"):
        assert option in res.stdout


def test_fit_refuses_a_csv_in_radians_before_fitting(app, tmp_path):
    ds = read_csv(CAL, load_robot_model(IIWA))
    rad = tmp_path / "radians.csv"
    write_csv(from_arrays(np.radians(ds.q_rad), ds.xyz_mm, marker=ds.marker, sensor=ds.sensor, config=ds.config), rad)
    res = run(app, rad, "--robot", IIWA, "-o", tmp_path / "result.json", *QUICK)
    assert res.exit_code == 2, res.output
    assert f"{rad}:2:columns'q1'…'q7':everyjointangle" in flat(res.output), res.output
    assert "theselooklikeradians" in flat(res.output) and "Traceback" not in res.output
    assert not (tmp_path / "result.json").exists()
