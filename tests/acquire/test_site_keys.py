"""Keys of a cell on a plant's router carry its site; a cell without a site keeps its keys."""

import json

import pytest

from acquire.live.bus import BusConfigError, control_key, key
from acquire.daemon.config import DaemonConfig


def test_a_cell_without_a_site_keeps_its_keys():
    assert key("c1", "run", "r1", "event") == "remaster/c1/run/r1/event"
    assert control_key("c1", "status") == "remaster/c1/control/status"


def test_a_cell_with_a_site_has_site_and_cell_in_every_key():
    assert key("c1", "daemon", site="plant-a") == "remaster/plant-a/c1/daemon"
    assert control_key("c1", "runs", "plant-a") == "remaster/plant-a/c1/control/runs"


def test_a_bad_site_id_is_refused_saying_what_is_allowed():
    with pytest.raises(BusConfigError, match=r"site id must match \[a-z0-9_-\]\+"):
        key("c1", "daemon", site="Plant A")


def test_the_daemon_config_takes_an_optional_site_and_robot_serial():
    assert DaemonConfig(cell="c1", fake=True).site is None
    cfg = DaemonConfig(cell="c1", fake=True, site="plant-a", robot_serial="KR6-0815")
    assert (cfg.site, cfg.robot_serial) == ("plant-a", "KR6-0815")
    with pytest.raises(ValueError):
        DaemonConfig(cell="c1", fake=True, auth={"anonymous": ["observe", "archive"]})


@pytest.mark.slow  # ~11 s: a daemon, three CLI processes and 6 s of watching
@pytest.mark.timeout(240)
def test_status_and_watch_find_a_cell_under_its_site(tmp_path):
    """A daemon with ``site: plant-a``: ``acquire status --site`` reaches it and ``acquire watch
    --site`` finds its cell; without the site nothing answers at ``remaster/<cell>/…``."""
    import os
    import subprocess

    from tests.acquire.daemon_harness import CELL, DaemonProcess, NotifySocket, free_port, write_config
    from tests.acquire.run_helpers import ROOT, acquire_cmd

    notify = NotifySocket()
    port = free_port()
    daemon = DaemonProcess(write_config(tmp_path, port, site="plant-a"), notify, watchdog_usec=1_000_000)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    endpoint = f"tcp/127.0.0.1:{port}"

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(acquire_cmd(*args), cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=90, stdin=subprocess.DEVNULL)

    try:
        daemon.wait_ready(90)
        sited = cli("status", "--site", "plant-a", "--cell", CELL, "--connect", endpoint, "--json")
        unsited = cli("status", "--cell", CELL, "--connect", endpoint, "--timeout", "2")
        bad = cli("status", "--site", "Plant A", "--cell", CELL, "--connect", endpoint)
        watched = cli("watch", "--site", "plant-a", "--connect", endpoint, "--duration", "6")
    finally:
        daemon.kill()
        notify.close()
    assert sited.returncode == 0, sited.stderr
    assert json.loads(sited.stdout)["cell"] == CELL
    assert unsited.returncode == 4 and "no reply" in unsited.stderr and "give --site" in unsited.stderr
    assert bad.returncode == 2 and "site id must match" in bad.stderr
    assert watched.returncode == 0, watched.stderr
    assert f"found cell {CELL} via {endpoint}" in watched.stderr
    assert f"daemon of cell {CELL}: alive" in watched.stdout


def test_watch_reads_a_sited_cells_keys_as_its_own_and_ignores_other_sites():
    from acquire.commands.watch import _Session
    from acquire.live.status import CellView

    s = _Session(None, None, site="plant-a", raw=False, until_done=False, count=0, duration=0, connect=[],
                 explicit_expr=False)
    assert s._local("remaster/plant-a/c7/run/r1/status") == "remaster/c7/run/r1/status"
    assert s._local("remaster/plant-b/c7/daemon") is None
    view = CellView("c7")
    assert view.alive(s._local("remaster/plant-a/c7/daemon"), True) == ["daemon of cell c7: alive"]
    unsited = _Session(None, None, raw=False, until_done=False, count=0, duration=0, connect=[], explicit_expr=False)
    assert unsited._local("remaster/c7/daemon") == "remaster/c7/daemon"
