"""Compensation: targets pre-corrected for a controller with nominal kinematics land on the target
on the real arm — a simulated robot whose truth is the calibrated model (link errors, offsets,
sag), and (slow) the simulated cell fitted from its measurements and scored on its hidden truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.ik.compensation import CompensationError, Compensator, calibrated_joints, pose_error
from calib.robot.calibrated import apply_result, entered_offsets
from calib.robot.gravity import gravity_torques
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import pose_to_matrix
from tests.calib.calibrated_sim import COMPLIANCE, full_result, with_masses

ROOT = Path(__file__).resolve().parents[2]
KR6 = with_masses(load_robot_model(ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml"))
TOOL = pose_to_matrix(np.array([10.0, -5.0, 150.0]), np.radians([0.0, 15.0, 0.0]))


def true_tcp(doc: dict, q: np.ndarray) -> np.ndarray:
    """The simulated robot: the chain with the result's parameters and its sag, computed here."""
    chain = Chain(KR6)
    params = chain.nominal.copy()
    for e in doc["parameters"]:
        params[chain.param_names.index(e["name"])] = math.radians(e["value"]) if e["unit"] == "deg" else e["value"]
    sag = chain.sign * COMPLIANCE * gravity_torques(chain, q, params)
    return chain.fk(q + sag, params) @ TOOL


