"""Cells discovered through a router and their runs archived; an interrupted transfer resumed;
a drifted robot flagged through the station; a cell without credentials archives nothing.

Every session is on loopback with explicit endpoints (ephemeral ports, no scouting): the station
is the router, each cell a peer connected to it, its daemon (``acquire.daemon.service.Daemon``, not
started: no devices) answering the control queries.
"""

from __future__ import annotations

import time

import numpy as np
from station_harness import Cell, result_doc, station, sync_until, wait_cells, write_run  # noqa: F401

from acquire.daemon import control_auth
from acquire.daemon.service import Daemon
from acquire.station.archive import RunRef
from acquire.station.history import load_history
from acquire.daemon.tokens import new_token


def test_cells_are_discovered_through_the_router_and_runs_archived_once(tmp_path, station):
    std = np.full(6, 0.005)
    c1 = Cell(tmp_path, station.bus.locators, "plant-a", "c1", "KR6-0001")
    c2 = Cell(tmp_path, station.bus.locators, "plant-b", "c1", "KR6-0002")  # same cell id, other site
    try:
        write_run(c1.state_dir, "c1-cal", result_doc(np.zeros(6), std, 40), 200_000, 1.7e9)
        write_run(c1.state_dir, "c1-chk", result_doc([0, 0, 0.1, 0, 0, 0], 2 * std, 8), 30_000, 1.7e9 + 86400)
        write_run(c2.state_dir, "c2-cal", result_doc(np.zeros(6), std, 40), 150_000, 1.7e9)
        write_run(c2.state_dir, "c2-chk", result_doc(np.full(6, 0.004), 2 * std, 8), 30_000, 1.7e9 + 86400)
        write_run(c2.state_dir, "c2-aborted", None, 5_000, 1.7e9 + 2 * 86400)  # no result: kept all the same
        wait_cells(station, 2)
        sync_until(station, "plant-a", "c1", 2)
        sync_until(station, "plant-b", "c1", 3)
        manifests = station.archive.manifests()
        assert sorted(m["run_id"] for m in manifests) == ["c1-cal", "c1-chk", "c2-aborted", "c2-cal", "c2-chk"]
        assert all(station.archive.verify(m) == [] for m in manifests)
        folder = station.archive.folder(station.archive.manifest(RunRef("plant-a", "c1", "c1-cal", "KR6-0001")))
        assert folder.relative_to(tmp_path / "archive").parts == ("KR6-0001", "2023-11-14", "c1-cal")
        assert (folder / "c1-cal.mcap").read_bytes() == (c1.state_dir / "runs/c1-cal/c1-cal.mcap").read_bytes()
        # Confirmed: the cells offer them no more, and a second sync archives nothing.
        assert c1.daemon.archive_list()["runs"] == [] and c2.daemon.archive_list()["runs"] == []
        assert station.sync_all() == 0 and len(station.archive.manifests()) == 5
        # The drifted robot (A3 moved 0.1°) is flagged, the stable one is not.
        h1, h2 = load_history(station.archive.root, "KR6-0001"), load_history(station.archive.root, "KR6-0002")
        assert [e["kind"] for e in h1] == ["calibration", "check"]
        assert h1[1]["drift"]["drifted"] and h1[1]["drift"]["joints"] == ["A3"]
        assert h1[1]["drift"]["reference"] == "c1-cal"
        assert not h2[1]["drift"]["drifted"]
    finally:
        c1.close()
        c2.close()


class FlakyDaemon(Daemon):
    """A daemon whose link is cut after ``cut_after`` chunks (then restored); counts chunk requests."""

    cut_after: int | None = 3

    def __init__(self, *a, **kw) -> None:
        super().__init__(*a, **kw)
        self.chunks: list[tuple[str, int]] = []

    def archive_chunk(self, request: dict) -> dict:
        if self.cut_after is not None and len(self.chunks) >= self.cut_after:
            raise OSError("link cut")
        self.chunks.append((request["name"], request["offset"]))
        return super().archive_chunk(request)


def test_an_interrupted_transfer_resumes_without_loss_or_duplicate(tmp_path, station):
    cell = Cell(tmp_path, station.bus.locators, "plant-a", "c9", "TX60-9", daemon_cls=FlakyDaemon)
    try:
        write_run(cell.state_dir, "r1", result_doc(np.zeros(6), np.full(6, 0.01), 40), 5 * 64 * 1024 + 123, 1.7e9)
        wait_cells(station, 1)
        deadline = time.monotonic() + 30
        while not cell.daemon.chunks and time.monotonic() < deadline:
            station.sync_cell("plant-a", "c9")
        state = station.cell_states()[0]
        assert len(cell.daemon.chunks) == 3 and "link cut" in state.last_error
        assert station.archive.manifests() == []
        assert [r["run_id"] for r in cell.daemon.archive_list()["runs"]] == ["r1"]  # kept: not confirmed
        cell.daemon.cut_after = None  # the link is back
        sync_until(station, "plant-a", "c9", 1)
        mcap = [off for name, off in cell.daemon.chunks if name == "r1.mcap"]
        assert mcap == sorted(set(mcap)) and mcap == [i * 64 * 1024 for i in range(6)]  # each chunk once
        (m,) = station.archive.manifests()
        assert station.archive.verify(m) == []
        assert cell.daemon.archive_list()["runs"] == []
    finally:
        cell.close()


def test_a_cell_without_the_station_credentials_cannot_publish_into_the_archive(tmp_path, station):
    other = control_auth.derive_credentials(new_token(), iterations=control_auth.MIN_ITERATIONS)
    rogue = Cell(tmp_path, station.bus.locators, "plant-a", "rogue", "KR6-0666", creds=other)
    try:
        write_run(rogue.state_dir, "evil", result_doc(np.full(6, 5.0), np.full(6, 0.01), 40), 10_000, 1.7e9)
        wait_cells(station, 1)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            assert station.sync_cell("plant-a", "rogue") == 0
            err = station.cell_states()[0].last_error or ""
            if "Unverified" in err or "Refused" in err:
                break
            time.sleep(0.1)
        assert "Unverified" in err or "Refused" in err, err
        assert station.archive.manifests() == []
        assert load_history(station.archive.root, "KR6-0666") == []
        assert [r["run_id"] for r in rogue.daemon.archive_list()["runs"]] == ["evil"]  # never confirmed
    finally:
        rogue.close()
