"""Full kinematic identification: recovery of known errors within the reported uncertainty,
detection of unidentifiable parameters, corrected-model output, the fused orientation objective."""

from pathlib import Path

import numpy as np
import pytest

from calib.measure.dataset import DatasetError, from_arrays
from calib.fit.identification import (
    IdentOptions,
    _Problem,
    comprehensive_errors,
    corrected_model,
    identify,
    pose_errors,
    write_model_yaml,
)
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, robot_model_from_dict
from calib.robot.transforms import exp_so3, pose_to_matrix

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
BASE2SENSOR = pose_to_matrix(np.array([1500.0, 200.0, -300.0]), np.radians([170.0, 10.0, -5.0]))


def measure(model, chain, q, params, rng, noise_mm, base2sensor=BASE2SENSOR):
    """Every marker in every configuration, as a sensor at ``base2sensor`` would see it."""
    k, m = q.shape[0], chain.m
    qq = np.repeat(q, m, axis=0)
    markers = np.tile(np.array(chain.marker_names), k)
    p = chain.marker_positions(qq, params)[np.arange(k * m), np.tile(np.arange(m), k)]
    xyz = p @ base2sensor[:3, :3].T + base2sensor[:3, 3] + rng.normal(0.0, noise_mm, p.shape)
    return from_arrays(qq, xyz, marker=markers)


def perturbed_truth(chain, names, rng, length_mm=0.3, angle_deg=0.02):
    """Nominal parameters with the identifiable ones perturbed by tenths of a mm / hundredths of a degree."""
    idx = [chain.param_names.index(n) for n in names if n in chain.param_names]
    scale = np.array(
        [np.radians(angle_deg) if n.rsplit(".", 1)[1] in ("offset", "alpha", "beta") else length_mm for n in np.array(chain.param_names)[idx]]
    )
    truth = chain.nominal.copy()
    truth[idx] += rng.normal(0.0, 1.0, len(idx)) * scale
    return truth, idx


@pytest.mark.parametrize("robot", ["staubli_tx60", "kuka_kr6_r900_2", "kuka_iiwa14_r820"])
def test_identification_recovers_errors_within_reported_uncertainty(robot):
    model = load_robot_model(ROBOTS / f"{robot}.yaml")
    chain = Chain(model)
    z = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (120, model.n_joints))
        nominal_fit = identify(model, measure(model, chain, q, chain.nominal, rng, 0.0))
        truth, idx = perturbed_truth(chain, nominal_fit.free_names, rng)
        result = identify(model, measure(model, chain, q, truth, rng, 0.02))
        assert result.free_names == nominal_fit.free_names
        errors = result.params[idx] - truth[idx]
        z.append(errors / result.std[idx])
        # The perturbations are far larger than what is left after identification.
        assert np.abs(errors).max() < np.abs(truth[idx] - chain.nominal[idx]).max()
    z = np.concatenate(z)
    coverage = np.mean(np.abs(z) < 1.96)
    assert 0.85 <= coverage, f"95% intervals covered the truth only {coverage:.0%} of the time"
    assert 0.7 < np.sqrt(np.mean(z**2)) < 1.3, "reported uncertainties are not calibrated"


def test_known_unidentifiable_parameters_are_excluded_with_reasons():
    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(0)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (80, 6))
    result = identify(model, measure(model, chain, q, chain.nominal, rng, 0.01))
    # A2 ∥ A3 in standard DH: d2 and d3 shift the arm along the same axis.
    assert "A3.d" in result.excluded and "A2.d" in result.excluded["A3.d"]
    # Axis 1's offset and d1 move every point like a change of the sensor registration.
    assert "A1.offset" in result.excluded and "sensor." in result.excluded["A1.offset"]
    assert "A1.d" in result.excluded
    assert all(name not in result.free_names for name in result.excluded)
    assert np.all(np.isnan(result.std[[chain.param_names.index(n) for n in result.excluded if n in chain.param_names]]))


def test_single_marker_on_the_last_axis_leaves_its_offset_unidentifiable():
    data = load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml").model_dump()
    data["tool"]["markers"] = [{"name": "tip", "xyz": (0.0, 0.0, 50.0)}]
    model = robot_model_from_dict(data)
    chain = Chain(model)
    rng = np.random.default_rng(1)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (60, 7))
    result = identify(model, measure(model, chain, q, chain.nominal, rng, 0.01))
    assert "A7.offset" in result.excluded
    assert "does not move any measured marker" in result.excluded["A7.offset"]


