"""``acquire station``: a bad configuration names file, line and field (exit 2); ``--once`` archives a
cell's run end to end (the station a peer connecting to the cell's session on a Unix socket)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from acquire.daemon import control_auth
from acquire.station.config import load_station_config
from acquire.daemon.tokens import new_token, write_token_file
from calib.io.yamlfile import ConfigError
from station_harness import socket_endpoint

ROOT = Path(__file__).resolve().parents[3]


def _acquire(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "acquire", *args], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=timeout)


def test_a_bad_station_configuration_names_file_line_and_field(tmp_path):
    cfg = tmp_path / "station.yaml"
    cfg.write_text("archive: a\ntoken_file: t\ndrift:\n  alpha: 2\n")
    with pytest.raises(ConfigError, match=r"station.yaml:4.*drift.alpha"):
        load_station_config(cfg)
    out = _acquire("station", "--config", str(cfg))
    assert out.returncode == 2 and "drift.alpha" in out.stderr


@pytest.mark.slow
def test_station_once_archives_a_cells_run_end_to_end(tmp_path):
    from acquire.live.bus import Bus
    from acquire.daemon.control import Authorizer, ControlServer
    from acquire.daemon.service import Daemon
    from acquire.daemon.config import AuthSection, DaemonConfig

    token = new_token()
    write_token_file(tmp_path / "station.token", token)
    creds = control_auth.derive_credentials(token, iterations=control_auth.MIN_ITERATIONS)
    daemon = Daemon(DaemonConfig(cell="c1", site="s1", robot_serial="R1", fake=True, state_dir=tmp_path / "cell"))
    run = tmp_path / "cell" / "runs" / "r1"
    run.mkdir(parents=True)
    (run / "r1.mcap").write_bytes(np.random.default_rng(0).bytes(100_000))
    with Bus("c1", site="s1", config={"listen": [socket_endpoint(tmp_path)]}) as bus:
        auth = AuthSection.model_validate({"clients": [{"name": "station", "scram": creds.config(), "allow": ["archive"]}]})
        server = ControlServer(bus.session, "c1", daemon, Authorizer(auth), site="s1")
        bus.liveliness_token(bus.key("daemon"))
        (tmp_path / "station.yaml").write_text(
            f"archive: archive\ntoken_file: station.token\ncells: {{s1/c1: {{robot_serial: R1}}}}\n"
            f"zenoh: {{mode: peer, listen: [], connect: {json.dumps(bus.locators)}}}\n")
        try:
            out = _acquire("station", "--config", str(tmp_path / "station.yaml"), "--once", "--wait", "4")
        finally:
            server.close()
    assert out.returncode == 0, out.stderr
    assert "1 run(s) archived from 1 cell(s)" in out.stdout
    assert (tmp_path / "archive" / "R1").is_dir() and (run / ".archived").exists()


def test_the_shipped_example_configuration_loads():
    cfg = load_station_config(ROOT / "systemd" / "station.yaml.example")
    assert cfg.zenoh.mode == "client" and cfg.drift.policy().accuracy_limit_mm is None
    assert cfg.cell("plant-a", "c7").robot_serial == "KR6-0815" and cfg.cell("plant-a", "c9") is None


def test_station_verify_reports_and_quarantines_a_damaged_file_and_exits_3(tmp_path):
    import hashlib

    from acquire.station.archive import Archive, RunRef

    content = {"r1.mcap": bytes(range(256)) * 100, "result.json": b'{"offset": 0.0123}'}
    archive = Archive(tmp_path / "archive")
    t = archive.begin(RunRef("s1", "c1", "r1", "R1"),
                      [{"name": n, "bytes": len(b), "sha256": hashlib.sha256(b).hexdigest()} for n, b in content.items()],
                      "2026-11-26T10:00:00+00:00")
    for name, data in content.items():
        t.write(name, 0, data)
    folder = archive.folder(t.finish())
    (tmp_path / "station.yaml").write_text("archive: archive\ntoken_file: station.token\n")
    from acquire.station.scrub import scrub

    assert scrub(archive).lines()[0] == "1 run(s), 25618 bytes read back: 1 intact, 0 damaged now, 0 awaiting a copy from their cell"
    (folder / "result.json").write_bytes(b'{"offset": 0.0128}')
    out = _acquire("station", "verify", "--config", str(tmp_path / "station.yaml"))
    assert out.returncode == 3, out.stderr
    assert "DAMAGED s1~c1~r1: result.json: content does not match the manifest's sha256" in out.stdout
    assert not (folder / "result.json").exists()
    assert [p.read_bytes() for p in (tmp_path / "archive" / ".quarantine").rglob("result.json.*")] == [
        b'{"offset": 0.0128}']


@pytest.mark.parametrize("service", ["station", "router"])
def test_the_station_and_the_router_tell_systemd_they_are_ready_and_alive_and_stop_cleanly(tmp_path, service):
    """``Type=notify`` and ``WatchdogSec=``: READY=1 once serving, WATCHDOG=1 while the loop runs,
    STOPPING=1 and exit 0 on SIGTERM (a NOTIFY_SOCKET stand-in; the station as its own router here)."""
    import signal

    from daemon_harness import NotifySocket

    write_token_file(tmp_path / "station.token", new_token())
    endpoint = socket_endpoint(tmp_path)
    if service == "station":
        (tmp_path / "cfg.yaml").write_text(
            f"archive: archive\ntoken_file: station.token\nzenoh: {{mode: router, listen: ['{endpoint}'], connect: []}}\n")
    else:
        (tmp_path / "cfg.yaml").write_text(f"listen: ['{endpoint}']\n")
    notify = NotifySocket()
    env = dict(os.environ, PYTHONPATH=str(ROOT), NOTIFY_SOCKET=notify.name, WATCHDOG_USEC="2000000")
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([sys.executable, "-m", "acquire", service, "--config", str(tmp_path / "cfg.yaml")],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        notify.wait_for(lambda f: f.get("READY") == "1", 90)
        notify.wait_for(lambda f: f.get("WATCHDOG") == "1", 30)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        notify.wait_for(lambda f: f.get("STOPPING") == "1", 5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        notify.close()
