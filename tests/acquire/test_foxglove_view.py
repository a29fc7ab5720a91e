"""The Foxglove view: frame transforms that compose to the model's kinematics, markers in the
right frames, Foxglove's schemas, log levels, and a layout that names only channels we write."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from acquire.record import foxglove_view as fv
from acquire.record.recorder import EVENT_TOPIC, SAMPLE_TOPIC, RunLog
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import euler_zyx_to_matrix, homogeneous

ROOT = Path(__file__).resolve().parents[2]
MODELS = sorted((ROOT / "fixtures" / "robots").glob("*.yaml"))
LAYOUT = ROOT / "fixtures" / "foxglove" / "remaster-layout.json"


def tf_matrix(tf: dict) -> np.ndarray:
    """(4, 4) mm of a foxglove.FrameTransform (child pose in parent), rebuilt from its quaternion."""
    q = tf["rotation"]
    x, y, z, w = q["x"], q["y"], q["z"], q["w"]
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    t = tf["translation"]
    return homogeneous(r, 1000.0 * np.array([t["x"], t["y"], t["z"]]))


def compose(transforms: list[dict], frame: str) -> np.ndarray:
    """Pose of ``frame`` in ``base`` by walking the parents."""
    by_child = {tf["child_frame_id"]: tf for tf in transforms}
    out = np.eye(4)
    while frame != fv.BASE_FRAME:
        tf = by_child[frame]
        out = tf_matrix(tf) @ out
        frame = tf["parent_frame_id"]
    return out


@pytest.mark.parametrize("model_path", MODELS, ids=[p.stem for p in MODELS])
def test_frame_transforms_compose_to_the_models_flange_and_markers(model_path):
    model = load_robot_model(model_path)
    chain = Chain(model)
    view = fv.RobotView(chain)
    rng = np.random.default_rng(3)
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    for q in rng.uniform(lo, hi, (20, model.n_joints)):
        doc = view.transforms(q, 1_700_000_000_123_456_789)
        jsonschema.validate(doc, fv.FRAME_TRANSFORMS_SCHEMA)
        tfs = doc["transforms"]
        assert [t["child_frame_id"] for t in tfs] == [f"link{i + 1}" for i in range(model.n_joints)] + ["flange"]
        assert [t["parent_frame_id"] for t in tfs] == ["base"] + [f"link{i + 1}" for i in range(model.n_joints)]
        flange = compose(tfs, "flange")  # Foxglove's numbers are rounded to 0.1 µm and 1e-10
        np.testing.assert_allclose(flange[:3, 3], chain.fk(q)[:3, 3], atol=1e-3)  # mm
        np.testing.assert_allclose(flange[:3, :3], chain.fk(q)[:3, :3], atol=1e-8)
        markers = np.array([flange[:3, :3] @ np.array(m.xyz) + flange[:3, 3] for m in model.tool.markers])
        np.testing.assert_allclose(markers, chain.marker_positions(q), atol=1e-3)
        assert tfs[0]["timestamp"] == {"sec": 1_700_000_000, "nsec": 123_456_789}


def test_base_to_sensor_places_sensor_points_where_the_registration_says():
    model = load_robot_model(MODELS[0])
    view = fv.RobotView(Chain(model))
    base2sensor = homogeneous(euler_zyx_to_matrix(0.3, -0.2, 2.9), np.array([-1800.0, 250.0, -900.0]))
    view.set_registration("tracker", base2sensor)
    tfs = view.transforms(np.zeros(model.n_joints), 0)["transforms"]
    sensor = next(t for t in tfs if t["child_frame_id"] == "tracker")
    assert sensor["parent_frame_id"] == "base"
    p_base = np.array([1200.0, -300.0, 650.0])
    p_sensor = base2sensor[:3, :3] @ p_base + base2sensor[:3, 3]
    sensor_in_base = compose(tfs, "tracker")
    np.testing.assert_allclose(sensor_in_base[:3, :3] @ p_sensor + sensor_in_base[:3, 3], p_base, atol=1e-3)
    view.set_registration("tracker", None)
    assert "tracker" not in {t["child_frame_id"] for t in view.transforms(np.zeros(model.n_joints), 0)["transforms"]}
    with pytest.raises(ValueError, match="finite"):
        view.set_registration("tracker", np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="need 7 finite joint angles, given 3"):
        view.transforms(np.zeros(3), 0)


def test_quaternion_of_rotations_near_and_far_from_identity():
    rng = np.random.default_rng(0)
    angles = [*rng.uniform(-np.pi, np.pi, (200, 3)), (np.pi, 0, 0), (0, np.pi, 0), (0, 0, np.pi), (0, 0, 0)]
    for a in angles:
        r = euler_zyx_to_matrix(*a)
        x, y, z, w = fv.quaternion(r)
        assert abs(x * x + y * y + z * z + w * w - 1) < 1e-12 and w >= 0
        back = tf_matrix({"rotation": {"x": x, "y": y, "z": z, "w": w}, "translation": {"x": 0, "y": 0, "z": 0}})
        np.testing.assert_allclose(back[:3, :3], r, atol=1e-12)


def test_scenes_are_in_metres_in_the_right_frames():
    doc = fv.scene_update("mocap", {"a": [1000.0, 0.0, -500.0], "b": None}, 5)
    jsonschema.validate(doc, fv.SCENE_UPDATE_SCHEMA)
    (ent,) = doc["entities"]
    assert ent["frame_id"] == "mocap" and ent["id"] == "mocap/a" and not ent["frame_locked"]
    assert ent["spheres"][0]["pose"]["position"] == {"x": 1.0, "y": 0.0, "z": -0.5}
    nominal = fv.nominal_markers_scene({"m1": (10.0, -20.0, 130.0)}, 5)
    jsonschema.validate(nominal, fv.SCENE_UPDATE_SCHEMA)
    (ent,) = nominal["entities"]
    assert ent["frame_id"] == "flange" and ent["frame_locked"] and ent["lifetime"] == {"sec": 0, "nsec": 0}
    assert ent["spheres"][0]["pose"]["position"] == pytest.approx({"x": 0.01, "y": -0.02, "z": 0.13})


def test_events_become_log_lines_with_a_level_that_matches_their_kind():
    levels = {k: fv.event_log({"kind": k, "t": 1.0, "config_id": "c1"}, 0)["level"]
              for k in ("moved", "settled", "suspended", "skipped", "failed", "log_resumed")}
    assert levels == {"moved": fv.INFO, "settled": fv.INFO, "suspended": fv.WARNING, "skipped": fv.WARNING,
                      "failed": fv.ERROR, "log_resumed": fv.WARNING}
    line = fv.event_log({"kind": "skipped", "t": 1.0, "config_id": "c7", "reason": "unreachable"}, 0)
    jsonschema.validate(line, fv.LOG_SCHEMA)
    assert line["message"] == "skipped config_id=c7 reason=unreachable"
    s = fv.sample_log({"config_id": "c3", "markers": [{"sensor": "mocap", "marker": "m1", "mean_mm": [1.0, 2.5, None]},
                                                      {"sensor": "mocap", "marker": "m2", "mean_mm": None}]}, 0)
    assert s["message"] == "measured c3: mocap/m1 [1.00, 2.50, nan] mm; mocap/m2 not seen"


def test_the_log_holds_every_foxglove_channel_with_valid_messages(tmp_path):
    model = load_robot_model(MODELS[0])
    view = fv.RobotView(Chain(model))
    view.set_registration("mocap", np.eye(4))
    path = tmp_path / "run.mcap"
    with RunLog.create(path, run_id="r", plan_text="", model_text="", metadata={}) as lg:
        q = np.radians(np.arange(model.n_joints) * 5.0)
        lg.record_joint_state("fri", q, names=model.axis_names, log_time_ns=10)
        lg.record_transforms(view.transforms(q, 10), log_time_ns=10)
        lg.record_markers("mocap", {"m1": [1.0, 2.0, 3.0]}, log_time_ns=11)
        lg.record_scene(fv.nominal_markers_scene({m.name: m.xyz for m in model.tool.markers}, 12), log_time_ns=12)
        lg.event("settled", config_id="c0")
        lg.sample({"config_id": "c0", "q_measured_deg": np.degrees(q).tolist(), "markers": []})
        body = {"sensor": "mocap", "marker": "body", "mean_mm": [900.0, 10.0, 5.0], "std_mm": [0.03] * 3, "count": 5,
                "quat_wxyz": [1.0, 0.0, 0.0, 0.0], "std_deg": 0.02}  # a 6-DoF target: /pose and a /tf frame
        lg.sample({"config_id": "c1", "q_measured_deg": np.degrees(q).tolist(), "markers": [body]})
    seen: dict[str, list[dict]] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            doc = json.loads(message.data)
            jsonschema.validate(doc, json.loads(schema.data))
            seen.setdefault(channel.topic, []).append(doc)
            if channel.topic in fv.CHANNELS:
                assert schema.name == fv.CHANNELS[channel.topic][0]
    assert set(fv.CHANNELS) <= set(seen)
    js = seen["/joint_state"][0]
    assert js["device"] == "fri" and js["name"] == model.axis_names
    assert js["position_deg"] == pytest.approx(np.arange(model.n_joints) * 5.0)
    assert js["position_rad"] == pytest.approx(q, abs=1e-8)
    assert [len(s["entities"]) for s in seen["/markers"]] == [1, len(model.tool.markers)]
    assert [d["level"] for d in seen["/log"]] == [fv.INFO, fv.INFO, fv.INFO]
    assert len(seen[SAMPLE_TOPIC]) == 2 and len(seen[EVENT_TOPIC]) == 1
    (pose,) = seen[fv.POSE_TOPIC]
    assert pose["frame_id"] == "mocap" and pose["pose"]["position"] == {"x": 0.9, "y": 0.01, "z": 0.005}
    assert seen[fv.TF_TOPIC][-1]["transforms"][0]["child_frame_id"] == "mocap/body"


# --------------------------------------------------------------------------------- layout
def _leaves(node) -> list[str]:
    if isinstance(node, str):
        return [node]
    return _leaves(node["first"]) + _leaves(node["second"])


def test_the_shipped_layout_shows_only_channels_the_run_writes():
    doc = json.loads(LAYOUT.read_text())
    panels = doc["configById"]
    assert sorted(_leaves(doc["layout"])) == sorted(panels)
    kinds = {pid.split("!")[0] for pid in panels}
    assert {"3D", "Plot", "RosOut", "RawMessages"} <= kinds
    written = set(fv.CHANNELS) | {SAMPLE_TOPIC, EVENT_TOPIC}
    three_d = next(v for k, v in panels.items() if k.startswith("3D!"))
    assert set(three_d["topics"]) <= written and three_d["topics"][fv.SCENE_TOPIC]["visible"]
    assert three_d["followTf"] == fv.BASE_FRAME
    plot = next(v for k, v in panels.items() if k.startswith("Plot!"))
    paths = [p["value"] for p in plot["paths"]]
    assert paths == [f"/joint_state.position_deg[{i}]" for i in range(7)]
    log_panel = next(v for k, v in panels.items() if k.startswith("RosOut!"))
    assert log_panel.get("topicToRender", fv.LOG_TOPIC) == fv.LOG_TOPIC
    raw = next(v for k, v in panels.items() if k.startswith("RawMessages!"))
    assert raw["topicPath"].split(".")[0] in written