def test_mdh_identifies_torsion_of_parallel_axes_instead_of_offset():
    model = load_robot_model(ROBOTS / "staubli_tx60.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(2)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (80, 6))
    result = identify(model, measure(model, chain, q, chain.nominal, rng, 0.01))
    assert "J2.beta" in result.free_names  # J2 ∥ J3: Hayati's β carries what d cannot
    assert "J3.d" in result.excluded


def test_corrected_model_file_reproduces_the_identified_kinematics(tmp_path):
    model = load_robot_model(ROBOTS / "staubli_tx60.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(3)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (80, 6))
    truth, _ = perturbed_truth(chain, identify(model, measure(model, chain, q, chain.nominal, rng, 0.0)).free_names, rng)
    result = identify(model, measure(model, chain, q, truth, rng, 0.01))
    path = tmp_path / "identified.yaml"
    write_model_yaml(result.corrected_model(), path)
    reloaded = load_robot_model(path)
    q_test = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (20, 6))
    np.testing.assert_allclose(
        Chain(reloaded).marker_positions(q_test), chain.marker_positions(q_test, result.params), atol=1e-6
    )
    assert corrected_model(model, chain.nominal).model_dump()["joints"] == model.model_dump()["joints"]


def test_fused_objective_jacobian_matches_finite_differences():
    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(4)
    q = rng.uniform(model.lower_limits_rad * 0.5, model.upper_limits_rad * 0.5, (6, 6))
    data = measure(model, chain, q, chain.nominal, rng, 0.0)
    # Measured target orientations: the flange's turned by a fixed frame and by up to ~20° of error,
    # so the rotation-vector residual and its exact Jacobian (J_l⁻¹ of the residual) are exercised.
    frame = exp_so3(np.array([0.3, -0.2, 1.0]))
    rot = BASE2SENSOR[:3, :3] @ chain.flange_pose(data.q_rad)[0] @ frame @ exp_so3(rng.normal(0, 0.2, (len(data), 3)))
    problem = _Problem(chain, data, {"sensor": BASE2SENSOR}, rot, 100.0)
    x = np.concatenate([chain.nominal + rng.normal(0, 1e-3, chain.n_params), rng.normal(0, 1e-3, len(problem.names) - chain.n_params)])
    _, j = problem.residuals_and_jacobian(x)
    h = 1e-6
    for col in [*rng.choice(x.size - 3, 12, replace=False), x.size - 3, x.size - 2, x.size - 1]:
        dx = np.zeros_like(x)
        dx[col] = h
        fd = (problem.residuals_and_jacobian(x + dx, False)[0] - problem.residuals_and_jacobian(x - dx, False)[0]) / (2 * h)
        np.testing.assert_allclose(j[:, col], fd, atol=1e-5 * max(1.0, np.abs(fd).max()))


def test_orientation_measurements_are_used_with_weight_L():
    model = load_robot_model(ROBOTS / "staubli_tx60.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(5)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (60, 6))
    truth, _ = perturbed_truth(chain, identify(model, measure(model, chain, q, chain.nominal, rng, 0.0)).free_names, rng)
    data = measure(model, chain, q, truth, rng, 0.01)
    rot_base, _ = chain.flange_pose(data.q_rad, truth)
    rotation = BASE2SENSOR[:3, :3] @ rot_base
    result = identify(model, data, rotation=rotation)
    p_only = identify(model, data)
    # Orientation adds information: never fewer identified parameters, smaller uncertainties.
    assert set(p_only.free_names) <= set(result.free_names)
    common = [chain.param_names.index(n) for n in p_only.free_names if n in chain.param_names]
    assert np.median(result.std[common] / p_only.std[common]) < 1.0


def test_ill_conditioned_fit_warns(caplog):
    model = load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(6)
    q = np.radians([10, 30, 0, -60, 0, 40, 0]) + rng.normal(0, 0.02, (40, 7))  # a tiny patch of joint space
    result = identify(model, measure(model, chain, q, chain.nominal, rng, 0.01), IdentOptions(cond_warn=1e3))
    assert result.warnings and "ill-conditioned" in result.warnings[0]


def test_too_few_measurements_is_a_clear_error():
    model = load_robot_model(ROBOTS / "staubli_tx60.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(7)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (6, 6))
    with pytest.raises(DatasetError, match="measure at least"):
        identify(model, measure(model, chain, q, chain.nominal, rng, 0.01))


def test_comprehensive_errors_on_a_hand_example():
    out = comprehensive_errors(np.array([3.0, 4.0, 5.0]), np.radians([1.0, 2.0, 3.0]))
    assert out["EACPE"] == pytest.approx(4.0) and out["EMCPE"] == 5.0
    assert out["EACAE"] == pytest.approx(2.0) and out["EMCAE"] == pytest.approx(3.0)  # degrees, as files are
    assert comprehensive_errors(np.array([1.0]))["EACAE"] is None


def test_pose_errors_vanish_for_the_true_model():
    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    chain = Chain(model)
    rng = np.random.default_rng(8)
    q = rng.uniform(model.lower_limits_rad * 0.7, model.upper_limits_rad * 0.7, (10, 6))
    data = measure(model, chain, q, chain.nominal, rng, 0.0)
    np.testing.assert_allclose(pose_errors(model, chain.nominal, data, {"sensor": BASE2SENSOR}), 0.0, atol=1e-9)
