"""6-DoF records in the run log: a measurement's orientation goes into the sample record as a
scalar-first quaternion (schema-checked) and comes back as the dataset's R_sensor←target."""

from __future__ import annotations

import math

import numpy as np

from acquire.record.recorder import dataset_from_run
from acquire.run.sequencer import _orientation
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from drivers.protocols import MarkerMeasurement

from test_recorder import IIWA, new_log


def test_orientation_goes_into_the_record_as_a_scalar_first_quaternion():
    c, s = math.cos(0.25), math.sin(0.25)
    rz = np.array([[c * c - s * s, -2 * s * c, 0], [2 * s * c, c * c - s * s, 0], [0, 0, 1]])  # 0.5 rad about z
    mm = MarkerMeasurement("tool", np.zeros(3), np.zeros(3), 5, 0.0, 0.0, rotation=rz, std_deg=0.02)
    rec = _orientation(mm)
    np.testing.assert_allclose(rec["quat_wxyz"], [c, 0, 0, s], atol=1e-12)
    assert rec["std_deg"] == 0.02
    assert _orientation(MarkerMeasurement("p", np.zeros(3), np.zeros(3), 5, 0.0, 0.0)) == {}


def test_dataset_from_run_reads_orientations(tmp_path):
    model = load_robot_model(IIWA)
    chain = Chain(model)
    rng = np.random.default_rng(2)
    q_deg = rng.uniform(-60, 60, (6, model.n_joints))
    pos = chain.marker_positions(np.radians(q_deg))
    name = model.marker_names[0]
    path = tmp_path / "run.mcap"
    half = math.sqrt(0.5)
    with new_log(path) as lg:
        for i in range(6):
            mk = {"sensor": "mocap", "marker": name, "mean_mm": pos[i, 0].tolist(), "std_mm": [0.03] * 3, "count": 10}
            if i % 2 == 0:  # every other configuration with the body's orientation: 90° about x
                mk |= {"quat_wxyz": [half, half, 0.0, 0.0], "std_deg": 0.05}
            lg.sample({"config_id": f"c{i}", "q_measured_deg": q_deg[i].tolist(), "markers": [mk]})
    ds = dataset_from_run(path, model)
    assert ds.oriented.tolist() == [True, False] * 3
    np.testing.assert_allclose(ds.rot[0] @ [0, 1, 0], [0, 0, 1], atol=1e-12)  # the body's y → the sensor's z
    np.testing.assert_allclose(ds.att_std_rad[ds.oriented], math.radians(0.05))


def test_measured_poses_are_foxglove_pose_frames_any_mcap_reader_opens(tmp_path):
    """A 6-DoF target's pose goes on /pose (foxglove.PoseInFrame, metres, sensor frame) and on /tf
    as the frame <sensor>/<marker>; point targets add nothing there. Read with mcap's own reader."""
    import json

    from mcap.reader import make_reader

    half = math.sqrt(0.5)
    path = tmp_path / "run.mcap"
    with new_log(path) as lg:
        for i in range(3):
            mk = {"sensor": "mocap", "marker": "body", "mean_mm": [1000.0 + i, 20.0, -30.0], "std_mm": [0.03] * 3, "count": 5}
            if i != 1:
                mk |= {"quat_wxyz": [half, 0.0, 0.0, half], "std_deg": 0.05}
            lg.sample({"config_id": f"c{i}", "q_measured_deg": [0.0] * 7, "markers": [mk]})
    with open(path, "rb") as fh:
        msgs = [(schema.name, channel.topic, json.loads(m.data)) for schema, channel, m in
                make_reader(fh).iter_messages(topics=["/pose", "/tf"])]
    poses = [d for name, topic, d in msgs if topic == "/pose"]
    assert {name for name, topic, _ in msgs if topic == "/pose"} == {"foxglove.PoseInFrame"}
    assert len(poses) == 2 and all(p["frame_id"] == "mocap" for p in poses)
    assert poses[1]["pose"]["position"] == {"x": 1.002, "y": 0.02, "z": -0.03}
    assert poses[0]["pose"]["orientation"] == {"x": 0.0, "y": 0.0, "z": half, "w": half}  # Foxglove: x, y, z, w
    frames = [t for _, topic, d in msgs if topic == "/tf" for t in d["transforms"]]
    assert [(f["parent_frame_id"], f["child_frame_id"]) for f in frames] == [("mocap", "mocap/body")] * 2
