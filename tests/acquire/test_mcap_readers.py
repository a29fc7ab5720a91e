"""The run log as independent MCAP readers see it: pymcap-cli doctor, the official TypeScript
reader (@mcap/core McapIndexedReader and McapStreamReader, run by node), and mcap's Python readers
— for a cleanly closed log and for a killed log finished by ``append_to``.

The TypeScript reader is installed with npm (pinned in ``mcap_ts/package.json``) into a cache
folder (``$REMASTER_NODE_CACHE`` or ``~/.cache/remaster/mcap-ts``); its tests skip when node/npm
is missing or the install cannot reach the registry. The doctor test skips without
``pymcap-cli`` (the ``test`` extra).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader

from acquire.record.recorder import EVENT_TOPIC, SAMPLE_TOPIC, RunLog, read_run

HERE = Path(__file__).resolve().parent
TS_DIR = HERE / "mcap_ts"


def write_log(path: Path, n_configs: int = 12, frames_per_config: int = 60, flush_interval_s: float = 0.0) -> Counter:
    """A log like a run's: 240 Hz markers, 250 Hz joints, a sample and events per configuration.
    Returns the expected message count per topic."""
    rng = np.random.default_rng(5)
    t0 = 1_750_000_000_000_000_000
    counts: Counter = Counter()
    lg = RunLog.create(path, run_id="r1", plan_text="plan: x\n", model_text="name: m\n", metadata={"seed": 1},
                       flush_interval_s=flush_interval_s, chunk_bytes=8 * 1024)
    t = t0
    for i in range(n_configs):
        for _ in range(frames_per_config):
            t += 4_000_000
            lg.record_markers("mocap", {"m1": rng.normal(0, 500, 3), "m2": None}, log_time_ns=t)
            lg.record_joint_state("fri", rng.normal(size=7), log_time_ns=t + 1)
            counts["/mocap/markers"] += 1
            counts["/joint_state"] += 1
        lg.event("settled", config_id=f"c{i:02d}")
        lg.sample({"config_id": f"c{i:02d}", "q_measured_deg": rng.normal(size=7).tolist(),
                   "markers": [{"sensor": "mocap", "marker": "m1", "mean_mm": rng.normal(0, 500, 3).tolist()}]})
        counts[EVENT_TOPIC] += 1
        counts[SAMPLE_TOPIC] += 1
        counts["/log"] += 2
    lg.close()
    counts["/markers"] = read_run(path).message_counts["/markers"]  # the decimated scene: whatever the rate gave
    assert counts["/markers"] > 0
    return counts


def killed_copy(src: Path, dst: Path, fraction: float) -> None:
    """``dst``: the first ``fraction`` of ``src`` (a writer killed mid-file), finished by a resume."""
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    RunLog.append_to(dst).close()


# --------------------------------------------------------------------------------- python
def test_python_readers_see_every_message_through_the_index(tmp_path):
    path = tmp_path / "run.mcap"
    expected = write_log(path)
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        assert len(summary.chunk_indexes) > 10  # small chunks, every one indexed
        assert all(ci.message_index_offsets for ci in summary.chunk_indexes)
        assert summary.statistics.message_count == sum(expected.values())
        got = Counter(ch.topic for _, ch, _ in reader.iter_messages())
    assert got == expected
    with open(path, "rb") as fh:
        streamed = Counter(ch.topic for _, ch, _ in NonSeekingReader(fh, validate_crcs=True).iter_messages())
    assert streamed == expected


def test_a_killed_log_becomes_an_indexed_file_with_exactly_its_complete_messages(tmp_path):
    full = tmp_path / "full.mcap"
    write_log(full)
    cut = tmp_path / "cut.mcap"
    killed_copy(full, cut, 0.6)
    recovered = read_run(cut).segments[0]
    assert recovered.complete and recovered.size < full.stat().st_size  # cut, then finished with a summary
    with open(cut, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        got = Counter(ch.topic for _, ch, _ in reader.iter_messages())
        assert reader.get_summary().statistics.message_count == sum(got.values())
    assert got == Counter(recovered.message_counts)
    assert 0 < got[SAMPLE_TOPIC] < 12


def test_a_stream_message_reaches_the_disk_without_a_further_write(tmp_path):
    path = tmp_path / "run.mcap"
    lg = RunLog.create(path, run_id="r", plan_text="", model_text="", metadata={}, flush_interval_s=0.05)
    try:
        lg.record_joint_state("fri", np.zeros(7))  # nothing follows it: the background flusher writes its chunk
        deadline = time.monotonic() + 60.0  # generous: a loaded machine may be slow to schedule the thread
        while read_run(path).message_counts.get("/joint_state", 0) == 0:
            assert time.monotonic() < deadline, "the open chunk was never written"
            time.sleep(0.02)
    finally:
        lg.close()


def test_the_flusher_and_stream_writers_share_the_file_safely(tmp_path):
    path = tmp_path / "run.mcap"
    lg = RunLog.create(path, run_id="r", plan_text="", model_text="", metadata={}, flush_interval_s=0.002)

    def stream():
        for _ in range(400):
            lg.record_joint_state("fri", np.zeros(7))

    threads = [threading.Thread(target=stream) for _ in range(3)]
    for t in threads:
        t.start()
    for i in range(10):
        lg.sample({"config_id": f"c{i}", "q_measured_deg": [0.0] * 7, "markers": []})
    for t in threads:
        t.join()
    lg.close()
    with open(path, "rb") as fh:
        got = Counter(ch.topic for _, ch, _ in make_reader(fh, validate_crcs=True).iter_messages())
    assert got["/joint_state"] == 1200 and got[SAMPLE_TOPIC] == 10


# --------------------------------------------------------------------------------- doctor
def doctor(path: Path) -> dict:
    exe = shutil.which("pymcap-cli")
    if exe is None:
        pytest.skip("pymcap-cli is not installed (pip install -e .[test])")
    proc = subprocess.run([exe, "doctor", "--format", "jsonl", str(path)], capture_output=True, text=True, timeout=120)
    lines = [json.loads(x) for x in proc.stdout.splitlines() if x.startswith("{")]
    summary = [x for x in lines if x.get("type") == "summary"]
    assert summary, f"no summary from pymcap-cli doctor: {proc.stdout[-2000:]} {proc.stderr[-2000:]}"
    findings = [x for x in lines if x.get("type") == "finding" and x.get("severity") in ("error", "warning")]
    return {"rc": proc.returncode, "summary": summary[-1], "findings": findings}


@pytest.mark.parametrize("killed", [
    pytest.param(False, id="closed", marks=pytest.mark.slow),  # ~25 s; the killed log (default) is the harder case
    pytest.param(True, id="killed-and-finished"),
])
def test_pymcap_cli_doctor_finds_no_error_and_no_warning(tmp_path, killed):
    path = tmp_path / "run.mcap"
    write_log(path)
    if killed:
        cut = tmp_path / "cut.mcap"
        killed_copy(path, cut, 0.45)
        path = cut
    d = doctor(path)
    assert d["summary"]["errors"] == 0 and d["summary"]["warnings"] == 0, d["findings"]
    assert d["rc"] == 0 and d["summary"]["complete"] is True
    assert d["summary"]["chunks"] > 1 and d["summary"]["messages"] == sum(read_run(path).segments[0].message_counts.values())


# --------------------------------------------------------------------------------- TypeScript
def ts_reader() -> Path:
    """The folder holding read_mcap.mjs with @mcap/core installed (installed on first use)."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node/npm not available: cannot run the TypeScript MCAP reader")
    pkg = json.loads((TS_DIR / "package.json").read_text())
    version = pkg["dependencies"]["@mcap/core"]
    cache = Path(os.environ.get("REMASTER_NODE_CACHE", Path.home() / ".cache" / "remaster")) / f"mcap-ts-{version}"
    cache.mkdir(parents=True, exist_ok=True)
    for name in ("package.json", "read_mcap.mjs"):
        shutil.copyfile(TS_DIR / name, cache / name)
    if not (cache / "node_modules" / "@mcap" / "core" / "package.json").exists():
        proc = subprocess.run([npm, "install", "--no-audit", "--no-fund", "--loglevel=error"], cwd=cache, capture_output=True,
                              text=True, timeout=300)
        if proc.returncode != 0:
            pytest.skip(f"npm install @mcap/core@{version} failed (offline?): {proc.stderr.strip()[-500:]}")
    return cache


