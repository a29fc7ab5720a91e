"""acquire.record.mcapfile: chunk bounds, corrupt chunks, and logs written by the earlier unchunked RunLog."""

from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from acquire.record.mcapfile import ChunkedWriter, McapFileError, scan
from acquire.record.recorder import EVENT_SCHEMA, SAMPLE_SCHEMA, SAMPLE_TOPIC, RunLog, read_run


def test_chunks_close_at_their_size_bound_and_the_file_reads_back():
    buf = io.BytesIO()
    w = ChunkedWriter(buf, chunk_bytes=1000)
    w.start()
    sid = w.add_schema("s", "jsonschema", b"{}")
    cid = w.add_channel("/a", "json", sid)
    payload = json.dumps({"x": list(range(20))}).encode()
    for i in range(100):
        w.add_message(cid, 1000 + i, payload, 1000 + i, sequence=i)
        assert w.pending_messages * (len(payload) + 31) < 1000 + len(payload) + 31
    w.close_chunk()
    assert w.pending_messages == 0 and w.close_chunk() is False  # nothing left to write
    w.finish()
    buf.seek(0)
    reader = make_reader(buf, validate_crcs=True)
    summary = reader.get_summary()
    assert len(summary.chunk_indexes) >= 100 * (len(payload) + 31) // 1000
    assert [m.sequence for _, _, m in reader.iter_messages()] == list(range(100))
    with pytest.raises(ValueError, match="unknown schema id 7"):
        w.add_channel("/b", "json", 7)
    with pytest.raises(ValueError, match="unknown channel id 9"):
        w.add_message(9, 0, b"{}", 0)


def test_a_corrupt_chunk_ends_the_readable_part_without_an_exception(tmp_path):
    path = tmp_path / "run.mcap"
    with RunLog.create(path, run_id="r", plan_text="", model_text="", metadata={}) as lg:
        for i in range(6):
            lg.sample({"config_id": f"c{i}", "q_measured_deg": [0.0] * 7, "markers": []})
    data = bytearray(path.read_bytes())
    at = data.index(b'"config_id":"c3"')
    data[at + 14] ^= 0x01  # one flipped bit inside the fourth sample's chunk: its CRC no longer matches
    path.write_bytes(bytes(data))
    run = read_run(path)
    assert run.measured_config_ids == ["c0", "c1", "c2"] and not run.complete
    with open(path, "rb") as fh:
        res = scan(fh, len(data))
    assert "CRC" in res.stop_reason
    (tmp_path / "x.mcap").write_bytes(b"PK\x03\x04 zip, not mcap")
    with open(tmp_path / "x.mcap", "rb") as fh, pytest.raises(McapFileError, match="not an MCAP file"):
        scan(fh, 20)


def _old_unchunked_log(path, n: int) -> list[dict]:
    """A log as the earlier RunLog wrote it: mcap Writer(use_chunking=False), same records."""
    samples = [{"config_id": f"c{i}", "q_measured_deg": [float(i)] * 7, "markers": []} for i in range(n)]
    with open(path, "wb") as fh:
        w = Writer(fh, use_chunking=False, compression=CompressionType.NONE)
        w.start(profile="", library="remaster")
        w.add_metadata("remaster.run", {"format": "remaster-run/1", "run_id": "old", "segment": "0"})
        w.add_metadata("remaster.run.metadata", {})
        w.add_metadata("remaster.plan", {"text": "plan"})
        w.add_metadata("remaster.robot_model", {"text": "model"})
        s1 = w.register_schema("remaster.Sample", "jsonschema", json.dumps(SAMPLE_SCHEMA).encode())
        s2 = w.register_schema("remaster.RunEvent", "jsonschema", json.dumps(EVENT_SCHEMA).encode())
        c1 = w.register_channel(SAMPLE_TOPIC, "json", s1)
        w.register_channel("/run/event", "json", s2)
        for i, s in enumerate(samples):
            w.add_message(c1, time.time_ns(), json.dumps(s).encode(), time.time_ns(), sequence=i + 1)
        w.finish()
    return samples


def test_logs_of_the_earlier_unchunked_format_still_read_and_resume(tmp_path):
    path = tmp_path / "old.mcap"
    samples = _old_unchunked_log(path, 5)
    run = read_run(path)
    assert run.samples == samples and run.complete and run.run_id == "old"
    data = path.read_bytes()
    cut = data.index(b'"config_id": "c3"') + 4  # killed while writing the fourth sample
    path.write_bytes(data[:cut])
    assert read_run(path).measured_config_ids == ["c0", "c1", "c2"]
    with RunLog.append_to(path) as lg:
        lg.sample({"config_id": "c3", "q_measured_deg": [3.0] * 7, "markers": []})
    run = read_run(path)
    assert run.measured_config_ids == ["c0", "c1", "c2", "c3"] and run.complete
    with open(path, "rb") as fh:  # the finished old segment: its summary counts what it holds
        assert make_reader(fh).get_summary().statistics.message_count == 3
    np.testing.assert_allclose(run.samples[3]["q_measured_deg"], [3.0] * 7)
