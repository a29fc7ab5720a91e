"""Orientation in the simulated cell: a 6-DoF target's frame on every observation (with attitude
noise), and the default cell's Motive rigid body (the SIR in a three-marker cluster) read by our
NatNet client with the orientation the robot's flange really turned by."""

from __future__ import annotations

import math

import numpy as np

from calib.io.resources import default_sim_config
from calib.robot.transforms import log_so3
from drivers.natnet.client import NatNetSensor
from drivers.sim.cell import SimCell
from drivers.sim.launch import SimLaunch


def _angle_deg(r: np.ndarray) -> float:
    return math.degrees(np.linalg.norm(log_so3(r)))


def test_observations_carry_the_flange_frame_with_attitude_noise():
    cell = SimCell.from_yaml(default_sim_config(), seed=4)
    q0 = cell.joint_positions()
    q1 = q0 + np.radians([0, 0, 0, 0, 0, 0, 20.0])  # A7 turns the flange about its own z
    cell.set_joint_positions(q0)
    (smr0,) = [o for o in cell.observe("tracker") if o.name == "smr"]
    cell.set_joint_positions(q1)
    draws = [next(o for o in cell.observe("tracker") if o.name == "smr").rotation for _ in range(200)]
    turn = np.stack(draws) @ smr0.rotation.T  # R(q1)·R(q0)ᵀ: 20° about the flange z, in the tracker frame
    angles = np.array([_angle_deg(t) for t in turn])
    assert abs(angles.mean() - 20.0) < 0.005
    spread = np.degrees(log_so3(np.stack(draws) @ draws[0].T)).std(axis=0)  # two draws' noise: ≈ 0.005° · √2 per axis
    assert np.all((spread > 0.004) & (spread < 0.012))
    p = cell.true_marker_positions(np.stack([q0, q1]), frame="tracker")
    sir_to_smr = p[:, cell.marker_names.index("smr")] - p[:, cell.marker_names.index("sir")]
    np.testing.assert_allclose(turn.mean(axis=0) @ sir_to_smr[0], sir_to_smr[1], atol=0.1)  # mm over 200 mm


def test_default_cells_rigid_body_gives_the_sir_and_the_flange_turn():
    cell = SimCell.from_yaml(default_sim_config(), seed=2)
    q0 = cell.joint_positions()
    q1 = q0 + np.radians([0, 0, 0, 0, 0, 0, 10.0])
    with SimLaunch(cell, controller=False) as launch:
        url = launch.addresses["mocap"].url
        with NatNetSensor.from_url(url, markers={"sir": "rb:tool"}) as sensor:
            m0 = sensor.measure("sir", 20, 10.0)
            cell.set_joint_positions(q1)
            sensor.read(2.0)
            m1 = sensor.measure("sir", 20, 10.0)
    sir = cell.true_marker_positions(np.stack([q0, q1]), frame="mocap")[:, cell.marker_names.index("sir")]
    np.testing.assert_allclose(m0.mean_mm, sir[0], atol=0.1)  # the body's origin is the SIR (noise 0.03 mm)
    np.testing.assert_allclose(m1.mean_mm, sir[1], atol=0.1)
    assert _angle_deg(m0.rotation) < 0.2  # Motive defined the body where it stood at start
    assert abs(_angle_deg(m1.rotation @ m0.rotation.T) - 10.0) < 0.2
    assert 0.0 < m1.std_deg < 0.2  # a 30 mm cluster with 0.03 mm per marker: a few hundredths of a degree
