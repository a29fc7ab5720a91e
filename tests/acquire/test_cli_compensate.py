"""``acquire compensate`` from the command line: a KUKA .dat, an ABB module and a CSV of targets
pre-corrected for a sagging KR 6 whose truth has link errors; the written files, driven through
the nominal controller onto that truth, land on the targets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.cli import app
from calib.ik.compensation import Compensator, pose_error
from calib.io.targets import read_targets
from calib.robot.calibrated import apply_result
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, model_yaml
from calib.robot.transforms import homogeneous, matrix_to_euler_zyx, matrix_to_quat, pose_to_matrix, quat_to_matrix
from tests.calib.calibrated_sim import full_result, with_masses

ROOT = Path(__file__).resolve().parents[2]
KR6 = with_masses(load_robot_model(ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml"))
TAUGHT_DEG = [[10, -80, 100, 20, 40, -30], [-30, -100, 110, -40, -50, 60], [45, -60, 80, 100, 70, 10]]
TOOL = "0,0,150,0,0,0"


@pytest.fixture()
def cell(tmp_path):
    robot = tmp_path / "kr6.yaml"
    robot.write_text(model_yaml(KR6))
    doc = full_result(KR6, seed=4)
    result = tmp_path / "result.json"
    result.write_text(json.dumps(doc))
    tool = pose_to_matrix(np.array([0, 0, 150.0]), np.zeros(3))
    poses = Chain(KR6).fk(np.radians(TAUGHT_DEG)) @ tool
    return robot, result, doc, tool, poses


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def landed_mm(doc, tool, fmt, path, poses) -> np.ndarray:
    """Each written target commanded to the nominal controller (its IK, the taught configuration),
    where the true arm's TCP ends up, against the original target (mm)."""
    comp = Compensator(KR6, apply_result(KR6, doc), tool)
    out = []
    for t, pose, q in zip(read_targets(path).targets, poses, np.radians(TAUGHT_DEG)):
        v = t.values
        written = (homogeneous(quat_to_matrix(np.array(v[3:])), np.array(v[:3])) if fmt == "rapid"
                   else pose_to_matrix(np.array(v[:3]), np.radians(v[3:])))
        sols = comp.controller_solutions(written).q
        q_ctrl = sols[np.argmin(np.max(np.abs(sols - q), axis=1))]
        out.append(np.linalg.norm(pose_error(pose, comp.true_pose(q_ctrl))[0]))
    return np.array(out)


def test_a_kuka_dat_is_compensated_keeping_status_turn_and_every_other_byte(tmp_path, cell):
    robot, result, doc, tool, poses = cell
    lines = ["&ACCESS RVP", "DEFDAT  weld", ";FOLD EXTERNAL DECLARATIONS", ";ENDFOLD"]
    for i, (pose, q) in enumerate(zip(poses, TAUGHT_DEG)):
        a, b, c = np.degrees(matrix_to_euler_zyx(pose[:3, :3]))
        turn = sum(1 << k for k, v in enumerate(q) if v < 0)
        x, y, z = pose[:3, 3]
        lines.append(f"DECL E6POS XP{i + 1}={{X {x:.4f},Y {y:.4f},Z {z:.4f},A {a:.4f},B {b:.4f},C {c:.4f},S 2,T {turn},"
                     "E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,E6 0.0}")
        lines.append(f"DECL FDAT FP{i + 1}={{TOOL_NO 1,BASE_NO 0,IPO_FRAME #BASE,POINT2[] \" \"}}")
    lines.append("ENDDAT")
    src = tmp_path / "weld.dat"
    src.write_text("\r\n".join(lines) + "\r\n")
    out = tmp_path / "weld_comp.dat"
    res = run("compensate", src, "--robot", robot, "--result", result, "--tool", TOOL, "-o", out)
    assert res.exit_code == 0, res.output
    assert "(ok; tolerance 0.001 mm" in res.output and f"wrote {out}" in res.output
    before, after = src.read_text().split("\n"), out.read_text().split("\n")
    assert len(before) == len(after)
    for b, a in zip(before, after):
        if b.startswith("DECL E6POS"):
            assert b != a and b.split(",S ")[1] == a.split(",S ")[1]  # S, T, E… kept
        else:
            assert b == a
    # the program's targets were ~1 mm off on this robot; the compensated ones land within rounding
    src_miss = landed_mm(doc, tool, "kuka", src, poses)
    assert src_miss.min() > 0.3 and landed_mm(doc, tool, "kuka", out, poses).max() < 1e-3


def test_an_abb_module_is_compensated_keeping_confdata(tmp_path, cell):
    robot, result, doc, tool, poses = cell
    rows = []
    for i, (pose, q) in enumerate(zip(poses, TAUGHT_DEG)):
        w, x, y, z = matrix_to_quat(pose[:3, :3])
        cf = [math.floor(q[k] / 90) for k in (0, 3, 5)]
        p = pose[:3, 3]
        rows.append(f"    CONST robtarget p{i + 1}0:=[[{p[0]:.4f},{p[1]:.4f},{p[2]:.4f}],[{w:.9f},{x:.9f},{y:.9f},{z:.9f}],"
                    f"[{cf[0]},{cf[1]},{cf[2]},0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]];")
    src = tmp_path / "Weld.mod"
    src.write_text("MODULE Weld\n" + "\n".join(rows) + "\n    PROC main()\n    ENDPROC\nENDMODULE\n")
    out = tmp_path / "Weld_comp.mod"
    joints = tmp_path / "joints.csv"
    res = run("compensate", src, "--robot", robot, "--result", result, "--tool", TOOL, "-o", out, "--joint-targets", joints)
    assert res.exit_code == 0, res.output
    for b, a in zip(read_targets(src).targets, read_targets(out).targets):
        assert a.config == b.config and a.values != b.values
    assert landed_mm(doc, tool, "rapid", out, poses).max() < 1e-3
    q = np.array([[float(v) for v in row.split(",")[7:13]] for row in joints.read_text().splitlines()[1:]])
    np.testing.assert_allclose(q, TAUGHT_DEG, atol=0.5)  # the joint targets: near the taught joints, not equal


