"""Orientation in the zero-offset fit (``fit_offsets``, the default methods): the attitude rows
join the position rows, each weighted by its stated spread. A simulated 6-DoF cell's offsets come
back within their intervals with the target's frame on the flange unknown (profiled), and with
the frame known the last joint's offset is identified from one marker on its axis, where
positions alone leave it undetermined."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.fit.offsets import FitOptions, fit_mode, fit_offsets
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, robot_model_from_dict
from calib.robot.transforms import exp_so3

from tests.calib.pose_sim import BASE2SENSOR, PoseCell, measure_poses

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
TX60 = load_robot_model(ROBOTS / "staubli_tx60.yaml")
FAST = FitOptions(n_draws=300, link_tolerance=None)


def one_marker_on_last_axis():
    d = TX60.model_dump()
    d["tool"]["markers"] = [{"name": "tmac", "xyz": (0.0, 0.0, 60.0), "kind": "retroreflector", "rpy_deg": (0.0, 0.0, 0.0)}]
    return robot_model_from_dict(d)


def cell_data(model, frame, n, seed, noise_mm=0.02, noise_deg=0.005):
    chain = Chain(model)
    rng = np.random.default_rng(seed)
    q = rng.uniform(model.lower_limits_rad * 0.6, model.upper_limits_rad * 0.6, (n, model.n_joints))
    offsets = np.radians(rng.normal(0.0, 0.05, model.n_joints))
    data = measure_poses(chain, q, PoseCell(chain.with_offsets(offsets), frame, BASE2SENSOR, noise_mm, noise_deg), rng)
    return data, offsets


@pytest.mark.parametrize("method", ["fast", "laplace"])
def test_offsets_with_attitude_and_an_unknown_target_frame_fall_within_their_intervals(method):
    data, offsets = cell_data(TX60, exp_so3(np.radians([3.0, -2.0, 40.0])), 40, 1)
    result = fit_offsets(TX60, data, FitOptions(method=method, n_draws=300, link_tolerance=None))
    post = result.posterior
    assert post.attitude is not None and post.n_rows == 2 * len(data)
    fitted = result.identifiable()
    assert list(np.flatnonzero(~fitted)) == [0, 5]  # J1: the registration's turn; J6: the target's frame takes it
    z = (result.offsets_rad[fitted] - offsets[fitted]) / result.offsets_std_rad[fitted]
    assert np.all(np.abs(z) < 4.0), z
    positions_only = fit_mode(TX60, data.without_orientation(), FitOptions(link_tolerance=None))
    assert positions_only.post.attitude is None


def test_with_a_known_target_frame_orientation_identifies_the_last_offset_from_one_marker():
    model = one_marker_on_last_axis()
    data, offsets = cell_data(model, np.eye(3), 30, 2)
    exact_tool = FitOptions(n_draws=300, link_tolerance=None, tool_prior_mm=0.0)
    poses = fit_offsets(model, data, exact_tool)
    assert poses.offset_status[5] == "fitted"
    assert abs(poses.offsets_rad[5] - offsets[5]) < 4 * poses.offsets_std_rad[5]
    assert np.degrees(poses.offsets_std_rad[5]) < 0.01
    positions = fit_offsets(model, data.without_orientation(), exact_tool)
    assert positions.offset_status[5] != "fitted", positions.offset_status[5]


def test_pose_metrics_of_a_zero_offset_fit_score_held_out_attitude_without_refitting():
    from calib.fit.pose_scoring import pose_metrics

    frame = exp_so3(np.radians([3.0, -2.0, 40.0]))
    data, _ = cell_data(TX60, frame, 60, 7)
    cal, val = data.subset(np.arange(60) < 40), data.subset(np.arange(60) >= 40)
    mf = fit_mode(TX60, cal, FitOptions(link_tolerance=None))
    m = pose_metrics(mf.post, mf.theta, mf.b2s0, cal, val)
    for part in ("calibration", "validation"):
        b, a = m[part]["before"], m[part]["after"]
        assert a["EACPE"] < 0.1 < b["EACPE"] and a["EACAE"] < 0.02 < b["EACAE"], m[part]
        assert a["EMCAE"] >= a["EACAE"] and a["EMCPE"] >= a["EACPE"]


def test_the_expansion_predicts_the_attitude_rows_as_the_walk_does_and_walks_a_batch_beyond_it():
    """While the posterior predicts by its expansion (the sampler), the attitude rows' flange
    rotations come from their first-order expansion about the mode: within the predictor's
    tolerance of the walked residuals at proposals 5 posterior stds out (a few 1e-4 rad), and a batch
    with a proposal far beyond that (0.1 rad) is walked instead."""
    from calib.fit.posterior import EXPANSION_TOLERANCE_MM

    data, _ = cell_data(TX60, exp_so3(np.radians([3.0, -2.0, 40.0])), 40, 1)
    mf = fit_mode(TX60, data, FitOptions(link_tolerance=None))
    post, theta = mf.post, mf.theta
    with np.errstate(all="ignore"):
        std = np.sqrt(np.diag(np.linalg.pinv(post.jacobian(theta).T @ post.jacobian(theta)))) * np.exp(mf.log_sigma[0])
    rng = np.random.default_rng(0)
    near = theta + 5.0 * std * rng.choice([-1.0, 1.0], (8, theta.size))
    post.expand(theta)
    try:
        expanded = post.residuals(near)[:, post.k_pos:]  # (first: a walk at the same vectors would be reused)
        check = dict(post.expansion_check)
        with post.exact():
            exact = post.residuals(near)[:, post.k_pos:]
        far = near.copy()
        far[0, :post.n] += 0.1  # 6° on every axis: far outside any expansion
        walked = post.residuals(far)[:, post.k_pos:]
        check_far = dict(post.expansion_check)
    finally:
        post.expand(None)
    assert np.abs(expanded - exact).max() < EXPANSION_TOLERANCE_MM
    assert 0.0 < check["attitude_max_error_mm"] < EXPANSION_TOLERANCE_MM and "attitude_walked_batches" not in check
    assert check_far["attitude_walked_batches"] == 1
    assert np.allclose(walked, post.residuals(far)[:, post.k_pos:], atol=1e-12)  # the walk's, exactly
