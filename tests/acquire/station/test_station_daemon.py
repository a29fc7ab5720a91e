"""End to end: a real ``acquire daemon`` (simulated cell) on site ``plant-a`` runs the example plan;
its keys carry the site; the station finds it by liveliness, is told the run ended, archives the
run (MCAP log, the run's text log, result.json, report) and enters it into the robot's history;
the cell then offers it no more."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from daemon_harness import (CELL, OPERATOR_TOKEN, DaemonProcess, NotifySocket, free_port,  # noqa: E402
                            scram, wait_until, write_config)
from station_harness import socket_endpoint  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.timeout(480)]  # a whole run of the example plan


def test_a_sited_daemons_run_is_archived_by_the_station(tmp_path):
    from acquire.live.bus import Bus
    from acquire.daemon.control import ControlClient
    from acquire.station.config import StationConfig
    from acquire.station.history import load_history
    from acquire.station.service import Station
    from acquire.daemon.tokens import new_token

    token = new_token()
    port = free_port()
    link = socket_endpoint(tmp_path)   # the station's link to the daemon's router (never tcp/)
    config = write_config(tmp_path, port, site="plant-a", robot_serial="IIWA-42",
                          zenoh={"listen": [f"tcp/127.0.0.1:{port}", link]})
    import yaml

    cfg = yaml.safe_load(config.read_text())
    cfg["auth"]["clients"].append({"name": "station", "scram": scram(token), "allow": ["archive"]})
    config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    notify = NotifySocket()
    proc = DaemonProcess(config, notify)
    scfg = StationConfig(archive=tmp_path / "archive", token_file=tmp_path / "unused", poll_s=600,
                         cells={f"plant-a/{CELL}": {"robot_serial": "IIWA-42"}},
                         zenoh={"mode": "peer", "listen": [], "connect": [link]})
    try:
        proc.wait_ready(60)
        with Station(scfg, token=token) as station, \
                Bus(CELL, site="plant-a", config={"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}) as bus:
            wait_until(lambda: any(c.cell == CELL and c.site == "plant-a" for c in station.cell_states()), 20,
                       "the station discovering the daemon")
            events: list[str] = []
            bus.subscribe(f"remaster/plant-a/{CELL}/run/*/event", lambda k, p: events.append(k))
            op = ControlClient(bus.session, CELL, site="plant-a", client="operator", token=OPERATOR_TOKEN)
            wait_until(lambda: _try(op), 20, "the daemon's control queries with the site in their keys")
            loop = threading.Thread(target=station.run, daemon=True)
            loop.start()   # its first sync finds nothing; the next comes from the run's announcement (poll 600 s)
            wait_until(lambda: station.cell_states()[0].last_sync, 30, "the station's first sync")
            run_id = op.call("start", {"plan": "example.yaml"})["run_id"]
            wait_until(lambda: op.call("status")["run"] is None, 240, "the run to end", poll=0.5)
            assert any(f"/run/{run_id}/event" in k for k in events)
            history = wait_until(lambda: load_history(station.archive.root, "IIWA-42"), 60, "the run in the history",
                                 poll=0.5)
            station.request_stop()
            loop.join(30)
        (manifest,) = station.archive.manifests()
        names = {f["name"] for f in manifest["files"]}
        assert {f"{run_id}.mcap", f"{run_id}.log", "result.json", "report.html"} <= names
        text_log = (station.archive.folder(manifest) / f"{run_id}.log").read_text()
        assert f"run {run_id} started by" in text_log
        assert station.archive.verify(manifest) == []
        assert history[0]["run_id"] == run_id and history[0]["kind"] == "calibration"
        assert (tmp_path / "state" / "runs" / run_id / ".archived").exists()
    finally:
        assert proc.stop() == 0
        notify.close()


def _try(op) -> bool:
    from acquire.daemon.control import ControlError

    try:
        return op.call("status", timeout=2.0)["daemon"] == "ready"
    except ControlError:
        return False