def targets(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n TCP poses in the KR 6's work space (wrist away from its singularity) and the joints they came from."""
    rng = np.random.default_rng(seed)
    q = np.radians(np.column_stack([rng.uniform(-120, 120, n), rng.uniform(-120, -40, n), rng.uniform(40, 130, n),
                                    rng.uniform(-150, 150, n), rng.uniform(20, 100, n) * rng.choice([-1, 1], n),
                                    rng.uniform(-170, 170, n)]))
    return Chain(KR6).fk(q) @ TOOL, q


def controller_goes_to(comp: Compensator, pose: np.ndarray, like: np.ndarray) -> np.ndarray:
    """The nominal controller commanded ``pose`` in the configuration of ``like``: its own IK."""
    sols = comp.controller_solutions(pose).q
    return sols[int(np.argmin(np.max(np.abs(sols - like), axis=1)))]


def test_compensated_targets_land_on_the_target_through_the_nominal_controller():
    doc = full_result(KR6, seed=8)
    comp = Compensator(KR6, apply_result(KR6, doc), TOOL)
    poses, q_taught = targets(25, seed=1)
    landed, missed = [], []
    for pose, q in zip(poses, q_taught):
        c = comp.compensate(pose, controller_goes_to(comp, pose, q))
        q_ctrl = controller_goes_to(comp, c.corrected, c.joints)
        np.testing.assert_allclose(q_ctrl, c.joints, atol=1e-9)  # the controller reaches the joint target
        landed.append(pose_error(pose, true_tcp(doc, q_ctrl)))
        missed.append(pose_error(pose, true_tcp(doc, controller_goes_to(comp, pose, q))))
    landed_mm = np.linalg.norm([d for d, _ in landed], axis=1)
    missed_mm = np.linalg.norm([d for d, _ in missed], axis=1)
    assert landed_mm.max() < 1e-6 and np.degrees(np.linalg.norm([w for _, w in landed], axis=1)).max() < 1e-7
    assert missed_mm.mean() > 0.5  # uncompensated, the same robot misses by about a millimetre


def test_offsets_entered_since_the_measurement_are_taken_into_account():
    doc = full_result(KR6, seed=9)
    doc["entered"] = {"verdict": "enter", "offsets": [{"joint": ax, "index": i + 1, "value_deg": v, "enter": True}
                                                      for i, (ax, v) in enumerate(zip(KR6.axis_names, [0.05, -0.1, 0.08, 0, 0, 0]))]}
    entered = entered_offsets(doc, KR6)
    after = Compensator(KR6, apply_result(KR6, doc).after_entering(entered), TOOL)
    assumed_none = Compensator(KR6, apply_result(KR6, doc), TOOL)
    poses, q_taught = targets(8, seed=2)
    for pose, q in zip(poses, q_taught):
        q_start = controller_goes_to(after, pose, q)
        good = after.compensate(pose, q_start)
        wrong = assumed_none.compensate(pose, q_start)
        # The controller now shows q + δ_entered where the arm stands at q: the real arm at its angles.
        physical = controller_goes_to(after, good.corrected, good.joints) - entered
        assert np.linalg.norm(pose_error(pose, true_tcp(doc, physical))[0]) < 1e-6
        physical = controller_goes_to(after, wrong.corrected, wrong.joints) - entered
        assert np.linalg.norm(pose_error(pose, true_tcp(doc, physical))[0]) > 0.05


def test_a_target_out_of_reach_is_refused():
    comp = Compensator(KR6, apply_result(KR6, full_result(KR6)), TOOL)
    far = pose_to_matrix(np.array([5000.0, 0, 500]), np.zeros(3))
    rows, why = comp.calibrated_solutions(far)
    assert len(rows) == 0 and "unreachable" in why
    with pytest.raises(CompensationError, match="did not converge"):
        calibrated_joints(comp.arm, far, np.zeros(6))


@pytest.mark.slow
def test_on_the_simulated_cell_compensation_lands_within_the_fits_predicted_error():
    """Fit offsets+tool+links+compliance to the example dataset of the simulated cell, compensate
    held-out targets (the validation configurations' true marker positions, in the sensor frame),
    and drive the nominal controller: the true marker lands within the fit's σ (~17 s)."""
    from calib.fit.offsets import FitOptions, fit_offsets
    from calib.fit.result import result_dict
    from calib.measure.dataset import read_csv
    from drivers.sim.cell import SimCell
    from drivers.sim.config import load_sim_config

    model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    cal = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", model).calibration()
    val = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_val.csv", model)
    fit = fit_offsets(model, cal, FitOptions(method="laplace", compliance=True, link_tolerance=(0.2, 0.02), n_draws=200))
    doc = result_dict(fit, cal)
    arm = apply_result(model, doc)
    # The cell the dataset came from (fixtures/datasets/make_sim.py --seed 7): the truth, for scoring only.
    config = load_sim_config(ROOT / "fixtures" / "sim" / "default.yaml")
    config = config.model_copy(update={"seed": 7, "truth": config.truth.model_copy(
        update={"offsets_deg": [0.477, -0.192, 0.139, 0.099, 0.392, -0.114, 0.936]})})
    cell = SimCell(config)
    k = model.marker_index("sir")
    tool = np.eye(4)
    tool[:3, 3] = arm.model.tool.markers[k].xyz
    comp = Compensator(model, arm, tool)
    base2sensor = np.array(doc["registration"]["mocap"]["base2sensor"])
    q_val = val.q_rad[::3]
    in_sensor = cell.true_marker_positions(q_val, frame="mocap")[:, k]
    in_base = (in_sensor - base2sensor[:3, 3]) @ np.linalg.inv(base2sensor[:3, :3]).T
    landed, missed = [], []
    for q, p_base, p_sensor in zip(q_val, in_base, in_sensor):
        pose = Chain(model).fk(q) @ tool
        pose[:3, 3] = p_base
        q_nominal = controller_goes_to(comp, pose, q)
        c = comp.compensate(pose, q_nominal)
        landed.append(np.linalg.norm(cell.true_marker_positions(c.joints, frame="mocap")[k] - p_sensor))
        missed.append(np.linalg.norm(cell.true_marker_positions(q_nominal, frame="mocap")[k] - p_sensor))
    rms = float(np.sqrt(np.mean(np.square(landed))))
    assert rms < fit.pooled_sigma_mm, (rms, fit.pooled_sigma_mm)  # measured: 0.0027 mm against σ 0.0069 mm
    assert float(np.sqrt(np.mean(np.square(missed)))) > 100 * rms  # uncompensated: 2.6 mm
