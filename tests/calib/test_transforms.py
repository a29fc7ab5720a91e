"""Rigid-transform helpers: Euler round trips (also at gimbal lock), inverse, exp/log, angles."""

import numpy as np
import pytest

from calib.robot.transforms import (
    apply,
    euler_zyx_to_matrix,
    exp_so3,
    invert,
    log_so3,
    matrix_to_euler_zyx,
    pose_to_matrix,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
)

RNG = np.random.default_rng(0)


def test_zyx_matrix_is_rz_ry_rx_and_a_proper_rotation():
    a = RNG.uniform(-np.pi, np.pi, (200, 3))
    r = euler_zyx_to_matrix(a[:, 0], a[:, 1], a[:, 2])
    np.testing.assert_allclose(r, rot_z(a[:, 0]) @ rot_y(a[:, 1]) @ rot_x(a[:, 2]), atol=1e-15)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(r), 1.0)


def test_zyx_round_trip_away_from_and_at_gimbal_lock():
    a = np.column_stack([RNG.uniform(-3, 3, 100), RNG.uniform(-1.5, 1.5, 100), RNG.uniform(-3, 3, 100)])
    np.testing.assert_allclose(matrix_to_euler_zyx(euler_zyx_to_matrix(*a.T)), a, atol=1e-9)
    locked = euler_zyx_to_matrix(0.3, np.pi / 2, -0.2)
    back = matrix_to_euler_zyx(locked)
    assert back[2] == 0.0  # roll folded into yaw
    np.testing.assert_allclose(euler_zyx_to_matrix(*back), locked, atol=1e-12)


def test_invert_and_apply():
    t = pose_to_matrix(np.array([10.0, -20.0, 30.0]), np.array([0.4, -0.2, 1.1]))
    p = RNG.normal(size=(7, 3))
    np.testing.assert_allclose(apply(invert(t), apply(t, p)), p, atol=1e-12)
    np.testing.assert_allclose(invert(t) @ t, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 0.5, 3.0])
def test_exp_log_round_trip_and_angle(angle):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    w = axis * angle
    r = exp_so3(w)
    assert rotation_angle(r) == pytest.approx(angle, abs=1e-12)
    np.testing.assert_allclose(log_so3(r), w, atol=1e-9)
