"""The MCAP run log: round trip, standard readers, truncation at any byte, kill -9, resume, fit input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader

from acquire.record.recorder import (
    EVENT_TOPIC,
    SAMPLE_TOPIC,
    RunLog,
    RunLogError,
    dataset_from_run,
    read_run,
    scene_update,
    segment_paths,
)
from calib.measure.dataset import DatasetError
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model

ROOT = Path(__file__).resolve().parents[2]
IIWA = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"
PLAN = "cell: c1\nrobot: robot.yaml\n# plan text kept byte for byte: ünïcode ✓\n"
MODEL = "name: test-arm\njoints: []\n"


def make_sample(i: int, rng: np.random.Generator, n_joints: int = 7) -> dict:
    q = rng.uniform(-90, 90, n_joints)
    return {
        "config_id": f"p{i:02d}-b{i % 4}",
        "pose": f"p{i:02d}",
        "branch": f"b{i % 4}",
        "q_target_deg": q.round(6).tolist(),
        "q_measured_deg": (q + rng.normal(0, 1e-3, n_joints)).tolist(),
        "q_measured_std_deg": [1e-4] * n_joints,
        "markers": [
            {"sensor": "mocap", "marker": "m1", "mean_mm": rng.normal(0, 500, 3).tolist(), "std_mm": [0.02, 0.03, 0.02],
             "count": 20, "device_time": 12.5 + i, "host_time": 1.7e9 + i}
        ],
        "t_start": 1.7e9 + i,
        "t_end": 1.7e9 + i + 0.5,
        "attempts": 1,
    }


def new_log(path: Path, **kw) -> RunLog:
    return RunLog.create(path, run_id="run-1", plan_text=PLAN, model_text=MODEL, metadata={"seed": 7, "speed": 0.3, "sensors": ["mocap"]}, **kw)


def test_every_record_type_round_trips(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "run.mcap"
    samples = [make_sample(i, rng) for i in range(3)]
    with new_log(path) as lg:
        lg.channel("/robot/status", "remaster.Status", {"type": "object", "properties": {"ok": {"type": "boolean"}}})
        lg.write("/robot/status", {"ok": True, "q": np.arange(3.0)}, log_time_ns=123)
        lg.record_joint_state("robot", np.radians([10.0, 20.0, -30.0]), device_time=4.5)
        lg.record_markers("mocap", {"m1": [1.0, 2.0, 3.0], "m2": None}, quality={"m1": 0.2})
        lg.event("moved", config_id=samples[0]["config_id"], duration_s=1.25)
        for s in samples:
            lg.sample(s)
        lg.event("skipped", config_id="p99-b0", reason="unreachable")
    run = read_run(path)
    assert run.run_id == "run-1"
    assert run.plan_text == PLAN and run.model_text == MODEL
    assert run.metadata == {"seed": 7, "speed": 0.3, "sensors": ["mocap"]}
    assert run.samples == samples
    assert [(e["kind"], e.get("config_id")) for e in run.events] == [("moved", "p00-b0"), ("skipped", "p99-b0")]
    assert run.events[0]["duration_s"] == 1.25 and run.events[1]["reason"] == "unreachable"
    assert run.complete and run.files == [path] and run.dropped_bytes == 0
    assert run.message_counts == {
        "/robot/status": 1, "/joint_state": 1, "/mocap/markers": 1, "/markers": 1, SAMPLE_TOPIC: 3, EVENT_TOPIC: 2, "/log": 5,
    }
    assert run.measured_config_ids == [s["config_id"] for s in samples]


def test_mcap_own_readers_read_the_log_and_messages_match_their_schemas(tmp_path):
    rng = np.random.default_rng(2)
    path = tmp_path / "run.mcap"
    with new_log(path) as lg:
        lg.record_joint_state("robot", np.radians([1.0, 2.0]))
        lg.record_markers("mocap", {"m1": [100.0, -200.0, 1500.0], "m2": None})
        lg.sample(make_sample(0, rng))
        lg.event("settled", config_id="p00-b0")
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        assert summary.statistics.message_count == 7  # + a foxglove.Log line per sample and event
        seen = {}
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            doc = json.loads(message.data)
            jsonschema.validate(doc, json.loads(schema.data))
            seen[channel.topic] = (schema.name, doc)
        assert {t: v[0] for t, v in seen.items()} == {
            "/joint_state": "remaster.JointState",
            "/mocap/markers": "remaster.MarkerFrame",
            "/markers": "foxglove.SceneUpdate",
            SAMPLE_TOPIC: "remaster.Sample",
            EVENT_TOPIC: "remaster.RunEvent",
            "/log": "foxglove.Log",
        }
        assert seen["/joint_state"][1]["position_deg"] == pytest.approx([1.0, 2.0])
        scene = seen["/markers"][1]
        assert [e["id"] for e in scene["entities"]] == ["mocap/m1"]  # the unseen m2 has no sphere
        assert scene["entities"][0]["spheres"][0]["pose"]["position"] == pytest.approx({"x": 0.1, "y": -0.2, "z": 1.5})
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["remaster.plan"]["text"] == PLAN and meta["remaster.run"]["run_id"] == "run-1"
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        assert attachments == {"plan.yaml": PLAN.encode(), "robot.yaml": MODEL.encode()}
    with open(path, "rb") as fh:  # the streaming reader validates the summary CRC and ends at the footer
        topics = [ch.topic for _, ch, _ in NonSeekingReader(fh, validate_crcs=True).iter_messages()]
    assert topics.count(SAMPLE_TOPIC) == 1


def test_scene_update_is_in_metres_and_skips_unseen_markers():
    doc = scene_update("tracker", {"a": [1000.0, 0.0, -500.0], "b": None, "c": [float("nan"), 0, 0]}, 1_500_000_000_250)
    assert len(doc["entities"]) == 1
    ent = doc["entities"][0]
    assert ent["frame_id"] == "tracker" and ent["timestamp"] == {"sec": 1500, "nsec": 250}
    assert ent["spheres"][0]["pose"]["position"] == {"x": 1.0, "y": 0.0, "z": -0.5}


def _write_reference_log(path: Path, joint_ends: list[int] | None = None) -> tuple[list[dict], list[int], list[dict], list[int]]:
    """A small log; returns the samples/events and the file size right after each was written."""
    rng = np.random.default_rng(3)
    samples, sample_ends, events, event_ends = [], [], [], []
    lg = new_log(path, flush_interval_s=0.0)
    for i in range(4):
        lg.record_joint_state("robot", rng.normal(size=7))
        if joint_ends is not None:
            joint_ends.append(path.stat().st_size)
        lg.event("moved", config_id=f"c{i}")
        events.append(read_run(path).events[-1])
        event_ends.append(path.stat().st_size)
        s = make_sample(i, rng)
        lg.sample(s)
        samples.append(s)
        sample_ends.append(path.stat().st_size)
    lg.close()
    return samples, sample_ends, events, event_ends


def test_truncation_at_any_byte_recovers_exactly_the_complete_records(tmp_path):
    src = tmp_path / "full.mcap"
    joint_ends: list[int] = []
    samples, sample_ends, events, event_ends = _write_reference_log(src, joint_ends)
    data = src.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    first_record_end = sample_ends[0] - 1
    # Every byte around the records that matter, plus a stride through the rest (and the last byte).
    offsets = set(range(0, len(data), 7)) | {len(data) - 1, len(data)}
    for end in sample_ends + event_ends + joint_ends:
        offsets |= set(range(end - 40, min(end + 40, len(data) + 1)))
    checked = 0
    for cut in sorted(o for o in offsets if 0 <= o <= len(data)):
        cut_path.write_bytes(data[:cut])
        run = read_run(cut_path)  # never raises
        n_s = sum(1 for e in sample_ends if e <= cut)
        n_e = sum(1 for e in event_ends if e <= cut)
        assert run.samples == samples[:n_s], f"cut at {cut}"
        assert run.events == events[:n_e], f"cut at {cut}"
        n_j = sum(1 for e in joint_ends if e <= cut)
        assert run.message_counts.get("/joint_state", 0) == n_j, f"cut at {cut}: a partial stream record was taken"
        assert run.complete == (cut == len(data))
        checked += 1
    assert checked > 500 and first_record_end > 0 and len(joint_ends) == 4


def test_truncated_zero_filled_tail_is_ignored(tmp_path):
    path = tmp_path / "run.mcap"
    samples, _, _, _ = _write_reference_log(path)
    data = path.read_bytes()
    cut = len(data) // 2
    path.write_bytes(data[:cut] + bytes(4096))  # a power cut can leave zeros after the last write
    run = read_run(path)
    assert run.samples == samples[: len(run.samples)] and not run.complete


WRITER = r"""
import sys, time
import numpy as np
from pathlib import Path
from acquire.record.recorder import RunLog
path, start, n = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
lg = RunLog.create(path, run_id="k", plan_text="p", model_text="m", metadata={}) if start == 0 else RunLog.append_to(path)
rng = np.random.default_rng(start)
for i in range(start, start + n):
    for _ in range(20):  # a 240 Hz stream between samples
        lg.record_markers("mocap", {"m1": rng.normal(size=3)})
        lg.record_joint_state("robot", rng.normal(size=7))
    lg.event("moved", config_id=f"c{i:03d}")
    lg.sample({"config_id": f"c{i:03d}", "q_measured_deg": rng.normal(size=7).tolist(), "markers": []})
    print(f"written c{i:03d}", flush=True)
