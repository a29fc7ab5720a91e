"""Socket (sensorless) calibration end to end: ``acquire run`` on a socket plan against the
simulated socket cell — the fake Sunrise over real FRI on loopback, the cell's operator
hand-guiding the ball into the true sockets — interrupted, resumed, and fitted by the socket fit,
which must recover the cell's hidden offsets within its 95 % intervals."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from acquire.plan.schema import load_plan, resolve_configurations
from acquire.record.recorder import read_run
from drivers.sim.cell import SimCell

from run_helpers import RUN_TIMEOUT_S, fake_controller, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.timeout(RUN_TIMEOUT_S)


def socket_plan(tmp_path: Path, **overrides) -> Path:
    doc = yaml.safe_load((ROOT / "fixtures" / "plans" / "example-socket.yaml").read_text())
    doc["robot"] = str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    doc["fake"]["sim_config"] = str(ROOT / "fixtures" / "sim" / "socket.yaml")
    doc["output"]["folder"] = str(tmp_path / "runs")
    for section, values in overrides.items():
        doc.setdefault(section, {}).update(values)
    path = tmp_path / "socket.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@pytest.mark.slow  # a recovery study over a whole socket run; resume is covered by test_run_resume.py, the socket run by the button test below
def test_socket_run_interrupted_resumed_and_fitted_recovers_the_hidden_offsets(tmp_path):
    lp = load_plan(socket_plan(tmp_path))
    configs = resolve_configurations(lp)
    assert len(configs) == 36 and all(c.socket is not None for c in configs)

    # first part: stop after some configurations, as an operator's Ctrl-C would
    first = fake_controller(lp, fit=False)
    first.start()
    deadline = time.monotonic() + 300
    while first.status()["measured"] < 8 and time.monotonic() < deadline and first.status()["state"] not in ("finished", "failed"):
        time.sleep(0.2)
    first.abort("test: stop halfway")
    part = wait_for_run(first)
    assert part.state == "aborted"
    done_before = {s["config_id"] for s in read_run(part.log_path).samples}
    assert 8 <= len(done_before) < len(configs)

    rc = fake_controller(lp, resume=part.log_path)
    rc.start()
    summary = wait_for_run(rc)
    assert summary.state == "finished", summary.reason
    contents = read_run(summary.log_path)
    ids = [s["config_id"] for s in contents.samples]
    assert len(ids) == len(set(ids))  # nothing measured twice
    # every configuration measured, or (an FRI link dropping under machine load) failed with a reason
    not_measured = {e["config_id"]: e["reason"] for e in contents.events if e["kind"] in ("skipped", "failed")}
    assert set(ids) | set(not_measured) == {c.config_id for c in configs}
    assert all(not_measured[c] for c in set(not_measured) - set(ids))
    assert len(ids) >= 0.85 * len(configs)
    by_id = {c.config_id: c for c in configs}
    for rec in contents.samples:
        placement, socket = by_id[rec["config_id"]].socket
        assert rec["socket"]["placement"] == placement and rec["socket"]["socket"] == socket
        assert rec["socket"]["trigger"] == "still" and rec["markers"] == []
        # the operator pushed the arm off the approach: measured ≠ commanded, by a hand's push
        push = np.abs(np.subtract(rec["q_measured_deg"], rec["q_target_deg"]))
        assert 0.01 < push.max() < 5.0

    doc = json.loads(summary.result_path.read_text())
    assert doc["kind"] == "socket"
    cell = SimCell.from_yaml(ROOT / "fixtures" / "sim" / "socket.yaml")
    truth = cell.truth.offsets_deg
    status = {j["joint"]: j for j in doc["joint_offsets"]}
    # what socket data cannot determine is said, not given a number: A1 (rotation about the
    # base z axis) and the last axis (it only turns the ball within the flange frame)
    for ax in ("A1", "A7"):
        assert status[ax]["status"] == "undetermined" and status[ax]["value_deg"] is None
    for j in doc["joint_offsets"]:
        if j["value_deg"] is None:
            continue
        lo, hi = j["ci95_deg"]
        assert lo <= truth[j["index"] - 1] <= hi, (j["joint"], j["value_deg"], truth[j["index"] - 1], j["ci95_deg"])
    comp = {c["joint"]: c for c in doc["compliance"]}
    true_c = cell.truth.compliance_rad_per_nm
    assert comp["A2"]["status"] == "fitted"
    assert abs(comp["A2"]["value"] - true_c[1]) <= 1.96 * comp["A2"]["std"]
    # held out: each placement scored by a fit on the other two, better than the nominal model
    held = doc["scores"]["held_out"]
    assert sorted(h["placement"] for h in held) == ["front", "left_back", "raised_left"]
    for h in held:
        assert h["after"]["spread_mm"] < 0.5 * h["before"]["spread_mm"]
        assert h["after"]["spread_mm"] < 0.2 and h["after"]["distance_error_mm"] < 0.1
    assert Path(doc["model_file"]).is_file()
    assert doc["sigma_point_mm"] < 0.1
    # the report beside the log (read in full by tests/calib/test_report_socket.py)
    assert summary.report_path == summary.log_path.with_name("report.html")
    page = summary.report_path.read_text()
    assert f"method <b>{doc['method']}</b>" in page and all(h["placement"] in page for h in held)

    # the log fits again later, as any run's: `acquire fit RUN.mcap` sees the socket records and, by
    # the run's method (the plan's; `acquire fit` would choose its model), gives the run's answer
    from typer.testing import CliRunner

    from acquire.cli import app

    out = CliRunner().invoke(app, ["fit", str(summary.log_path), "--robot", str(lp.model_path), "--compliance",
                                   "--method", doc["method"], "-o", str(tmp_path / "refit.json")])
    assert out.exit_code == 0, out.output
    refit = json.loads((tmp_path / "refit.json").read_text())
    assert refit["data"]["distances_mm"] and refit["data"]["n_configurations"] == len(ids)
    for a, b in zip(refit["joint_offsets"], doc["joint_offsets"]):
        assert (a["value_deg"] is None) == (b["value_deg"] is None)
        if a["value_deg"] is not None:
            assert a["value_deg"] == pytest.approx(b["value_deg"], abs=1e-9)


def test_socket_run_confirmed_by_the_button_on_the_flange(tmp_path):
    """The operator confirms with the media flange's button, an input the robot application shares
    over FRI (the fake Sunrise's ``readIORequest``; the cell's operator presses it once the ball
    sits). With a stillness window longer than he holds the ball, every recording is the button's,
    taken while the ball is held in the socket."""
    doc = yaml.safe_load(socket_plan(tmp_path).read_text())
    doc["sensors"][0]["url"] = "operator://none?window_s=30&input=MediaFlange.UserButton"
    doc["socket"]["placements"] = doc["socket"]["placements"][:1]
    doc["socket"]["configurations"] = 4
    path = tmp_path / "button.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    lp = load_plan(path)
    configs = resolve_configurations(lp)
    assert len(configs) == 8
    rc = fake_controller(lp, fit=False)
    rc.start()
    summary = wait_for_run(rc)
    assert summary.state == "finished", summary.reason
    contents = read_run(summary.log_path)
    ids = [s["config_id"] for s in contents.samples]
    not_measured = {e["config_id"]: e["reason"] for e in contents.events if e["kind"] in ("skipped", "failed")}
    assert set(ids) | set(not_measured) == {c.config_id for c in configs}
    assert all(not_measured[c] for c in set(not_measured) - set(ids))  # an FRI drop under load says why
    assert len(ids) >= 6
    for rec in contents.samples:
        assert rec["socket"]["trigger"] == "input"
        push = np.abs(np.subtract(rec["q_measured_deg"], rec["q_target_deg"]))
        assert 0.01 < push.max() < 5.0  # recorded with the hand on the arm, the ball in the socket


def test_socket_plan_dry_run_lists_every_socket(tmp_path):
    from typer.testing import CliRunner

    from acquire.cli import app

    out = CliRunner().invoke(app, ["run", str(socket_plan(tmp_path)), "--dry-run"])
    assert out.exit_code == 0, out.output
    for group in ("front/0", "front/1", "left_back/0", "raised_left/1"):
        assert group in out.output
