"""The station as a plant needs it, over real Zenoh sessions (loopback, ephemeral ports) and the real
SCRAM-authenticated archive operations:

- a run is filed under the serial the station's configuration binds to the cell, never the one
  the cell reports: a cell claiming another robot's serial is refused and that robot's run stays;
- a 1 TiB announcement is refused before any chunk is asked for;
- the scrub finds a corrupted result.json (one digit) and a truncated MCAP, quarantines them, and
  the next sync fetches them again from the cell; once re-verified the cell may delete the run;
- a frozen cell does not delay the others; a cell whose control queries come up after its
  liveliness token, and a run announced by its cell, are archived without waiting for the poll.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import numpy as np
from station_harness import (TOKEN, Cell, result_doc, socket_endpoint, station, station_config,  # noqa: F401
                             sync_until, wait_cells, write_run)

from acquire.daemon.service import Daemon
from acquire.station.archive import RunRef
from acquire.station.history import load_history
from acquire.station.scrub import scrub
from acquire.station.service import Station

STD = np.full(6, 0.005)


def _until(cond, timeout: float, what: str, poll: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _answered_error(station: Station, site: str, cell: str) -> str | None:
    """Sync a cell once; its error once it has answered (before, a just-joined cell may not reply yet)."""
    assert station.sync_cell(site, cell) == 0
    state = next(c for c in station.cell_states() if (c.site, c.cell) == (site, cell))
    return state.last_error if state.answered else None


def _alert_command(path) -> list[str]:
    """An alert hook that appends each event (JSON on stdin) as one line to ``path``."""
    return [sys.executable, "-c", f"import sys; open({str(path)!r}, 'a').write(sys.stdin.read() + '\\n')"]


def test_a_cell_claiming_another_robots_serial_is_refused_and_that_robots_run_stays(tmp_path):
    events = tmp_path / "alerts.jsonl"
    cfg = station_config(tmp_path, alert={"command": _alert_command(events)})
    with Station(cfg, token=TOKEN) as station:
        victim = Cell(tmp_path, station.bus.locators, "plant-b", "c1", "KR6-0002")
        liar = Cell(tmp_path, station.bus.locators, "plant-a", "c1", "KR6-0002")   # bound to KR6-0001
        try:
            write_run(victim.state_dir, "r-1", result_doc(np.zeros(6), STD, 40), 50_000, 1.7e9)
            write_run(liar.state_dir, "r-1", result_doc(np.full(6, 3.0), STD, 40), 40_000, 1.7e9)  # same folder name
            wait_cells(station, 2)
            sync_until(station, "plant-b", "c1", 1)
            (stored,) = station.archive.manifests()
            before = {p.name: p.read_bytes() for p in station.archive.folder(stored).iterdir()}
            err = _until(lambda: _answered_error(station, "plant-a", "c1"), 20, "the liar's listing")
            assert "reports robot 'KR6-0002', but the station's configuration binds it to 'KR6-0001'" in err
            assert station.archive.manifests() == [stored]
            assert {p.name: p.read_bytes() for p in station.archive.folder(stored).iterdir()} == before
            assert [e["run_id"] for e in load_history(station.archive.root, "KR6-0002")] == ["r-1"]
            assert [r["run_id"] for r in liar.daemon.archive_list()["runs"]] == ["r-1"]   # not confirmed: kept
            sent = [json.loads(line) for line in events.read_text().splitlines() if line.strip()]
            assert any(e["event"] == "refused" and e["cell"] == "c1" and "binds it to" in e["text"] for e in sent)
        finally:
            victim.close()
            liar.close()


class HugeRunDaemon(Daemon):
    """A cell that announces a 1 TiB file; counts the chunks asked of it."""

    chunks = 0

    def archive_list(self) -> dict:
        listing = super().archive_list()
        listing["runs"] = [{"run_id": "huge", "finished": "2026-11-26T10:00:00+00:00",
                            "files": [{"name": "huge.mcap", "bytes": 1 << 40, "sha256": "0" * 64}]}]
        return listing

    def archive_chunk(self, request: dict) -> dict:
        type(self).chunks += 1
        return super().archive_chunk(request)


def test_a_one_tebibyte_announcement_is_refused_before_any_chunk(tmp_path, station):
    cell = Cell(tmp_path, station.bus.locators, "plant-a", "c9", "TX60-9", daemon_cls=HugeRunDaemon)
    try:
        wait_cells(station, 1)
        err = _until(lambda: _answered_error(station, "plant-a", "c9"), 20, "the refusal")
        assert "1099511627776 bytes, over limits.max_file_bytes" in err and "before any byte" in err
        assert HugeRunDaemon.chunks == 0 and station.archive.manifests() == []
        assert not any((station.archive.root / ".incoming").iterdir())
    finally:
        cell.close()


def test_the_scrub_finds_a_corrupted_and_a_truncated_file_and_the_cell_sends_them_again(tmp_path, station):
    cell = Cell(tmp_path, station.bus.locators, "plant-a", "c1", "KR6-0001", keep_days=0)
    try:
        write_run(cell.state_dir, "cal", result_doc(np.full(6, 0.0123), STD, 40), 300_000, 1.7e9)
        wait_cells(station, 1)
        sync_until(station, "plant-a", "c1", 1)
        (m,) = station.archive.manifests()
        folder = station.archive.folder(m)
        result = (folder / "result.json").read_text()
        (folder / "result.json").write_text(result.replace("0.0123", "0.0128", 1))   # one digit
        with open(folder / "cal.mcap", "r+b") as f:
            f.truncate(100_000)
        report = station.scrub()
        assert sorted((name, why) for _, name, why in report.damaged) == [
            ("cal.mcap", "100000 bytes, the manifest says 300000"),
            ("result.json", "content does not match the manifest's sha256")]
        quarantined = sorted(p.name.split(".2")[0] for p in (station.archive.root / ".quarantine").rglob("*")
                             if p.is_file())
        assert quarantined == ["cal.mcap", "result.json"]
        again = scrub(station.archive)   # a second pass reports them as awaiting, not twice
        assert again.damaged == [] and again.awaiting == [(RunRef.of(m).tag, ["cal.mcap", "result.json"])]
        station.sync_cell("plant-a", "c1")   # the repair: fetched again from the cell, checked, put back
        assert station.archive.verify(m) == []
        for name in ("result.json", "cal.mcap"):
            assert (folder / name).read_bytes() == (cell.state_dir / "runs" / "cal" / name).read_bytes()
        assert station.cell_states()[0].repaired == 1
        # Re-verified → told to the cell → its retention policy (keep 0 days) deletes its copy.
        assert scrub(station.archive).verified == 1
        station.sync_cell("plant-a", "c1")
        assert not (cell.state_dir / "runs" / "cal").exists()
        assert station.archive.verify(m) == []
    finally:
        cell.close()


class FrozenDaemon(Daemon):
    """A daemon whose listing hangs until released (a cell PC frozen mid-exchange)."""

    release = threading.Event()

    def archive_list(self) -> dict:
        self.release.wait(60)
        return super().archive_list()


def test_a_frozen_cell_does_not_delay_the_others(tmp_path):
    cfg = station_config(tmp_path, cell_timeout_s=60, poll_s=60)
    FrozenDaemon.release.clear()
    with Station(cfg, token=TOKEN) as station:
        frozen = Cell(tmp_path, station.bus.locators, "plant-a", "c1", "KR6-0001", daemon_cls=FrozenDaemon)
        ok = Cell(tmp_path, station.bus.locators, "plant-b", "c1", "KR6-0002")
        loop = threading.Thread(target=station.run, daemon=True)
        try:
            write_run(frozen.state_dir, "f1", result_doc(np.zeros(6), STD, 40), 10_000, 1.7e9)
            write_run(ok.state_dir, "o1", result_doc(np.zeros(6), STD, 40), 10_000, 1.7e9)
            wait_cells(station, 2)
            loop.start()
            _until(lambda: station.archive.manifest(RunRef("plant-b", "c1", "o1", "KR6-0002")), 30,
                   "the healthy cell's run while the other is frozen")
            assert not FrozenDaemon.release.is_set()
            assert station.archive.manifest(RunRef("plant-a", "c1", "f1", "KR6-0001")) is None
            FrozenDaemon.release.set()   # the cell thaws: its run comes in too
            _until(lambda: station.archive.manifest(RunRef("plant-a", "c1", "f1", "KR6-0001")), 30, "the thawed cell")
        finally:
            FrozenDaemon.release.set()
            station.request_stop()
            loop.join(30)
            frozen.close()
            ok.close()


class HookedDaemon(Daemon):
    """A daemon that runs ``on_confirm()`` once, inside its first ``archive-confirm`` (while the
    station's sync of this cell is still under way)."""

    on_confirm = None

    def archive_confirm(self, request, identity):
        reply = super().archive_confirm(request, identity)
        hook, self.on_confirm = self.on_confirm, None
        if hook is not None:
            hook()
        return reply


def test_a_cell_that_answers_late_and_an_announced_run_are_archived_without_waiting_for_the_poll(tmp_path):
    """Late answers are retried quickly; a run announced while the cell is being synced (after its
    listing) is fetched by one more sync, not by the 600 s poll."""
    with Station(station_config(tmp_path, poll_s=600), token=TOKEN) as station:
        cell = Cell(tmp_path, station.bus.locators, "plant-a", "c1", "KR6-0001", serve=False, daemon_cls=HookedDaemon)
        loop = threading.Thread(target=station.run, daemon=True)
        try:
            write_run(cell.state_dir, "r1", result_doc(np.zeros(6), STD, 40), 10_000, 1.7e9)
            loop.start()
            wait_cells(station, 1)
            time.sleep(0.5)   # its token is up, its queries are not: the station keeps asking, briefly
            assert station.archive.manifests() == []
            cell.daemon.on_confirm = lambda: (
                write_run(cell.state_dir, "r2", result_doc(np.zeros(6), STD, 8), 10_000, 1.7e9 + 3600),
                cell.announce("r2"))
            cell.serve()
            _until(lambda: station.archive.manifests(), 30, "the first run once the cell answers")
            _until(lambda: len(station.archive.manifests()) == 2, 30, "the run announced during the sync")
        finally:
            station.request_stop()
            loop.join(30)
            cell.close()


def test_the_station_is_a_client_of_the_sites_router_and_its_restart_leaves_the_cells_reachable(tmp_path):
    """``acquire router`` (its own process) routes; the station and a cell are its clients. With the
    station stopped, an operator still reaches the cell through the router."""
    import os
    import subprocess
    from pathlib import Path

    from acquire.live.bus import Bus
    from acquire.daemon.control import ControlClient

    endpoint = [socket_endpoint(tmp_path, "router.sock")]
    (tmp_path / "router.yaml").write_text(f"listen: ['{endpoint[0]}']\n")
    root = Path(__file__).resolve().parents[3]
    router = subprocess.Popen([sys.executable, "-m", "acquire", "router", "--config", str(tmp_path / "router.yaml")],
                              env=dict(os.environ, PYTHONPATH=str(root)), stderr=subprocess.PIPE, text=True)
    cfg = station_config(tmp_path, zenoh={"mode": "client", "listen": [], "connect": endpoint})
    try:
        _until(lambda: _router_up(endpoint), 60, "the router to accept a client", poll=0.2)
        cell = Cell(tmp_path, endpoint, "plant-a", "c1", "KR6-0001")
        try:
            write_run(cell.state_dir, "r1", result_doc(np.zeros(6), STD, 40), 10_000, 1.7e9)
            with Station(cfg, token=TOKEN) as station:
                wait_cells(station, 1)
                sync_until(station, "plant-a", "c1", 1)
            with Bus("operator", config={"mode": "client", "connect": endpoint}) as op:
                client = ControlClient(op.session, "c1", site="plant-a", client="station", token=TOKEN)
                assert client.call("archive-list", timeout=20.0)["runs"] == []   # confirmed, through the router
        finally:
            cell.close()
    finally:
        router.terminate()
        _, err = router.communicate(timeout=30)
        assert router.returncode == 0, err


def _router_up(endpoint) -> bool:
    from acquire.live.bus import Bus, BusError

    try:
        with Bus("probe", config={"mode": "client", "connect": endpoint}):
            return True
    except BusError:
        return False