lg.close()
print("closed", flush=True)
"""


def _run_and_kill(path: Path, start: int, n: int, kill_after: int | None) -> list[str]:
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path), str(start), str(n)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    reported = []
    try:
        for line in proc.stdout:
            if line.startswith("written "):
                reported.append(line.split()[1])
                if kill_after is not None and len(reported) >= kill_after:
                    proc.send_signal(signal.SIGKILL)
                    break
    finally:
        proc.stdout.close()
        proc.wait(timeout=30)
    return reported


def test_sigkill_at_random_moments_loses_no_reported_sample_and_resume_completes_the_run(tmp_path):
    rng = np.random.default_rng(11)
    path = tmp_path / "run.mcap"
    total = 30
    done = 0
    expected = [f"c{i:03d}" for i in range(total)]
    for round_ in range(3):
        kill_after = int(rng.integers(1, 6))
        reported = _run_and_kill(path, done, total - done, kill_after)
        run = read_run(path)
        ids = run.measured_config_ids
        assert ids == expected[: len(ids)], "recovered samples are a prefix of the written ones, without repeats"
        assert set(reported) <= set(ids), f"round {round_}: a reported sample was lost"
        assert len(ids) >= done + len(reported)
        assert not run.complete
        done = len(ids)
    reported = _run_and_kill(path, done, total - done, None)  # resume to the end, cleanly
    run = read_run(path)
    assert run.measured_config_ids == expected and len(run.samples) == total
    assert run.complete and len(run.files) == 4
    assert [e["kind"] for e in run.events].count("log_resumed") == 3
    for seg in run.files:  # every segment, including the killed ones, is valid MCAP again
        with open(seg, "rb") as fh:
            msgs = list(NonSeekingReader(fh).iter_messages(topics=[SAMPLE_TOPIC]))
        assert all(json.loads(m.data)["config_id"] in expected for _, _, m in msgs)


def test_resume_appends_a_segment_without_duplicates_and_reads_as_one_run(tmp_path):
    rng = np.random.default_rng(4)
    samples = [make_sample(i, rng) for i in range(6)]
    full = tmp_path / "full.mcap"
    lg = new_log(full)
    sizes = []
    for s in samples[:3]:
        lg.record_joint_state("robot", rng.normal(size=7))
        lg.sample(s)
        sizes.append(full.stat().st_size)
    lg.close()
    path = tmp_path / "run.mcap"
    path.write_bytes(full.read_bytes()[: sizes[1] + 5])  # killed just after the second sample
    resumed = RunLog.append_to(path)
    assert resumed.path == tmp_path / "run.resume1.mcap" and resumed.segment == 1
    assert resumed.recovered.measured_config_ids == [s["config_id"] for s in samples[:2]]
    for s in samples[2:4]:
        resumed.sample(s)
    resumed.close()
    again = RunLog.append_to(tmp_path / "run.resume1.mcap")  # any segment names the run
    assert again.path == tmp_path / "run.resume2.mcap"
    again.sample(samples[4])
    again.sample(samples[5])
    again.close()
    for name in ("run.mcap", "run.resume1.mcap", "run.resume2.mcap"):
        run = read_run(tmp_path / name)
        assert run.samples == samples and run.complete
        assert run.run_id == "run-1" and run.plan_text == PLAN and run.metadata["seed"] == 7
    assert segment_paths(path) == [path, tmp_path / "run.resume1.mcap", tmp_path / "run.resume2.mcap"]
    with open(path, "rb") as fh:  # the repaired first segment: valid MCAP with its two samples
        got = [json.loads(m.data)["config_id"] for _, _, m in make_reader(fh).iter_messages(topics=[SAMPLE_TOPIC])]
    assert got == [s["config_id"] for s in samples[:2]]


def test_resume_refuses_a_log_killed_before_its_metadata(tmp_path):
    full = tmp_path / "full.mcap"
    new_log(full).close()
    path = tmp_path / "run.mcap"
    path.write_bytes(full.read_bytes()[:40])
    assert read_run(path).run_id == ""
    with pytest.raises(RunLogError, match="no run metadata"):
        RunLog.append_to(path)


def test_concurrent_writers_lose_nothing(tmp_path):
    path = tmp_path / "run.mcap"
    lg = new_log(path, flush_interval_s=0.0)
    rng = np.random.default_rng(5)
    samples = [make_sample(i, rng) for i in range(20)]

    def stream():
        for _ in range(300):
            lg.record_joint_state("robot", np.zeros(7))

    threads = [threading.Thread(target=stream) for _ in range(2)]
    for t in threads:
        t.start()
    for s in samples:
        lg.sample(s)
    for t in threads:
        t.join()
    lg.close()
    run = read_run(path)
    assert run.samples == samples and run.message_counts["/joint_state"] == 600


def test_bad_use_raises_clear_errors(tmp_path):
    path = tmp_path / "run.mcap"
    lg = new_log(path)
    with pytest.raises(RunLogError, match="exists already"):
        new_log(path)
    with pytest.raises(RunLogError, match=r"lacks \['config_id'\]"):
        lg.sample({"q_measured_deg": [], "markers": []})
    with pytest.raises(RunLogError, match="no channel"):
        lg.write("/nowhere/stream", {"a": 1})
    with pytest.raises(RunLogError, match="topic must look like"):
        lg.channel("no-slash", "x", {})
    lg.channel("/a/b", "s1", {"type": "object"})
    with pytest.raises(RunLogError, match="one schema"):
        lg.channel("/a/b", "s2", {"type": "object"})
    with pytest.raises(RunLogError, match="event kind"):
        lg.event("Bad Kind")
    lg.close()
    lg.close()  # idempotent
    with pytest.raises(RunLogError, match="closed"):
        lg.event("late")
    not_mcap = tmp_path / "x.mcap"
    not_mcap.write_bytes(b"hello world, not mcap")
    with pytest.raises(RunLogError, match="not an MCAP file"):
        read_run(not_mcap)
    with pytest.raises(RunLogError, match="no such run log"):
        read_run(tmp_path / "missing.mcap")
    other = RunLog.create(tmp_path / "o.mcap", run_id="other", plan_text="", model_text="", metadata={})
    other.close()
    os.replace(tmp_path / "o.mcap", tmp_path / "run.resume1.mcap")
    with pytest.raises(RunLogError, match="belongs to run 'other'"):
        read_run(path)


def test_dataset_from_run_gives_one_row_per_marker_measurement(tmp_path):
    model = load_robot_model(IIWA)
    chain = Chain(model)
    rng = np.random.default_rng(6)
    q_deg = rng.uniform(-60, 60, (8, model.n_joints))
    pos = chain.marker_positions(np.radians(q_deg))  # (8, m, 3) base frame; registration is identity
    names = model.marker_names
    path = tmp_path / "run.mcap"
    with new_log(path) as lg:
        for i in range(8):
            markers = [
                {"sensor": "mocap", "marker": names[j], "mean_mm": pos[i, j].tolist(), "std_mm": [0.03, 0.04, 0.0], "count": 10 + j}
                for j in range(len(names))
            ]
            markers.append({"sensor": "mocap", "marker": names[0], "mean_mm": None, "count": 0})  # not seen: no row
            lg.sample({"config_id": f"c{i}", "pose": f"p{i // 2}", "q_measured_deg": q_deg[i].tolist(), "markers": markers})
    ds = dataset_from_run(path, model)
    m = len(names)
    assert len(ds) == 8 * m
    np.testing.assert_allclose(ds.q_rad, np.radians(np.repeat(q_deg, m, axis=0)))
    np.testing.assert_allclose(ds.xyz_mm, pos.reshape(-1, 3))
    assert ds.config.tolist() == [f"c{i}" for i in range(8) for _ in range(m)]
    assert ds.pose.tolist() == [f"p{i // 2}" for i in range(8) for _ in range(m)]
    assert ds.marker.tolist() == names * 8 and set(ds.sensor) == {"mocap"}
    np.testing.assert_allclose(ds.std_mm, np.sqrt((0.03**2 + 0.04**2) / 3))
    assert ds.count.tolist() == [10 + j for _ in range(8) for j in range(m)]
    assert ds.source == str(path)


def test_dataset_from_run_rejects_what_does_not_fit_the_model(tmp_path):
    model = load_robot_model(IIWA)
    bad_joints = tmp_path / "j.mcap"
    with new_log(bad_joints) as lg:
        lg.sample({"config_id": "c0", "q_measured_deg": [0.0] * 6, "markers": []})
    with pytest.raises(DatasetError, match=r"c0.*7 numbers"):
        dataset_from_run(bad_joints, model)
    bad_marker = tmp_path / "m.mcap"
    with new_log(bad_marker) as lg:
        lg.sample({"config_id": "c1", "q_measured_deg": [0.0] * 7, "markers": [{"sensor": "s", "marker": "nope", "mean_mm": [1, 2, 3]}]})
    with pytest.raises(DatasetError, match="'nope' is not on the tool"):
        dataset_from_run(bad_marker, model)
    empty = tmp_path / "e.mcap"
    new_log(empty).close()
    with pytest.raises(DatasetError, match="no marker measurements"):
        dataset_from_run(empty, model)


def test_sample_is_on_disk_when_sample_returns(tmp_path):
    path = tmp_path / "run.mcap"
    lg = new_log(path, flush_interval_s=3600.0)  # streams may wait; samples may not
    lg.record_joint_state("robot", np.zeros(7))
    before = path.stat().st_size
    lg.sample({"config_id": "c0", "q_measured_deg": [0.0] * 7, "markers": []})
    assert path.stat().st_size > before
    assert read_run(path).measured_config_ids == ["c0"]  # read by another handle while still open
    lg.close()
    t0 = time.monotonic()
    assert read_run(path).complete and time.monotonic() - t0 < 5


def test_marker_frames_are_all_kept_and_the_foxglove_scene_is_decimated(tmp_path):
    path = tmp_path / "run.mcap"
    t0 = 1_700_000_000_000_000_000
    with new_log(path, scene_rate_hz=30.0) as lg:
        for i in range(240):  # one second of a 240 Hz stream
            lg.record_markers("mocap", {"m1": [i + 0.123456789, 0.0, 0.0]}, log_time_ns=t0 + int(i * 1e9 / 240))
            lg.record_joint_state("robot", [np.radians(10.123456789)], log_time_ns=t0 + int(i * 1e9 / 240))
    counts = read_run(path).message_counts
    assert counts["/mocap/markers"] == 240 and counts["/joint_state"] == 240
    assert counts["/markers"] == 30
    with open(path, "rb") as fh:
        first = {ch.topic: json.loads(m.data) for _, ch, m in make_reader(fh).iter_messages(topics=["/mocap/markers", "/joint_state"])}
    assert first["/mocap/markers"]["markers"][0]["position_mm"][0] == pytest.approx(239.1235, abs=1e-9)  # 1e-4 mm
    assert first["/joint_state"]["position_deg"] == [10.123457]  # 1e-6 degree
    with new_log(tmp_path / "none.mcap", scene_rate_hz=0.0) as lg:
        lg.record_markers("mocap", {"m1": [1.0, 2.0, 3.0]})
    assert "/markers" not in read_run(tmp_path / "none.mcap").message_counts


def test_acquire_fit_reads_a_run_log_like_the_same_measurements_in_csv(tmp_path, monkeypatch):
    from typer.testing import CliRunner
    import typer

    from acquire.commands import fit as fit_command
    from calib.measure.dataset import read_csv

    model = load_robot_model(IIWA)
    csv_path = ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"
    ds = read_csv(csv_path, model)
    path = tmp_path / "run.mcap"
    order = list(dict.fromkeys(ds.config.tolist()))
    with new_log(path) as lg:
        for cid in order:
            rows = np.flatnonzero(ds.config == cid)
            lg.sample({
                "config_id": cid, "pose": ds.pose[rows[0]], "q_measured_deg": np.degrees(ds.q_rad[rows[0]]),
                "markers": [{"sensor": ds.sensor[r], "marker": ds.marker[r], "mean_mm": ds.xyz_mm[r],
                             "std_mm": [ds.std_mm[r]] * 3, "count": int(ds.count[r])} for r in rows],
            })
    got = dataset_from_run(path, model)
    idx = np.concatenate([np.flatnonzero(ds.config == cid) for cid in order])
    np.testing.assert_allclose(got.q_rad, ds.q_rad[idx], atol=1e-12)
    np.testing.assert_allclose(got.xyz_mm, ds.xyz_mm[idx], atol=1e-9)
    assert got.marker.tolist() == ds.marker[idx].tolist() and got.sensor.tolist() == ds.sensor[idx].tolist()

    # The fit command picks its loader by suffix (acquire.record.datasets); this is the one-line wiring it needs.
    from acquire.record import datasets

    monkeypatch.setitem(datasets.LOADERS, ".mcap", dataset_from_run)
    app = typer.Typer()
    app.callback()(lambda: None)
    fit_command.register(app)
    out = tmp_path / "result.json"
    res = CliRunner().invoke(app, ["fit", str(path), "--robot", str(IIWA), "-o", str(out), "--seed", "3", "--draws", "300", "--random-configs", "50",
                                      "--tool-prior-mm", "0"])  # the simulated tool is the model's
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["data"]["n_measurements"] == len(ds)
    fitted = np.array([j["value_deg"] for j in doc["joint_offsets"][1:]])
    np.testing.assert_allclose(fitted, [-0.192, 0.139, 0.099, 0.392, -0.114, 0.936], atol=0.05)  # the simulated truth


@pytest.mark.parametrize("keep", [0, 3, 8, 20, 200])
def test_a_resume_segment_killed_while_being_created_is_repaired_and_resumed(tmp_path, keep):
    path = tmp_path / "run.mcap"
    rng = np.random.default_rng(8)
    samples = [make_sample(i, rng) for i in range(3)]
    with new_log(path) as lg:
        lg.sample(samples[0])
    with RunLog.append_to(path) as lg:
        lg.sample(samples[1])
    seg1 = tmp_path / "run.resume1.mcap"
    seg1.write_bytes(seg1.read_bytes()[:keep])  # as if killed while creating resume1
    with RunLog.append_to(path) as lg:
        assert lg.path == tmp_path / "run.resume2.mcap"
        lg.sample(samples[2])
    run = read_run(path)
    assert run.samples == [samples[0], samples[2]] and run.complete
    with open(seg1, "rb") as fh:  # the repaired stub is valid MCAP for mcap's own reader
        assert list(NonSeekingReader(fh, validate_crcs=True).iter_messages()) == []
