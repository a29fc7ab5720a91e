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


def test_a_six_dof_tracker_target_turns_with_the_flange_on_both_protocols(tmp_path):
    """``six_dof: true``: the simulated tracker's target is a T-Mac; the line protocol's POSE and
    emScon's 6D stationary mode both see the flange turn by A7's 10°."""
    import yaml

    from drivers.emscon.client import EmsconSensor
    from drivers.tracker.client import TrackerSensor

    doc = yaml.safe_load(default_sim_config().read_text())
    doc["robot"] = str((default_sim_config().parent / doc["robot"]).resolve())
    tracker = next(s for s in doc["sensors"] if s["kind"] == "tracker")
    tracker |= {"six_dof": True, "protocols": ["line", "emscon"]}
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc))
    cell = SimCell.from_yaml(path, seed=3)
    q0 = cell.joint_positions()
    q1 = q0 + np.radians([0, 0, 0, 0, 0, 0, 10.0])
    got = {}
    with SimLaunch(cell, controller=False) as launch:
        with TrackerSensor.from_url(launch.addresses["tracker"].url, pose=True, reply_timeout=5.0) as line, \
                EmsconSensor(launch.addresses["tracker-emscon"].url, pose=True, reply_timeout=5.0) as emscon:
            for q in (q0, q1):
                cell.set_joint_positions(q)
                got.setdefault("line", []).append(line.measure("smr", 100, 10.0))
                got.setdefault("emscon", []).append(emscon.measure("smr", 100, 10.0))
    smr = cell.true_marker_positions(np.stack([q0, q1]), frame="tracker")[:, cell.marker_names.index("smr")]
    for proto, (m0, m1) in got.items():
        np.testing.assert_allclose(m1.mean_mm, smr[1], atol=0.1, err_msg=proto)
        assert abs(_angle_deg(m1.rotation @ m0.rotation.T) - 10.0) < 0.05, proto
        assert 0.0 < m1.std_deg < 0.05, proto
    assert _angle_deg(got["line"][1].rotation @ got["emscon"][1].rotation.T) < 0.05  # one target, two protocols
