"""Compliance together with orientation in full identification: a joint that yields under gravity
turns everything downstream of it, so the sag moves the measured attitude as well as the position;
a simulated 6-DoF cell with sagging joints is fitted with both kinds of rows and its compliances
come back within their intervals, the attitude residual at the noise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.fit.identification import IdentOptions, identify
from calib.measure.dataset import from_arrays
from calib.robot.gravity import gravity_torques
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import exp_so3, log_so3

from tests.calib.pose_sim import BASE2SENSOR

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
UR10 = load_robot_model(ROBOTS / "ur10.yaml")
FRAME = exp_so3(np.radians([2.0, -3.0, 25.0]))  # the target's frame on the flange
K_TRUE = np.array([0.0, 4e-6, 6e-6, 0.0, 0.0, 0.0])  # rad/(N·m): the shoulder and elbow yield
NOISE_MM, NOISE_DEG = 0.02, 0.005


def sagging_cell(q: np.ndarray, rng: np.random.Generator):
    """Pose rows of a UR10 whose joints 2 and 3 sag under gravity (exactly: the arm is walked at the
    deflected angles), its offsets off by a few hundredths of a degree; q (k, 6) rad commanded."""
    chain = Chain(UR10)
    truth = chain.with_offsets(np.radians(rng.normal(0.0, 0.03, 6)))
    q_true = q + chain.sign * K_TRUE * gravity_torques(chain, q, truth)
    m = 0
    p = chain.marker_positions(q_true, truth)[:, m]
    r_f, _ = chain.flange_pose(q_true, truth)
    k = q.shape[0]
    xyz = p @ BASE2SENSOR[:3, :3].T + BASE2SENSOR[:3, 3] + rng.normal(0.0, NOISE_MM, (k, 3))
    rot = exp_so3(rng.normal(0.0, np.radians(NOISE_DEG), (k, 3))) @ BASE2SENSOR[:3, :3] @ r_f @ FRAME
    return from_arrays(q, xyz, marker=chain.marker_names[m], sensor="tracker", std_mm=np.full(k, NOISE_MM),
                       rot=rot, att_std_rad=np.full(k, np.radians(NOISE_DEG)))


def test_compliances_with_orientation_are_recovered_and_the_attitude_residual_is_at_the_noise():
    rng = np.random.default_rng(5)
    q = rng.uniform(UR10.lower_limits_rad * 0.5, UR10.upper_limits_rad * 0.5, (50, 6))
    data = sagging_cell(q, rng)
    result = identify(UR10, data, IdentOptions(compliance=True, n_starts=1))
    assert not [w for w in result.warnings if "orientations not used" in w]
    assert result.attitude_weight is not None  # the attitude rows are in the fit
    fitted = np.isfinite(result.compliance_std)
    assert fitted[1] and fitted[2], result.excluded
    z = (result.compliance[fitted] - K_TRUE[fitted]) / result.compliance_std[fitted]
    assert np.all(np.abs(z) < 4.0), z
    chain = Chain(UR10)
    # The attitude the fit predicts, with the fitted sag turning the flange, against the measured one.
    q_fit = q + chain.sign * result.compliance * gravity_torques(chain, q, result.params)  # the sag at the identified arm, as the fit takes it
    r_f, _ = chain.flange_pose(q_fit, result.params)
    pred = result.base2sensor["tracker"][:3, :3] @ r_f @ result.tool_frames[chain.marker_names[0]]
    att = np.degrees(np.linalg.norm(log_so3(data.rot @ np.swapaxes(pred, 1, 2)), axis=1))
    assert np.mean(att) < 2.5 * NOISE_DEG * np.sqrt(2), np.mean(att)  # χ₃ mean ≈ 1.6 σ
    # Without the sag turning the flange, the same parameters leave the attitude visibly worse.
    r_plain, _ = chain.flange_pose(q, result.params)
    pred_plain = result.base2sensor["tracker"][:3, :3] @ r_plain @ result.tool_frames[chain.marker_names[0]]
    att_plain = np.degrees(np.linalg.norm(log_so3(data.rot @ np.swapaxes(pred_plain, 1, 2)), axis=1))
    assert np.mean(att_plain) > 2 * np.mean(att)


def test_the_zero_offset_posterior_fits_compliances_on_position_and_attitude_rows():
    """The default method's compliance candidate with orientation: the sag's attitude effect is in
    the attitude rows, the compliances come back within their intervals."""
    from calib.fit.offsets import FitOptions, fit_offsets

    rng = np.random.default_rng(6)
    q = rng.uniform(UR10.lower_limits_rad * 0.5, UR10.upper_limits_rad * 0.5, (50, 6))
    data = sagging_cell(q, rng)
    result = fit_offsets(UR10, data, FitOptions(method="laplace", n_draws=300, compliance=True, link_tolerance=None))
    assert result.posterior.attitude is not None
    comp = result.diagnostics["compliance"]
    fitted = [(c, k) for c, k in zip(comp, K_TRUE) if c["status"] == "fitted"]
    assert [c["joint"] for c, _ in fitted] == ["J2", "J3"], comp
    z = [(c["value"] - k) / c["std"] for c, k in fitted]  # seeds 6–13: |z| up to 2.6, rms 1.3
    assert np.all(np.abs(z) < 4.0), z
