"""Keys of a cell on a plant's router carry its site; a cell without a site keeps its keys."""

import pytest

from acquire.bus import BusConfigError, control_key, key
from acquire.daemon_config import DaemonConfig


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
