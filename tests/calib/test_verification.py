"""The verification's scoring on simulated data: a robot whose controller got the fitted offsets
(through its mastering, as ``drivers.sim.mastering`` enters them) improves as the calibration's
held-out prediction says; entered with the wrong sign it does not, and the verdict says so.

The simulated cell's truth (offsets, link errors, sag) makes the measurements here; the scoring
never sees it."""

from __future__ import annotations

import numpy as np
import pytest

from calib.fit.as_running import predict_entry, score_as_running
from calib.fit.offsets import FitOptions, fit_mode
from calib.fit.verification import summary_lines, verify_entry
from calib.measure.dataset import from_arrays
from calib.plan.poses import plan_poses
from drivers.sim.cell import SimCell
from drivers.sim.config import DEFAULT_CONFIG_PATH
from drivers.sim.mastering import Mastering

# One xdist worker runs this file: its module fixture (a calibrated cell) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("calib/test_verification")

SENSOR = "tracker"
NOISE_MM = 0.01


@pytest.fixture(scope="module")
def cell() -> SimCell:
    return SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=5)


def configurations(cell: SimCell, seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(q (k, n) rad, pose group (k,)) of ``n`` poses aimed at the tracker, every IK branch."""
    pp = plan_poses(cell.model, (2000.0, 0.0, 900.0), n=n, seed=seed, min_solutions=2, limit_margin_rad=0.05)
    q = np.stack([c.q for c in pp.configurations])
    return q, np.array([f"s{seed}p{c.pose}" for c in pp.configurations])


def measured(cell: SimCell, q_reported: np.ndarray, q_arm: np.ndarray, poses: np.ndarray, seed: int):
    """What the tracker measures with the arm at ``q_arm`` while the controller reports ``q_reported``."""
    smr = cell.marker_names.index("smr")
    xyz = cell.true_marker_positions(q_arm, frame=SENSOR)[:, smr]
    xyz = xyz + NOISE_MM * np.random.default_rng(seed).standard_normal(xyz.shape)
    ids = np.array([f"{p}-{i}" for i, p in enumerate(poses)])
    return from_arrays(q_reported, xyz, marker="smr", sensor=SENSOR, pose=poses, config=ids)


@pytest.fixture(scope="module")
def calibrated(cell):
    """The calibration: data, its held-out prediction, and the offsets δ (deg) fitted for the controller."""
    q, poses = configurations(cell, seed=1, n=24)
    cal = measured(cell, q, q, poses, seed=1)  # mastering as built: the controller reports the arm's angles
    prediction = predict_entry(cell.model, cal)
    mf = fit_mode(cell.model, cal, FitOptions(link_tolerance=None, compliance=False))
    delta_deg = np.degrees(mf.post.full_vector(mf.theta)[: cell.model.n_joints])
    return cal, prediction, delta_deg


def fresh_after_entry(cell: SimCell, corrections_deg: np.ndarray):
    """Fresh configurations commanded after ``corrections_deg`` went into the controller's mastering."""
    mastering = Mastering(cell.model.axis_names, cell.model.controller, corrections_deg)
    q_cmd, poses = configurations(cell, seed=2, n=24)
    q_arm = np.stack([mastering.cell_position(q) for q in q_cmd])
    return measured(cell, q_cmd, q_arm, poses, seed=2)


def test_the_calibration_predicts_a_real_improvement(calibrated):
    _, prediction, _ = calibrated
    found, entered = prediction["as_found"], prediction["entered"]
    assert found["n"] == entered["n"] >= 20
    assert entered["mean_mm"] < 0.5 * found["mean_mm"]  # 0.3° offsets: millimetres; links and sag: tenths
    lo, hi = prediction["improvement_mm"]["ci95"]
    assert lo < prediction["improvement_mm"]["value"] < hi and lo > 0


def test_entering_the_offsets_improves_the_robot_as_predicted(cell, calibrated):
    cal, prediction, delta = calibrated
    fresh = fresh_after_entry(cell, -delta)  # the correction the controller's zero takes is −δ
    assert not np.isin(fresh.config, cal.config).any()
    doc = verify_entry(cell.model, fresh, delta, prediction)
    assert doc["verdict"] == "as predicted", summary_lines(doc)
    m, p = doc["measured"]["improvement_mm"], doc["predicted"]["improvement_mm"]
    assert m["value"] > 0 and m["ci95"][0] > 0
    assert doc["entry_matches_result"] and doc["measured"]["improvement_replayed_mm"]["ci95"][0] > 0
    lo, hi = doc["predicted"]["interval_for_this_run"]
    assert lo <= p["ci95"][0] and hi >= p["ci95"][1]  # widened by this run's sampling spread only
    # the replayed robot as found and the calibration's held-out one describe the same robot
    assert doc["before"]["replayed"]["mean_mm"] == pytest.approx(doc["before"]["calibration"]["mean_mm"], rel=0.35)
    assert any(line.startswith("verdict: as predicted") for line in summary_lines(doc))


def test_offsets_entered_with_the_wrong_sign_are_found_out(cell, calibrated):
    _, prediction, delta = calibrated
    fresh = fresh_after_entry(cell, +delta)  # the operator typed +δ where −δ was asked for
    doc = verify_entry(cell.model, fresh, delta, prediction)
    assert doc["verdict"] == "worse than predicted", summary_lines(doc)
    assert doc["after"]["mean_mm"] > doc["before"]["calibration"]["mean_mm"]  # the robot got worse
    assert not doc["entry_matches_result"] and "other sign" in doc["notes"][0]


def test_the_scores_are_held_out_and_need_two_folds(cell, calibrated):
    cal, _, _ = calibrated
    one_pose = cal.subset(cal.pose == cal.pose[0])
    with pytest.raises(ValueError, match="pose groups"):
        score_as_running(cell.model, one_pose)
    # the robot as found scored here is the model choice's nominal robot with the tool fitted too
    s = score_as_running(cell.model, cal)
    assert s.errors_mm.size == len(np.unique(cal.config))