def read_with_ts(path: Path) -> dict:
    folder = ts_reader()
    proc = subprocess.run(["node", "read_mcap.mjs", str(path)], cwd=folder, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("killed", [
    pytest.param(False, id="closed", marks=pytest.mark.slow),  # ~25 s; the killed log (default) is the harder case
    pytest.param(True, id="killed-and-finished"),
])
def test_typescript_indexed_and_stream_readers_see_every_message(tmp_path, killed):
    path = tmp_path / "run.mcap"
    expected = write_log(path)
    if killed:
        cut = tmp_path / "cut.mcap"
        killed_copy(path, cut, 0.7)
        path = cut
        expected = Counter(read_run(path).segments[0].message_counts)
    got = read_with_ts(path)
    idx = got["indexed"]
    assert idx["topics"] == dict(expected)
    assert idx["messages"] == idx["statistics_messages"] == got["stream"]["messages"] == sum(expected.values())
    assert idx["samples"] == [s["config_id"] for s in read_run(path).segments[0].samples]
    assert idx["ordered"] and idx["chunks"] > 1
    assert idx["metadata"] == ["remaster.run", "remaster.run.metadata", "remaster.plan", "remaster.robot_model"]
    assert idx["attachments"] == ["plan.yaml", "robot.yaml"]
    assert got["stream"]["footer"] and got["stream"]["done"]
