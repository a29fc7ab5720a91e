"""The run's end-of-run fit (``acquire.run.fitting``) compares full identification too: a plan's
``fit.model: full`` (or the data) choosing it writes the corrected model, the identification
report with the model-choice table, and offsets the run summary reads like any other."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from acquire.commands.run_summary import format_run_summary
from acquire.plan.schema import FitSpec
from acquire.run.fitting import _fit_run_auto
from calib.fit.offsets import FitOptions
from calib.robot.model import load_robot_model
from tests.calib.test_model_choice import cell


def test_the_runs_default_compares_full_identification(tmp_path):
    model, _, cal = cell(5, k=24)
    doc, result_path, report_path = _fit_run_auto(tmp_path / "run.mcap", model, cal, None, FitOptions(n_draws=200),
                                                  FitSpec(), 20)
    mc = doc["model_choice"]
    full = next(c for c in mc["candidates"] if c["model"] == "full")
    assert full["failed"] is None and full["cv_mean_mm"] is not None and mc["excluded"] is None
    assert json.loads(result_path.read_text())["model_choice"]["candidates"] == mc["candidates"]
    assert report_path is not None and "full" in report_path.read_text()


def test_a_plan_forcing_full_writes_the_identified_model_and_its_report(tmp_path):
    model, truth, cal = cell(5, k=24)
    doc, result_path, report_path = _fit_run_auto(tmp_path / "run.mcap", model, cal, None, FitOptions(n_draws=200),
                                                  FitSpec(model="full"), 20)
    assert doc["model_choice"]["chosen"] == "full" and doc["model_choice"]["forced"]
    corrected = load_robot_model(Path(doc["model_file"]))
    assert corrected.n_joints == model.n_joints and Path(doc["model_file"]).parent == tmp_path
    assert "id=model-choice" in report_path.read_text()
    # The identified zero-offsets, as the offsets fits give them: wrapped, with intervals, statuses.
    offsets = doc["joint_offsets"]
    assert [j["joint"] for j in offsets] == model.axis_names
    fitted = [j for j in offsets if j["value_deg"] is not None]
    assert len(fitted) >= 4
    assert all(j["status"] == "undetermined" and j["reason"] for j in offsets if j["value_deg"] is None)
    for j in fitted:
        assert -180 < j["value_deg"] <= 180 and j["status"] in ("fitted", "do not enter")
        assert abs(j["value_deg"] - np.degrees(truth[j["index"] - 1])) < 5 * j["std_deg"] + 1e-3
    summary = SimpleNamespace(run_id="r", state="finished", reason="", total=24, measured=24, skipped=0, failed=0,
                              wall_seconds=1.0, cell_seconds=1.0, log_path=tmp_path / "run.mcap", skipped_reasons={},
                              fit=doc, result_path=result_path, report_path=report_path)
    text = format_run_summary(summary, SimpleNamespace(model=model))
    assert "full" in text and "← chosen (--model)" in text and "corrected model (full identification)" in text


def test_a_socket_runs_default_fit_chooses_the_model_and_a_plan_can_fix_the_method(tmp_path, monkeypatch):
    """The end of a socket run (``fit_socket_run_log``): the plan's default ``fit.method: auto`` lets
    the data choose (table in result.json, the chosen model named); ``fast`` keeps the fixed prior."""
    import acquire.run.socket_fit as socket_fit
    from acquire.run.fitting import fit_socket_run_log
    from tests.calib.socket_sim import simulate, true_params
    from calib.robot.kinematics import Chain

    model = load_robot_model(Path(__file__).resolve().parents[2] / "fixtures" / "robots" / "franka_panda.yaml")
    rng = np.random.default_rng(2)
    ds, _ = simulate(model, true_params(Chain(model), rng, link_mm=0.5, twist_deg=0.3), rng, per_socket=10)
    monkeypatch.setattr(socket_fit, "read_socket_run", lambda path, n, distance_mm=None: ds)
    for spec, method in ((FitSpec(), "auto"), (FitSpec(method="fast"), "fast")):
        lp = SimpleNamespace(model=model, plan=SimpleNamespace(fit=spec, socket=SimpleNamespace(distance_mm=50.0)))
        doc, result_path, report_path = fit_socket_run_log(tmp_path / "run.mcap", lp)
        assert doc["fit_model"]["method"] == method and Path(doc["model_file"]).is_file()
        # the report beside the log names the method and model that ran (tests/calib/test_report_socket.py reads it all)
        assert report_path == tmp_path / "report.html" and f"method <b>{method}</b>" in report_path.read_text()
        if method == "auto":
            mc = doc["model_choice"]
            assert doc["fit_model"]["model"] == mc["chosen"] and len(mc["candidates"]) == 4  # no masses: no compliance
            assert json.loads(result_path.read_text())["model_choice"]["chosen"] == mc["chosen"]
        else:
            assert "model_choice" not in doc and doc["fit_model"]["link_prior"] == {"mm": 0.2, "deg": 0.02}