def test_a_csv_is_compensated_and_bad_targets_stop_everything(tmp_path, cell):
    robot, result, doc, tool, poses = cell
    src = tmp_path / "t.csv"
    lines = ["name,x,y,z,a,b,c,q1,q2,q3,q4,q5,q6"]
    for i, (pose, q) in enumerate(zip(poses, TAUGHT_DEG)):
        abc = np.degrees(matrix_to_euler_zyx(pose[:3, :3]))
        lines.append(",".join([f"t{i}", *(f"{v:.6f}" for v in (*pose[:3, 3], *abc)), *(str(v) for v in q)]))
    src.write_text("\n".join(lines) + "\n")
    out = tmp_path / "t_comp.csv"
    res = run("compensate", src, "--robot", robot, "--result", result, "--tool", TOOL, "-o", out)
    assert res.exit_code == 0, res.output
    assert landed_mm(doc, tool, "csv", out, poses).max() < 1e-3
    src.write_text("\n".join(lines + ["far,5000,0,500,0,0,0,0,-90,90,0,45,0"]) + "\n")
    out2 = tmp_path / "t2.csv"
    res = run("compensate", src, "--robot", robot, "--result", result, "--tool", TOOL, "-o", out2)
    assert res.exit_code == 2 and f"{src}:5: far: the controller cannot reach it" in res.output
    assert "nothing written" in res.output and not out2.exists()


def test_the_entered_offsets_assumption_is_said_and_can_be_overridden(tmp_path, cell):
    robot, result, doc, tool, poses = cell
    src = tmp_path / "t.csv"
    abc = np.degrees(matrix_to_euler_zyx(poses[0][:3, :3]))
    src.write_text("name,x,y,z,a,b,c\n" + ",".join(["t0", *(f"{v:.6f}" for v in (*poses[0][:3, 3], *abc))]) + "\n")
    res = run("compensate", src, "--robot", robot, "--result", result, "--entered", "result", "-o", tmp_path / "x.csv")
    assert res.exit_code == 2 and "records no entered offsets" in " ".join(res.output.replace("│", " ").split())
    doc["entered"] = {"verdict": "enter", "offsets": [{"joint": "A2", "index": 2, "value_deg": 0.1, "enter": True}],
                      "heldout": {"scored_on": "validation", "as_found": {"rms_mm": 1.2}, "full_model": {"rms_mm": 0.05}}}
    result.write_text(json.dumps(doc))
    auto, none = tmp_path / "auto.csv", tmp_path / "none.csv"
    res = run("compensate", src, "--robot", robot, "--result", result, "-o", auto, "--near", "10,-80,100,20,40,-30")
    assert res.exit_code == 0 and "after entering A2 +0.1000° (the offsets" in res.output
    assert "give --entered none if they are not on the controller" in res.output
    assert "predicted by the fit, held out (validation): the compensated robot lands within 0.0500 mm rms" in res.output
    res = run("compensate", src, "--robot", robot, "--result", result, "--entered", "none", "-o", none,
              "--near", "10,-80,100,20,40,-30")
    assert res.exit_code == 0 and "no offsets entered since (--entered none)" in res.output
    a, n = (np.array(read_targets(p).targets[0].values) for p in (auto, none))
    assert np.linalg.norm(a[:3] - n[:3]) > 0.1  # 0.1° on A2 moves the TCP by about a millimetre


def test_a_seven_axis_arm_gets_its_arm_angle_with_each_corrected_pose(tmp_path):
    """A redundant arm reaches a pose in a continuum of configurations: the corrected pose lands
    only with the arm angle written beside it, and the read-back holds the controller to it."""
    iiwa = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    doc = full_result(iiwa, seed=2)
    result = tmp_path / "result.json"
    result.write_text(json.dumps(doc))
    src = tmp_path / "t.csv"
    rows = ["name,x,y,z,a,b,c"]
    for i, q in enumerate([[10, 40, 5, -70, 10, 50, 0], [-30, 60, -10, -50, 20, -40, 30]]):
        t = Chain(iiwa).fk(np.radians(q))
        rows.append(",".join([f"p{i}", *(f"{v:.6f}" for v in (*t[:3, 3], *np.degrees(matrix_to_euler_zyx(t[:3, :3]))))]))
    src.write_text("\n".join(rows) + "\n")
    out = tmp_path / "out.csv"
    res = run("compensate", src, "--robot", ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml", "--result", result, "-o", out)
    assert res.exit_code == 0, res.output
    assert out.read_text().splitlines()[0].endswith(",shift_mm,arm_angle_deg") and "(ok; tolerance" in res.output
    dat = tmp_path / "t.dat"
    dat.write_text("DECL E6POS XP1={X 600,Y 0,Z 500,A 0,B 90,C 0,S 2,T 0}\n")
    res = run("compensate", dat, "--robot", ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml", "--result", result,
              "-o", tmp_path / "o.dat")
    assert res.exit_code == 2 and "give the targets as CSV" in " ".join(res.output.replace("│", " ").split())
