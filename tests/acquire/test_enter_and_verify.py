"""Entering and verifying without a whole run. ``acquire sim``'s mastering lines, as its stdin reader
answers them: ``enter RESULT.json`` puts
the correction of every axis the result enters into the running controller (a result written by
the real ``acquire fit``), ``save`` writes the cell a later ``--fake`` run starts with, and a bad
line changes nothing."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.cli import app
from acquire.commands.sim import _answer
from calib.robot.entered import read_entered
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH, load_sim_config
from drivers.sim.launch import SimLaunch

from run_helpers import ROOT  # noqa: E402 - tests/acquire is on sys.path under pytest

# One xdist worker runs this file: its module fixture (a fit) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("acquire/test_enter_and_verify")


@pytest.fixture(scope="module")
def result_json(tmp_path_factory):
    """A result of the real ``acquire fit`` (the packaged simulated calibration, offsets for the nominal arm)."""
    out = tmp_path_factory.mktemp("fit") / "result.json"
    res = CliRunner().invoke(app, ["fit", str(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"), "--robot",
                                   str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"), "--method", "fast",
                                   "--link-tolerance", "none", "--draws", "200", "-o", str(out)])
    assert res.exit_code == 0, res.output
    return out


def test_enter_a_result_then_save_the_cell_with_its_mastering(result_json, tmp_path):
    values = read_entered(result_json)
    chosen = [e["joint"] for e in json.loads(result_json.read_text())["entered"]["offsets"] if e["enter"]]
    assert values.source == "entered" and [a.axis for a in values.axes] == chosen and len(chosen) >= 4
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, clock=SimClock(4.0))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fri_client:
        fri_client.bind(("127.0.0.1", 0))
        with SimLaunch(cell, fri_port=fri_client.getsockname()[1], max_runtime_s=60) as launch:
            first = launch.controller
            answer = _answer(launch, f"enter {result_json}", DEFAULT_CONFIG_PATH)
            assert answer.startswith(f"entered from {result_json} (entered)"), answer
            assert launch.controller is not first
            expected = np.zeros(7)
            for a in values.axes:
                expected[a.index - 1] = -a.delta_deg  # the zero takes −δ: the reported angle grows by δ
            assert launch.mastering.corrections_deg == pytest.approx(expected, abs=1e-12)
            # bad lines: an error, the table unchanged
            for bad in ("master A8 0.1", f"enter {tmp_path / 'none.json'}", "save", "master A2 x"):
                assert _answer(launch, bad, DEFAULT_CONFIG_PATH).startswith("error: "), bad
            assert launch.mastering.corrections_deg == pytest.approx(expected, abs=1e-12)
            assert "A2 zero" in _answer(launch, "mastering", DEFAULT_CONFIG_PATH)
            saved = tmp_path / "entered.yaml"
            assert _answer(launch, f"save {saved}", DEFAULT_CONFIG_PATH).startswith(f"saved {saved}")
    cfg = load_sim_config(saved)
    assert cfg.controller.mastering_deg == pytest.approx(expected, abs=1e-8)
    # the same robot: the hidden truth is the file's, only the controller's mastering changed
    assert SimCell(cfg).truth.offsets_deg == pytest.approx(cell.truth.offsets_deg)


def test_verify_scores_a_given_log_against_a_prediction_made_from_the_calibration(result_json, tmp_path):
    """``acquire verify --log``: the robot of the packaged validation set had nothing entered, so it
    does worse than the result predicts (exit 3); the prediction is made from the calibration data
    the result names (an older result without ``entered``)."""
    from run_helpers import small_plan

    plan = small_plan(tmp_path, n=6)
    older = tmp_path / "older.json"  # as `acquire fit` wrote it before results recorded what the controller gets
    doc = json.loads(result_json.read_text())
    del doc["entered"]
    older.write_text(json.dumps(doc))
    result_json = older
    val = tmp_path / "val.csv"
    val.write_bytes((ROOT / "fixtures" / "datasets" / "iiwa14_sim_val.csv").read_bytes())
    res = CliRunner().invoke(app, ["verify", str(plan), "--result", str(result_json), "--log", str(val), "--out", str(tmp_path)])
    assert res.exit_code == 3, res.output
    assert "prediction: made here from the calibration log" in res.output
    assert "verdict: worse than predicted" in res.output
    doc = json.loads((tmp_path / "verify.json").read_text())
    assert doc["entered_from"] == "joint_offsets"
    after, found = doc["after"]["mean_mm"], doc["before"]["calibration"]["mean_mm"]
    assert after == pytest.approx(found, rel=0.3)  # nothing entered: the robot is as found
    assert doc["measured"]["improvement_mm"]["value"] < doc["predicted"]["interval_for_this_run"][0]
    assert (tmp_path / "verify.html").read_text().count("<svg") == 1


def test_fresh_configurations_are_the_regions_and_never_the_calibrations(tmp_path):
    from acquire.plan.schema import load_plan, resolve_configurations
    from acquire.run.verify import fresh_configurations
    from calib.io.yamlfile import ConfigError
    from run_helpers import small_plan

    lp = load_plan(small_plan(tmp_path, n=4))
    cal = np.stack([c.q_rad for c in resolve_configurations(lp)])
    fresh = fresh_configurations(lp, poses=4)
    assert fresh and all(c.config_id.startswith("v") for c in fresh)
    q = np.stack([c.q_rad for c in fresh])
    assert np.min(np.abs(q[:, None] - cal[None]).max(axis=-1)) > 1e-3  # another sample of the region
    assert all(lp.model.within_limits(c.q_rad, lp.commander_margin_rad) for c in fresh)
    # a configuration the calibration measured is left out; the plan's own seed is refused
    again = fresh_configurations(lp, poses=4, exclude_q_rad=q[:2] + 1e-5)
    assert [c.config_id for c in again] == [c.config_id for c in fresh[2:]]
    with pytest.raises(ConfigError, match="other than the calibration's"):
        fresh_configurations(lp, poses=4, seed=lp.plan.poses.generated.seed)
