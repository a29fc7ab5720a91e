"""``acquire fit`` on socket data: the real iiwa 14 sockets written as our CSV format."""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.cli import app
from calib.robot.model import load_robot_model
from calib.fit.socket import read_hole_folder
from calib.report.report_format import fixed

ROOT = Path(__file__).resolve().parents[2]
IIWA = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"
REAL = ROOT.parent / "shared" / "fixtures" / "socket-iiwa14-platonics"


@pytest.fixture()
def socket_csv(tmp_path):
    if not REAL.is_dir():
        pytest.skip(f"shared socket data not found at {REAL}")
    ds = read_hole_folder(REAL)
    lines = ["# real iiwa 14 socket data (platonics-delft), in degrees", "# socket_distance_mm: 50",
             "config," + ",".join(f"q{i}" for i in range(1, 8)) + ",placement,socket"]
    for i, (q, g) in enumerate(zip(np.degrees(ds.q_rad), ds.group)):
        lines.append(f"c{i:03d}," + ",".join(f"{v:.9f}" for v in q) + ",{},{}".format(*ds.groups[g]))
    path = tmp_path / "sockets.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_acquire_fit_takes_socket_data_and_scores_held_out_placements(tmp_path, socket_csv):
    out, report = tmp_path / "result.json", tmp_path / "report.html"
    r = CliRunner().invoke(app, ["fit", str(socket_csv), "--robot", str(IIWA), "--method", "fast", "-o", str(out),
                                 "--report", str(report)])
    assert r.exit_code == 0, r.output
    assert "A1     " in r.output and "undetermined" in r.output and "held-out placements" in r.output
    doc = json.loads(out.read_text())
    # the report states what result.json states (its full reading: tests/calib/test_report_socket.py)
    page = html.unescape(re.sub(r"<[^>]+>", "", report.read_text()))
    assert f"method fast — fitted model: {doc['fit_model']['description']}" in page
    for j in doc["joint_offsets"]:
        if j["value_deg"] is not None:
            lo, hi = (fixed(v, 4, sign=True) for v in j["ci95_deg"])
            assert f"{j['joint']}{fixed(j['value_deg'], 4, sign=True)}{fixed(j['std_deg'], 4)}[{lo}, {hi}]" in page
    for h in doc["scores"]["held_out"]:
        assert f"{fixed(h['before']['spread_mm'], 3)} → {fixed(h['after']['spread_mm'], 3)}" in page
    assert f"σ = {fixed(doc['sigma_point_mm'], 4)} mm" in page
    assert doc["kind"] == "socket" and doc["trusted"]
    status = [j["status"] for j in doc["joint_offsets"]]
    assert status[0] == status[6] == "undetermined" and status[1:5] == ["fitted"] * 4
    # A6 moves the ball little in this data: under the link prior its interval is too wide to enter.
    assert status[5] == "do not enter" and "weakly determined" in doc["joint_offsets"][5]["reason"]
    after = [h["after"]["spread_mm"] for h in doc["scores"]["held_out"]]
    assert np.mean(after) <= 0.30
    # The corrected model carries the ball as its tool and loads back.
    model = load_robot_model(out.with_name("result.model.yaml"))
    assert [m.name for m in model.tool.markers] == ["ball"]
    assert abs(model.tool.markers[0].xyz[2] - doc["ball_mm"]["value"][2]) < 1e-6


@pytest.mark.slow  # 6 CPU-s; the socket default fit's choice: test_run_fit_choice.py (a socket run) and test_socket_choice.py (real sockets)
def test_default_chooses_the_socket_model_by_held_out_placements_and_says_so(tmp_path, socket_csv):
    """``acquire fit`` without --method on socket data: the candidates' table (held-out placements),
    the chosen model named in the summary and result.json, its link prior from the evidence."""
    out = tmp_path / "result.json"
    r = CliRunner().invoke(app, ["fit", str(socket_csv), "--robot", str(IIWA), "--compliance", "-o", str(out)])
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    mc, fm = doc["model_choice"], doc["fit_model"]
    assert mc["grouped_by"] == "placement" and mc["folds"] == 3
    names = [c["model"] for c in mc["candidates"]]
    assert names == ["offsets+compliance", "offsets+ball+compliance", "offsets+ball+links+compliance", "full+compliance"]
    assert fm["method"] == "auto" and fm["model"] == mc["chosen"]
    assert f"method: auto — model {mc['chosen']} — fitted model: {fm['description']}" in r.output
    for name in ["nominal (data sheet, ball from the training data)"] + names:
        assert name in r.output
    links = mc["link_scale"]["offsets+ball+links+compliance"]
    assert not links.get("given") and links["length_mm"] > 0 and links["angle_deg"] > 0
    chosen = next(c for c in mc["candidates"] if c["model"] == mc["chosen"])
    assert chosen["cv_mean_mm"] < 0.6 * mc["nominal"]["cv_mean_mm"]  # the real arm is predicted better
    assert doc["trusted"] and any(j["status"] == "fitted" for j in doc["joint_offsets"])
    forced = CliRunner().invoke(app, ["fit", str(socket_csv), "--robot", str(IIWA), "--model", "offsets+bogus"])
    assert forced.exit_code == 2 and "known: offsets" in forced.output


def test_sensor_options_are_refused_for_socket_data(socket_csv):
    r = CliRunner().invoke(app, ["fit", str(socket_csv), "--robot", str(IIWA), "--fix-registration"])
    assert r.exit_code == 2 and "do not apply to socket data" in r.output


def test_full_method_identifies_without_the_prior_and_agrees_with_fast(tmp_path, socket_csv):
    docs = {}
    for method in ("fast", "full"):
        out = tmp_path / f"{method}.json"
        r = CliRunner().invoke(app, ["fit", str(socket_csv), "--robot", str(IIWA), "--method", method, "-o", str(out)])
        assert r.exit_code == 0, r.output
        docs[method] = json.loads(out.read_text())
        # The summary and result.json say which method and which model of the arm ran.
        fm = docs[method]["fit_model"]
        assert fm["method"] == method and f"method: {method} — fitted model: {fm['description']}" in r.output
        if method == "fast":
            assert fm["link_prior"] == {"mm": 0.2, "deg": 0.02} and "fixed prior of ±0.2 mm / ±0.02°" in fm["description"]
        else:
            assert fm["link_prior"] is None and "without a prior" in fm["description"]
    fast, full = (docs[m]["joint_offsets"] for m in ("fast", "full"))
    for a, b in zip(fast[1:5], full[1:5]):  # A2–A5 agree within their intervals
        assert abs(a["value_deg"] - b["value_deg"]) < 2 * max(a["std_deg"], b["std_deg"])
    assert "A6.a" in docs["full"]["identifiability"]["excluded"]  # weak without a prior: left out, said so
    assert full[5]["status"] == "fitted" and full[5]["std_deg"] < 0.01
