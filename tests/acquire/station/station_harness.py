"""What the station tests share: cells as peer sessions with their daemon's control queries (not
started: no devices), a station as the router of the test on a Unix socket, runs written as folders."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from acquire.daemon import control_auth
from acquire.live.bus import Bus
from acquire.daemon.control import Authorizer, ControlServer
from acquire.daemon.service import Daemon
from acquire.daemon.config import AuthSection, DaemonConfig
from acquire.station.config import StationConfig
from acquire.station.service import Station
from acquire.daemon.tokens import new_token

TOKEN = new_token()
CREDS = control_auth.derive_credentials(TOKEN, iterations=control_auth.MIN_ITERATIONS)
JOINTS = [f"A{i}" for i in range(1, 7)]


def result_doc(offsets_deg, std_deg, n_conf, acc_before=0.4) -> dict:
    return {"format": "remaster.fit/1", "data": {"n_configurations": n_conf},
            "joint_offsets": [{"joint": j, "value_deg": float(v), "std_deg": float(s), "identifiable": True,
                               "ci95_deg": [float(v - 2 * s), float(v + 2 * s)]}
                              for j, v, s in zip(JOINTS, offsets_deg, std_deg)],
            "metrics": {"absolute": {"before": {"mean": acc_before}, "after": {"mean": 0.1}}}}


def write_run(state_dir, run_id, result: dict | None, mcap_bytes: int, mtime: float) -> None:
    """A finished run's folder on a cell: an MCAP-named file of random bytes, result.json and a report."""
    folder = state_dir / "runs" / run_id
    folder.mkdir(parents=True)
    (folder / f"{run_id}.mcap").write_bytes(np.random.default_rng(len(run_id)).bytes(mcap_bytes))
    files = [folder / f"{run_id}.mcap"]
    if result is not None:
        (folder / "result.json").write_text(json.dumps(result))
        (folder / "report.html").write_text("<html><body>report</body></html>")
        files += [folder / "result.json", folder / "report.html"]
    for f in files:
        os.utime(f, (mtime, mtime))


class Cell:
    """A cell PC: its daemon's control queries and liveliness token on a peer session."""

    def __init__(self, tmp_path, router: list[str], site: str, cell: str, serial: str, creds=CREDS,
                 daemon_cls=Daemon, keep_days: float | None = None, serve: bool = True) -> None:
        self.state_dir = tmp_path / f"{site}-{cell}"
        self.cfg = DaemonConfig(cell=cell, site=site, robot_serial=serial, fake=True, state_dir=self.state_dir,
                                archive_keep_days=keep_days)
        self.daemon = daemon_cls(self.cfg)
        self.bus = Bus(cell, site=site, config={"listen": [], "connect": router})
        self.creds, self.server = creds, None
        self.bus.liveliness_token(self.bus.key("daemon"))
        if serve:
            self.serve()

    def serve(self) -> None:
        """Answer the control queries (a daemon declares its liveliness token before this)."""
        auth = AuthSection.model_validate({"clients": [{"name": "station", "scram": self.creds.config(),
                                                        "allow": ["observe", "archive"]}]})
        self.server = ControlServer(self.bus.session, self.cfg.cell, self.daemon, Authorizer(auth), site=self.cfg.site)

    def announce(self, run_id: str) -> None:
        """What the daemon puts when a run has ended."""
        self.bus.publish(self.bus.key("archive", "ready"), {"run_id": run_id, "state": "finished"})

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
        self.bus.close()


#: The cells the station's configuration knows, and the serial each is bound to.
CELLS = {"plant-a/c1": {"robot_serial": "KR6-0001"}, "plant-b/c1": {"robot_serial": "KR6-0002"},
         "plant-a/c9": {"robot_serial": "TX60-9"}, "plant-a/rogue": {"robot_serial": "KR6-0666"}}


#: A Unix socket's path holds at most 107 bytes (sun_path); pytest's tmp_path may be longer.
_SUN_PATH_MAX = 107
#: Short socket folders made for tests whose tmp_path is too long; removed after each test (conftest.py).
SHORT_FOLDERS: list[Path] = []


def socket_endpoint(tmp_path: Path, name: str = "zenoh.sock") -> str:
    """``unixsock-stream/<path>`` of a socket only this account can make: in ``tmp_path`` (pytest
    makes it and its parents mode 0700) when the path fits in sun_path, else in a short folder
    ``/tmp/rms-<hash>`` of mode 0700 (/tmp is sticky: its entries stay their owners')."""
    path = Path(tmp_path) / name
    if len(str(path)) > _SUN_PATH_MAX:
        folder = Path("/tmp") / f"rms-{hashlib.sha256(str(tmp_path).encode()).hexdigest()[:12]}"
        folder.mkdir(mode=0o700, exist_ok=True)
        if folder not in SHORT_FOLDERS:
            SHORT_FOLDERS.append(folder)
        path = folder / name
    return f"unixsock-stream/{path}"


def remove_short_folders() -> None:
    while SHORT_FOLDERS:
        shutil.rmtree(SHORT_FOLDERS.pop(), ignore_errors=True)


def station_config(tmp_path, **overrides) -> StationConfig:
    """The station as the router of the test on a Unix socket (cells connect to it), knowing the
    cells of ``CELLS``."""
    kw = dict(archive=tmp_path / "archive", token_file=tmp_path / "unused", cells=CELLS,
              zenoh={"mode": "router", "listen": [socket_endpoint(tmp_path)], "connect": []}, chunk_bytes=64 * 1024,
              poll_s=0.2)
    return StationConfig(**{**kw, **overrides})


@pytest.fixture()
def station(tmp_path):
    with Station(station_config(tmp_path), token=TOKEN) as st:
        yield st


def wait_cells(st: Station, n: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if sum(c.alive for c in st.cell_states()) >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"{n} cells not discovered: {st.cell_states()}")


def sync_until(st: Station, site: str, cell: str, want: int, timeout: float = 30.0) -> None:
    """Routes to a just-connected cell may take a moment: sync until ``want`` runs are archived."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st.sync_cell(site, cell)
        state = next(c for c in st.cell_states() if (c.site, c.cell) == (site, cell))
        if state.archived >= want and state.pending == 0:
            return
        time.sleep(0.1)
    raise AssertionError(f"cell {site}/{cell}: {state}")
