"""The station judges the robot the controller runs — its nominal arm at the reported angles plus
what is entered, scored held out by ``calib.fit.as_running.score_as_running`` from the archived
MCAP log — never the fit's model (whose in-sample figures a result also carries).

The simulated cell's truth (offsets, link errors, sag) makes the measurements; nothing scored
sees it. Its link errors and sag are what the nominal arm plus offsets cannot take up, so the robot
with the offsets entered is tenths of a millimetre off where the full model claims hundredths."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from acquire.record.recorder import RunLog
from acquire.station.accuracy import run_accuracy
from acquire.station.history import entry_from_result
from acquire.station.states import Policy, robot_state
from calib.fit.as_running import score_as_running
from calib.fit.offsets import FitOptions, fit_mode
from calib.measure.dataset import from_arrays
from calib.plan.poses import plan_poses
from drivers.sim.cell import SimCell
from drivers.sim.config import DEFAULT_CONFIG_PATH, load_sim_config
from drivers.sim.mastering import Mastering

# One xdist worker runs this file: its module fixture (a calibrated cell) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("station/test_accuracy")

SENSOR = "tracker"
NOISE_MM = 0.01
#: What a full model (offsets, links, sag) claims in-sample on such data: the result's metrics.
MODEL_AFTER_MM = 0.02


@pytest.fixture(scope="module")
def cell() -> SimCell:
    return SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=5)


def measure(cell: SimCell, seed: int, corrections_deg=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(q reported (k, n) rad, marker xyz (k, 3) mm in the tracker frame, pose groups, config ids) of
    a short plan measured on ``cell`` whose controller holds ``corrections_deg`` (None: as built)."""
    pp = plan_poses(cell.model, (2000.0, 0.0, 900.0), n=10, seed=seed, min_solutions=2, limit_margin_rad=0.05)
    q = np.stack([c.q for c in pp.configurations])
    mastering = Mastering(cell.model.axis_names, cell.model.controller, corrections_deg)
    q_arm = np.stack([mastering.cell_position(v) for v in q]) if corrections_deg is not None else q
    smr = cell.marker_names.index("smr")
    xyz = cell.true_marker_positions(q_arm, frame=SENSOR)[:, smr]
    xyz = xyz + NOISE_MM * np.random.default_rng(seed).standard_normal(xyz.shape)
    poses = np.array([f"s{seed}p{c.pose}" for c in pp.configurations])
    return q, xyz, poses, [f"{p}-{i}" for i, p in enumerate(poses)]


def write_log(path, cell: SimCell, measured) -> None:
    """The run's MCAP log as a daemon writes it: the robot model's text and one sample per configuration."""
    q, xyz, poses, ids = measured
    model_text = Path(load_sim_config(DEFAULT_CONFIG_PATH).robot).read_text()
    log = RunLog.create(path, run_id=path.stem, plan_text="cell: test\n", model_text=model_text, metadata={})
    for qi, p, pose, cid in zip(q, xyz, poses, ids):
        log.sample({"config_id": cid, "pose": str(pose), "q_measured_deg": np.degrees(qi).tolist(),
                    "markers": [{"sensor": SENSOR, "marker": "smr", "mean_mm": p.tolist(), "std_mm": [NOISE_MM] * 3,
                                 "count": 5}]})
    log.close()


def result_for(model, measured, delta_deg: np.ndarray, *, verdict: str = "enter") -> dict:
    """A result.json: offsets to enter δ (the ``entered`` section), the full model's joint offsets (not
    those), and the model's own in-sample accuracy (metrics) — what the station must not judge by."""
    axes = model.axis_names
    return {"format": "remaster.fit/1", "data": {"n_configurations": len(measured[3])},
            "joint_offsets": [{"joint": a, "value_deg": float(d) + 0.05, "std_deg": 0.002, "identifiable": True,
                               "status": "fitted"} for a, d in zip(axes, delta_deg)],
            "metrics": {"absolute": {"before": {"mean": 2.0}, "after": {"mean": MODEL_AFTER_MM}}},
            "entered": {"verdict": verdict, "reasons": [] if verdict == "enter" else ["not better held out"],
                        "offsets": [{"joint": a, "index": i + 1, "value_deg": float(d), "std_deg": 0.002,
                                     "enter": verdict == "enter"} for i, (a, d) in enumerate(zip(axes, delta_deg))]}}


