"""``acquire model import / export``: URDF in and out from the command line, with real fits."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.cli import app
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.urdf import fk_difference, load_urdf, random_configurations, urdf_fk

# One xdist worker runs this file: its module fixture (a full fit) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("acquire/test_cli_model")

ROOT = Path(__file__).resolve().parents[2]
IIWA = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"
CAL = ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"
URDFS = ROOT / "tests" / "calib" / "urdf"


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_import_writes_a_model_that_loads_and_prints_its_fk_check(tmp_path):
    out = tmp_path / "kr6.yaml"
    res = run("model", "import", URDFS / "kuka_kr6r900_2.urdf", "-o", out, "--axes", "A1,A2,A3,A4,A5,A6",
              "--controller", "kss", "--check", "50")
    assert res.exit_code == 0, res.output
    assert "FK check against the URDF (base_link → tool0, yourdfpy), 50 configurations" in res.output
    assert "convention mdh: axes 2 and 3 are parallel" in res.output and f"wrote {out}" in res.output
    model = load_robot_model(out)
    assert model.controller == "kss" and model.axis_names == ["A1", "A2", "A3", "A4", "A5", "A6"]
    text = out.read_text()
    assert text.startswith("# Imported by `acquire model import` from kuka_kr6r900_2.urdf")
    q = random_configurations(model, 20, seed=9)
    ref = urdf_fk(load_urdf(URDFS / "kuka_kr6r900_2.urdf"), [f"joint_a{i}" for i in range(1, 7)], "base_link", "tool0", q)
    assert fk_difference(Chain(model).fk(q), ref)[0] < 1e-9


def test_import_takes_the_tool_from_a_model_file_and_the_command_is_listed(tmp_path):
    out = tmp_path / "kr6.yaml"
    kr6 = ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml"
    res = run("model", "import", URDFS / "kuka_kr6r900_2.urdf", "-o", out, "--tool", kr6, "--check", "10")
    assert res.exit_code == 0, res.output
    assert load_robot_model(out).tool == load_robot_model(kr6).tool
    listing = run("--help").output
    assert "model" in listing and "URDF" in listing


def test_import_asks_for_the_tip_when_the_urdf_has_two_flanges(tmp_path):
    out = tmp_path / "iiwa.yaml"
    res = run("model", "import", URDFS / "kuka_iiwa14.urdf", "-o", out)
    assert res.exit_code == 2 and "choose the flange with --tip" in res.output and "iiwa_link_ee_kuka" in res.output
    assert not out.exists()
    res = run("model", "import", URDFS / "kuka_iiwa14.urdf", "--tip", "iiwa_link_ee_kuka", "-o", out)
    assert res.exit_code == 0, res.output
    assert load_robot_model(out).has_dynamics


def test_import_refuses_bad_options(tmp_path):
    res = run("model", "import", URDFS / "kuka_kr6r900_2.urdf", "-o", tmp_path / "x.yaml", "--convention", "poe")
    assert res.exit_code == 2 and "dh, mdh or auto" in res.output
    res = run("model", "import", URDFS / "kuka_kr6r900_2.urdf", "-o", tmp_path / "x.yaml", "--axes", "A1,A1,A3,A4,A5,A6")
    assert res.exit_code == 2 and "distinct" in res.output
    res = run("model", "import", URDFS / "kuka_kr6r900_2.urdf", "-o", tmp_path / "x.yaml", "--axes", "A1,A2")
    assert res.exit_code == 2 and "2 axis names given for 6 revolute joints" in res.output


@pytest.fixture(scope="module")
def full_fit(tmp_path_factory):
    """A real ``acquire fit --method full`` on the simulated iiwa data."""
    out = tmp_path_factory.mktemp("fit") / "full.json"
    res = run("fit", CAL, "--robot", IIWA, "--method", "full", "-o", out)
    assert res.exit_code == 0, res.output
    return out


def test_calibrated_export_has_the_identified_kinematics_in_yourdfpy_and_on_reimport(tmp_path, full_fit):
    doc = json.loads(full_fit.read_text())
    out = tmp_path / "iiwa_cal.urdf"
    # --entered none: the arm as it was measured (the default, auto, describes it after the
    # result's controller offsets are entered: tests/calib/test_calibrated.py)
    res = run("model", "export", IIWA, "--result", full_fit, "-o", out, "--check", "50", "--entered", "none")
    assert res.exit_code == 0, res.output
    assert "FK check of the URDF read by yourdfpy, 50 configurations" in res.output
    assert "FK check of the URDF re-imported, 50 configurations" in res.output
    nominal = load_robot_model(IIWA)
    chain = Chain(nominal)
    params = np.array([p["value"] for p in doc["parameters"]], dtype=float)
    angle = np.array([p["unit"] == "deg" for p in doc["parameters"]])
    params[angle] = np.radians(params[angle])
    q = random_configurations(nominal, 40, seed=10)
    fitted = chain.fk(q, params)  # the fit's own kinematics, from result.json
    in_urdf = urdf_fk(load_urdf(out), nominal.axis_names, "base_link", "flange", q)
    assert fk_difference(in_urdf, fitted)[0] < 1e-6
    assert fk_difference(in_urdf, chain.fk(q))[0] > 1.0  # and it is not the nominal arm
    # The corrected model file the fit wrote beside result.json agrees as well.
    corrected = load_robot_model(doc["model_file"])
    assert fk_difference(Chain(corrected).fk(q), in_urdf)[0] < 1e-6
    again = tmp_path / "again.yaml"
    assert run("model", "import", out, "-o", again, "--check", "20").exit_code == 0
    assert fk_difference(Chain(load_robot_model(again)).fk(q), fitted)[0] < 1e-6


def test_offset_fit_export_applies_offsets_links_and_tool_and_says_which_stay_nominal(tmp_path):
    fit_out = tmp_path / "fast.json"
    res = run("fit", CAL, "--robot", IIWA, "--method", "fast", "--draws", "300", "--random-configs", "100", "-o", fit_out)
    assert res.exit_code == 0, res.output
    doc = json.loads(fit_out.read_text())
    out = tmp_path / "iiwa_off.urdf"
    res = run("model", "export", IIWA, "--result", fit_out, "-o", out, "--check", "30", "--entered", "none")
    assert res.exit_code == 0, res.output
    fitted = {e["joint"]: e["value_deg"] for e in doc["joint_offsets"] if e["status"] == "fitted"}
    kept = [e["joint"] for e in doc["joint_offsets"] if e["status"] != "fitted"]
    assert fitted and all(f"{ax}.offset kept nominal" in res.output for ax in kept)
    nominal = load_robot_model(IIWA)
    chain = Chain(nominal)
    # The fit's own arm, from result.json: offsets, the link terms it estimated alongside them
    # (--method fast marginalises a link prior) and the fitted marker.
    params = chain.nominal.copy()
    params[:nominal.n_joints] = np.radians([fitted.get(ax, 0.0) for ax in nominal.axis_names])
    links = doc["diagnostics"]["link_prior"]["parameters"]
    assert links
    for name, entry in links.items():
        kind = name.rsplit(".", 1)[1]
        params[chain.param_names.index(name)] += np.radians(entry["mean"]) if kind in ("alpha", "beta") else entry["mean"]
    q = random_configurations(nominal, 30, seed=11)
    in_urdf = urdf_fk(load_urdf(out), nominal.axis_names, "base_link", "flange", q)
    assert fk_difference(in_urdf, chain.fk(q, params))[0] < 1e-6
    offsets_only = chain.fk(q + params[:nominal.n_joints])
    assert fk_difference(in_urdf, offsets_only)[0] > 0.05  # the link terms are in it, not only the offsets


def test_export_of_a_result_on_the_wrong_model_is_refused(tmp_path, full_fit):
    res = run("model", "export", ROOT / "fixtures" / "robots" / "kuka_iiwa7_r800.yaml", "--result", full_fit,
              "-o", tmp_path / "x.urdf")
    assert res.exit_code == 2 and "give the nominal model the fit used" in res.output
    assert not (tmp_path / "x.urdf").exists()


def test_the_model_commands_do_not_load_yourdfpy_until_used():
    code = ("import sys, acquire.commands.model; "
            "print(sorted(m for m in ('yourdfpy', 'trimesh', 'lxml', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT), "PATH": ""}, check=True)
    assert out.stdout.strip() == "[]"


def test_import_of_a_malformed_urdf_exits_non_zero_and_writes_nothing(tmp_path):
    """A 2-joint URDF with an unclosed <link> (recovered by yourdfpy, it has 1 joint)."""
    urdf = tmp_path / "two.urdf"
    urdf.write_text((URDFS / "unclosed_link.urdf").read_text())
    out = tmp_path / "two.yaml"
    res = subprocess.run([sys.executable, "-m", "acquire", "model", "import", str(urdf), "-o", str(out)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.startswith(f"error: {urdf}:10:") and "Opening and ending tag mismatch" in res.stderr
    assert "Traceback" not in res.stderr and "Using different parsing approach" not in res.stderr
    assert not out.exists()


UR10 = ROOT / "fixtures" / "robots" / "ur10.yaml"


@pytest.mark.parametrize("fmt,name", [("ur", "ur10_calibration.yaml"), ("urdf", "ur10.urdf"), ("model", "ur10_cal.yaml")])
def test_export_of_a_compliance_fit_writes_the_sag_beside_the_kinematics_and_checks_both(tmp_path, fmt, name):
    from calib.robot.calibrated import apply_result
    from calib.robot.sag_file import read_sag_file
    from tests.calib.calibrated_sim import full_result

    nominal = load_robot_model(UR10)
    doc = full_result(nominal, seed=5)
    result = tmp_path / "result.json"
    result.write_text(json.dumps(doc))
    out = tmp_path / name
    res = run("model", "export", UR10, "--result", result, "--format", fmt, "-o", out, "--check", "40")
    assert res.exit_code == 0, res.output
    sag = out.with_name(out.stem + ".sag.yaml")
    assert f"the gravity sag cannot be in a {fmt} file: wrote it as data to {sag}" in res.output
    assert "with the sag of" in res.output and "FAILED" not in res.output
    assert "J2.a" in res.output and "J3.compliance" in res.output  # links and compliance applied, and said so
    truth = apply_result(nominal, doc)
    back = read_sag_file(sag)
    q = random_configurations(nominal, 30, seed=3)
    assert fk_difference(back.fk(q), truth.fk(q))[0] < 1e-6
    if fmt == "ur":
        assert "the model's flange is wrist_3_link" in res.output


def test_export_needs_a_format_it_can_tell(tmp_path):
    res = run("model", "export", UR10, "-o", tmp_path / "x.yaml")
    assert res.exit_code == 2 and "--format" in res.output and "x.yaml" in res.output and not (tmp_path / "x.yaml").exists()
