"""Disk full mid-run (issue 21): one clear line, no tracebacks, the log sealed readable, resumable.

The disk is simulated (``fake_disk.py``: a byte budget behind ``acquire.record.logstorage``'s system
calls, a text log that fails once the disk was full) because a small tmpfs is not available to
tests. Everything else is a real ``acquire run --fake`` process.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader

from acquire.live.console import TextLogHandler
from acquire.record.logstorage import RESERVE_MIN_BYTES, RESERVE_SUFFIX, LogFile, StorageError
from acquire.plan.schema import load_plan, resolve_configurations
from acquire.record.recorder import RunLog, read_run

from run_helpers import ROOT, popen, run_logs, small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest

pytestmark = pytest.mark.timeout(300)
FAKE_DISK = Path(__file__).with_name("fake_disk.py")


def _mcap_messages(path: Path) -> Counter:
    """Messages per topic as the ``mcap`` package's reader sees them (the summary, then the index)."""
    with open(path, "rb") as f:
        return Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages())


@pytest.mark.slow  # ~70 s: two whole fake runs; the storage faults themselves are tests/acquire/test_logstorage.py's
def test_a_full_disk_stops_the_run_in_one_line_with_the_log_readable_and_resume_completes_it(tmp_path):
    plan = small_plan(tmp_path, n=8, sequencing={"samples": 5, "settle_window_s": 0.2}, fake={"time_scale": 6.0})
    configs = {c.config_id for c in resolve_configurations(load_plan(plan))}
    args = ("run", str(plan), "--fake", "--no-bus", "--no-fit")
    # The first reserve, the log's header records and about two configurations' worth of streams.
    budget = RESERVE_MIN_BYTES + 150_000
    out = subprocess.run([sys.executable, str(FAKE_DISK), str(budget), *args], cwd=ROOT, capture_output=True, text=True,
                         timeout=240, stdin=subprocess.DEVNULL, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 1, out.stderr[-3000:]
    assert "Traceback" not in out.stderr and "Logging error" not in out.stderr, out.stderr[-3000:]
    errors = [line for line in out.stderr.splitlines() if line.startswith("ERROR")]
    assert len(errors) == 1, errors
    [log] = run_logs(tmp_path / "runs")
    assert re.fullmatch(rf"ERROR acquire\.run: run \S+ stopped: cannot write the run log {re.escape(str(log))}: "
                        r"No space left on device \([0-9.]+ k?M?G?B free on its file system\); the log is closed at "
                        r"its last complete record \([0-9.]+ k?M?B, readable\)", errors[0]), errors[0]
    assert f"resume with: acquire run {plan} --resume " in out.stdout, out.stdout

    # Sealed: complete and indexed for every reader, holding exactly what remaster reads back.
    first = read_run(log)
    assert first.complete and first.dropped_bytes == 0
    topics = _mcap_messages(log)
    assert topics["/run/sample"] == len(first.samples) and topics["/run/event"] == len(first.events)
    assert len(first.samples) < len(configs)
    # The text log failed too (fake_disk: from the first ENOSPC on) and stopped without a word.
    assert "stopped: cannot write the run log" not in log.with_suffix(".log").read_text()
    assert not list(log.parent.glob(f"*{RESERVE_SUFFIX}"))  # the reserve was spent on the summary
    # The robot held: no configuration was moved to after the one in flight when the disk filled
    # (the fake cell answers every move; "move to" is the commander's line for each).
    moves = sum(1 for line in out.stderr.splitlines() if "remaster.device.fri: move to [" in line)
    assert moves <= len(first.samples) + 1, (moves, len(first.samples))

    # Space freed: the resume measures the rest, each configuration once.
    proc = popen(*args, "--resume", str(log))
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 0, err[-3000:]
    contents = read_run(log)
    counts = Counter(s["config_id"] for s in contents.samples)
    ended = {e["config_id"] for e in contents.events if e["kind"] in ("skipped", "failed")}
    assert max(counts.values()) == 1 and set(counts) | ended == configs
    assert sum(_mcap_messages(segment)["/run/sample"] for segment in contents.files) == len(contents.samples)


@pytest.mark.parametrize("stays_full", [False, True])
def test_log_file_seals_at_the_last_complete_record_and_refuses_further_writes(tmp_path, monkeypatch, stays_full):
    """The disk fills in the middle of a sample's write. Releasing the reserve makes room for the
    summary (sealed), or — ``stays_full``, another writer took it — the file is cut after its last
    complete record and the resume finishes it."""
    import acquire.record.logstorage as storage

    path = tmp_path / "r.mcap"
    rl = RunLog.create(path, run_id="r1", plan_text="plan: 1\n", model_text="model: 1\n", metadata={}, flush_interval_s=0)
    rl.sample({"config_id": "c1", "q_measured_deg": [1.0], "markers": []})
    assert (tmp_path / ("r.mcap" + RESERVE_SUFFIX)).stat().st_size >= RESERVE_MIN_BYTES
    calls = []

    def disk(fd, data):
        calls.append(len(data))
        if len(calls) == 1:
            return os.write(fd, bytes(data[: len(data) // 2]))  # the disk fills in the middle of this write
        if len(calls) == 2 or stays_full:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(storage, "_write", disk)
    with pytest.raises(StorageError) as exc:
        rl.sample({"config_id": "c2", "q_measured_deg": [2.0], "markers": []})
    err = exc.value
    assert err.errno == errno.ENOSPC and err.sealed is not stays_full and err.path == path and err.free_bytes is not None
    assert "\n" not in str(err) and str(err).startswith(f"cannot write the run log {path}: No space left on device (")
    assert ("--resume completes it" in str(err)) is stays_full
    monkeypatch.undo()  # space again: still nothing is written after the failure
    with pytest.raises(StorageError) as again:
        rl.event("after")
    assert again.value is err
    rl.write("/run/event", {"kind": "stream"})  # stream messages are dropped without a word
    rl.close()
    contents = read_run(path)
    assert contents.complete is not stays_full and [s["config_id"] for s in contents.samples] == ["c1"]
    assert contents.dropped_bytes == 0  # cut exactly after the last complete record
    if not stays_full:
        assert _mcap_messages(path)["/run/sample"] == 1
    assert not (tmp_path / ("r.mcap" + RESERVE_SUFFIX)).exists()
    # Resume after space was freed: a new segment; the first is finished if it was not.
    rl2 = RunLog.append_to(path, flush_interval_s=0)
    rl2.sample({"config_id": "c2", "q_measured_deg": [2.0], "markers": []})
    rl2.close()
    assert [s["config_id"] for s in read_run(path).samples] == ["c1", "c2"]
    assert _mcap_messages(path)["/run/sample"] == 1


def test_log_file_refuses_to_grow_its_reserve_on_a_full_disk(tmp_path, monkeypatch):
    import acquire.record.logstorage as storage

    def no_room(fd, offset, size):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(storage, "_fallocate", no_room)
    with pytest.raises(StorageError, match="No space left on device"):
        RunLog.create(tmp_path / "r.mcap", run_id="r1", plan_text="p: 1\n", model_text="m: 1\n", metadata={})
    assert read_run(tmp_path / "r.mcap").complete  # even a log that could not start is a valid file


def test_text_log_handler_stops_quietly_on_a_full_disk(tmp_path, capsys):
    handler = TextLogHandler(tmp_path / "run.log", encoding="utf-8", delay=True)

    class Full:
        def write(self, text):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def flush(self):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def close(self):
            pass

    handler.stream = Full()
    log = logging.getLogger("test-text-log-full")
    log.addHandler(handler)
    log.propagate = False  # only this handler: a console handler another test left on the root would echo
    try:
        for i in range(5):
            log.error("record %d", i)
    finally:
        log.removeHandler(handler)
        log.propagate = True
    handler.close()
    assert isinstance(handler.failed, OSError) and handler.failed.errno == errno.ENOSPC
    assert capsys.readouterr().err == ""  # no "--- Logging error ---" per record


def test_a_disk_full_but_for_the_reserve_still_closes_the_log_normally(tmp_path, monkeypatch, caplog):
    import acquire.record.logstorage as storage
    import fake_disk  # tests/acquire: the byte budget behind logstorage's system calls

    monkeypatch.setattr(fake_disk, "state", {"left": 10**9, "sizes": {}, "full": False})
    for name in ("write", "fallocate", "unlink"):
        monkeypatch.setattr(storage, f"_{name}", getattr(fake_disk, name))
    path = tmp_path / "r.mcap"
    rl = RunLog.create(path, run_id="r1", plan_text="plan: 1\n", model_text="model: 1\n", metadata={}, flush_interval_s=0)
    rl.sample({"config_id": "c1", "q_measured_deg": [1.0], "markers": []})
    fake_disk.state["left"] = 0  # every byte but the reserve's is taken
    with caplog.at_level(logging.ERROR):
        rl.close()  # gives the reserve back, then writes the summary in its space
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]  # no storage error: closed as usual
    assert not fake_disk.state["full"] and read_run(path).complete
    assert _mcap_messages(path)["/run/sample"] == 1
