"""The cell's side: finished runs offered with checksums, read in chunks, kept until confirmed."""

import base64
import hashlib

import pytest

from acquire.daemon.control import BadRequest, Conflict
from acquire.daemon.archive import CellRuns


def _run(runs, run_id, data=b"x" * 5000):
    (runs / run_id).mkdir(parents=True)
    (runs / run_id / f"{run_id}.mcap").write_bytes(data)
    return runs / run_id


def test_runs_are_offered_until_confirmed_and_again_when_they_change(tmp_path):
    cell = CellRuns(tmp_path, "R1")
    folder = _run(tmp_path, "r1")
    _run(tmp_path, "active")
    listing = cell.pending(current="active")
    assert listing["robot_serial"] == "R1" and [r["run_id"] for r in listing["runs"]] == ["r1"]
    files = listing["runs"][0]["files"]
    assert files == [{"name": "r1.mcap", "bytes": 5000, "sha256": hashlib.sha256(b"x" * 5000).hexdigest()}]
    with pytest.raises(Conflict, match="do not match"):
        cell.confirm({"run_id": "r1", "files": [dict(files[0], bytes=1)]}, "station")
    assert cell.pending("active")["runs"]  # a wrong confirmation keeps it
    cell.confirm({"run_id": "r1", "files": files}, "station")
    assert cell.pending("active")["runs"] == []
    (folder / "r1.resume1.mcap").write_bytes(b"resumed")  # resumed after it was archived
    assert [r["run_id"] for r in cell.pending("active")["runs"]] == ["r1"]


def test_chunks_are_read_at_an_offset_and_bad_requests_say_what_is_allowed(tmp_path):
    cell = CellRuns(tmp_path, "R1")
    _run(tmp_path, "r1", bytes(range(256)) * 10)
    reply = cell.chunk({"run_id": "r1", "name": "r1.mcap", "offset": 2000, "size": 1000}, current=None)
    assert base64.b64decode(reply["data"]) == (bytes(range(256)) * 10)[2000:] and reply["eof"]
    with pytest.raises(BadRequest, match="no file '../x'"):
        cell.chunk({"run_id": "r1", "name": "../x", "offset": 0}, current=None)
    with pytest.raises(BadRequest, match="run_id must be a run id"):
        cell.chunk({"run_id": "..", "name": "r1.mcap", "offset": 0}, current=None)
    with pytest.raises(Conflict, match="still active"):
        cell.chunk({"run_id": "r1", "name": "r1.mcap", "offset": 0}, current="r1")


def test_retention_deletes_a_run_only_once_the_station_re_verified_it_and_it_is_old_enough(tmp_path):
    from datetime import datetime, timedelta, timezone

    cell = CellRuns(tmp_path, "R1", keep_days=7)
    for run_id in ("old", "young", "changed", "unverified"):
        _run(tmp_path, run_id)
        files = cell.pending(None)["runs"][0]["files"]
        cell.confirm({"run_id": run_id, "files": files}, "station")
        if run_id != "unverified":
            cell.confirm({"run_id": run_id, "files": files, "verified": True}, "station")
    (tmp_path / "changed" / "changed.resume1.mcap").write_bytes(b"resumed since")   # not what the station holds
    later = datetime.now(timezone.utc) + timedelta(days=8)
    assert cell.prune(now=later, current="young") == ["old"]   # the active run is never touched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["changed", "unverified", "young"]
    assert cell.prune(now=datetime.now(timezone.utc)) == []    # too young
    with pytest.raises(Conflict, match="was not confirmed with these files"):
        cell.confirm({"run_id": "changed", "files": cell.files(tmp_path / "changed"), "verified": True}, "station")
    assert CellRuns(tmp_path, "R1").prune(now=later) == []     # no retention configured: keep everything


def test_a_daemon_offers_its_ended_run_only_once_it_has_let_it_go(tmp_path):
    """An ended run's text log still takes lines until the daemon closes it: the run is listed as
    current (not offered) until then, and offered as soon as it is closed."""
    from acquire.daemon.config import DaemonConfig
    from acquire.daemon.service import Daemon

    daemon = Daemon(DaemonConfig(cell="c1", robot_serial="R1", fake=True, state_dir=tmp_path))
    _run(daemon.runs_dir, "r1")

    class Ended:
        run_id = "r1"

        @staticmethod
        def status() -> dict:
            return {"state": "finished", "run_id": "r1"}

    daemon.controller = Ended()
    assert daemon.archive_list()["runs"] == []
    daemon._release(daemon.controller)   # its text log closed: offered while the devices come back
    assert [r["run_id"] for r in daemon.archive_list()["runs"]] == ["r1"]