@pytest.fixture(scope="module")
def calibration(cell, tmp_path_factory):
    """A calibration run's log, its data and the offsets δ (deg) fitted for the controller."""
    measured = measure(cell, seed=1)
    q, xyz, poses, ids = measured
    data = from_arrays(q, xyz, marker="smr", sensor=SENSOR, pose=poses, config=np.array(ids))
    mf = fit_mode(cell.model, data, FitOptions(link_tolerance=None, compliance=False))
    delta = np.degrees(mf.post.full_vector(mf.theta)[: cell.model.n_joints])
    path = tmp_path_factory.mktemp("cal") / "cal-1.mcap"
    write_log(path, cell, measured)
    return path, data, delta, measured


def test_the_station_scores_the_nominal_arm_plus_what_is_entered(cell, calibration):
    path, data, delta, measured = calibration
    acc = run_accuracy(path, result_for(cell.model, measured, delta))
    before = score_as_running(cell.model, data).summary()["mean_mm"]
    after = score_as_running(cell.model, data, joint_shift_rad=np.radians(delta)).summary()["mean_mm"]
    assert acc["before"] == pytest.approx(before, rel=1e-9) and acc["after"] == pytest.approx(after, rel=1e-9)
    assert acc["n"] == len(measured[3]) and "nominal arm" in acc["how"]
    assert acc["after"] < 0.5 * acc["before"]            # entering δ helps the robot …
    assert acc["after"] > 3 * MODEL_AFTER_MM              # … but it is not the full model the result describes
    # what is entered decides: the other sign makes it worse, "do not enter" leaves it as found
    wrong = run_accuracy(path, result_for(cell.model, measured, -delta))
    assert wrong["before"] == pytest.approx(acc["before"]) and wrong["after"] > acc["before"]
    refused = run_accuracy(path, result_for(cell.model, measured, delta, verdict="do not enter"))
    assert refused["after"] == pytest.approx(refused["before"])


def test_a_stable_robot_after_its_entry_is_within_tolerance(cell, calibration, tmp_path):
    """The reference's limit is what the robot runs with its values entered; a check measured after
    the entry (the controller's zeros corrected by −δ) is within it. Judged by the model's 0.02 mm,
    the same stable robot would be out of tolerance."""
    path, _, delta, measured = calibration
    t0 = datetime(2026, 3, 1, tzinfo=timezone.utc)
    cal_result = result_for(cell.model, measured, delta)
    ref = entry_from_result(cal_result, run_id="cal-1", finished=t0.isoformat(), site="s", cell="c",
                            check_max_configurations=5, accuracy=run_accuracy(path, cal_result))
    assert ref["entered"] and ref["accuracy_mm"]["after"] > 3 * MODEL_AFTER_MM
    after_entry = measure(cell, seed=2, corrections_deg=-delta)
    check_log = tmp_path / "chk-1.mcap"
    write_log(check_log, cell, after_entry)
    chk_result = {"format": "remaster.fit/1", "data": {"n_configurations": len(after_entry[3])},
                  "joint_offsets": [{"joint": a, "value_deg": None, "std_deg": None, "identifiable": False}
                                    for a in cell.model.axis_names],
                  "metrics": {"absolute": {"before": {"mean": MODEL_AFTER_MM}, "after": {"mean": MODEL_AFTER_MM}}}}
    chk = entry_from_result(chk_result, run_id="chk-1", finished=(t0 + timedelta(days=1)).isoformat(), site="s",
                            cell="c", accuracy=run_accuracy(check_log, chk_result))
    state = robot_state([ref, chk], Policy(), now=t0 + timedelta(days=2))
    assert state["state"] == "calibrated", state["reasons"]
    assert state["accuracy_mm"] == chk["accuracy_mm"]["before"] <= state["accuracy_limit_mm"]
    assert state["accuracy_limit_mm"] == pytest.approx(1.5 * ref["accuracy_mm"]["after"])
    assert chk["accuracy_mm"]["before"] > 1.5 * MODEL_AFTER_MM   # the model's limit would flag it


def test_a_run_without_a_readable_log_is_not_scored(cell, tmp_path):
    result = {"joint_offsets": [{"joint": "A1", "value_deg": 0.1, "std_deg": 0.01, "identifiable": True}]}
    assert run_accuracy(None, result)["before"] is None
    bad = tmp_path / "r.mcap"
    bad.write_bytes(b"not an MCAP file")
    acc = run_accuracy(bad, result)
    assert acc["before"] is None and acc["after"] is None and acc["how"].startswith("not scored: r.mcap")
