"""The Zenoh bus on loopback: keys, loopback-only configuration, pub/sub, queries, liveliness, watch."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from acquire.live.bus import (
    Bus,
    BusConfigError,
    BusError,
    BusQueryError,
    BusTimeoutError,
    build_config,
    control_key,
    is_loopback_endpoint,
    key,
    run_key,
)
from acquire.commands.watch import format_line

ROOT = Path(__file__).resolve().parents[2]
EPHEMERAL = {"listen": ["tcp/127.0.0.1:0"]}


@pytest.fixture()
def pair():
    """A serving bus on an ephemeral loopback port and a second bus connected to it."""
    server = Bus("cell1", config=EPHEMERAL)
    client = Bus("cell1", config={"listen": [], "connect": server.locators})
    yield server, client
    client.close()
    server.close()


class Inbox:
    def __init__(self, n: int):
        self.items: list[tuple[str, bytes]] = []
        self.n = n
        self.done = threading.Event()
        self._lock = threading.Lock()

    def __call__(self, k: str, payload: bytes) -> None:
        with self._lock:
            self.items.append((k, payload))
            if len(self.items) >= self.n:
                self.done.set()


def test_keys_follow_the_design_and_reject_bad_chunks():
    assert key("cell1", "robot", "joint_state") == "remaster/cell1/robot/joint_state"
    assert key("cell1", "tracker/point") == "remaster/cell1/tracker/point"
    assert run_key("cell1", "20261121-0930", "sample") == "remaster/cell1/run/20261121-0930/sample"
    assert control_key("cell1", "status") == "remaster/cell1/control/status"
    for bad_cell in ("Cell", "a/b", "", "c*"):
        with pytest.raises(BusConfigError, match=r"cell id must match \[a-z0-9_-\]\+"):
            key(bad_cell, "x")
    for bad_part in ("*", "a//b", "run/**", "", "a b", "/x"):
        with pytest.raises(BusConfigError, match="chunk"):
            key("cell1", bad_part)
    with pytest.raises(BusConfigError, match="'event' or 'sample'"):
        run_key("cell1", "r1", "samples")


@pytest.mark.parametrize(
    "endpoint, loopback",
    [
        ("tcp/127.0.0.1:7447", True),
        ("tcp/127.8.9.1:0", True),
        ("udp/[::1]:7447", True),
        ("tcp/localhost:7447", True),
        ("unixsock-stream//tmp/zenoh.sock", True),
        ("tcp/0.0.0.0:7447", False),
        ("tcp/192.168.1.10:7447", False),
        ("tcp/[::]:7447", False),
        ("tcp/127.0.0.1", False),
        ("serial//dev/ttyUSB0", False),
    ],
)
def test_loopback_endpoints_are_recognised(endpoint, loopback):
    assert is_loopback_endpoint(endpoint) is loopback


def test_loopback_only_bus_refuses_any_route_off_the_machine():
    with pytest.raises(BusConfigError, match=r"listen endpoint\(s\) \['tcp/0.0.0.0:7447'\] are not loopback"):
        build_config({"listen": ["tcp/0.0.0.0:7447"]}, True)
    with pytest.raises(BusConfigError, match=r"connect endpoint\(s\) \['tcp/10.0.0.2:7447'\] are not loopback"):
        build_config({"listen": [], "connect": ["tcp/10.0.0.2:7447"]}, True)
    with pytest.raises(BusConfigError, match="'scouting/multicast/enabled' is refused"):
        build_config({"zenoh": {"scouting/multicast/enabled": True}}, True)
    with pytest.raises(BusConfigError, match=r"unknown bus config key\(s\) \['listne'\]"):
        build_config({"listne": []}, True)
    with pytest.raises(BusConfigError, match="mode must be one of"):
        build_config({"mode": "server"}, True)
    cfg, listen, defaulted = build_config(None, True)
    assert listen == ["tcp/127.0.0.1:7447"] and defaulted
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("scouting/gossip/enabled")) is False
    assert json.loads(cfg.get_json("connect/endpoints")) == []
    # a remote-facing daemon opts out explicitly (config only; nothing is opened here)
    cfg, listen, _ = build_config({"listen": ["tcp/0.0.0.0:7447"]}, False)
    assert listen == ["tcp/0.0.0.0:7447"]


def test_a_second_default_bus_falls_back_to_a_free_loopback_port():
    with Bus("cell1") as first, Bus("cell1") as second:
        locs = first.locators + second.locators
        assert len(set(locs)) == 2 and all(is_loopback_endpoint(loc) for loc in locs)


def test_an_explicit_endpoint_in_use_is_an_error():
    with Bus("cell1", config=EPHEMERAL) as first:
        taken = first.locators[0]
        with pytest.raises(BusError, match="cannot open the Zenoh session"):
            Bus("cell1", config={"listen": [taken]})


def test_json_and_bytes_payloads_cross_between_two_sessions(pair):
    server, client = pair
    inbox = Inbox(2)
    client.subscribe("remaster/cell1/run/*/event", inbox)
    pub = server.publisher(run_key("cell1", "r1", "event"))
    assert pub.wait_matched(5.0)
    pub.put({"kind": "moved", "q_deg": np.array([1.5, float("nan")]), "n": np.int64(3)})
    pub.put(b"\x00\x01raw")
    assert inbox.done.wait(5.0)
    (k1, p1), (k2, p2) = inbox.items
    assert k1 == k2 == "remaster/cell1/run/r1/event"
    assert json.loads(p1) == {"kind": "moved", "q_deg": [1.5, None], "n": 3}
    assert p2 == b"\x00\x01raw"


def test_blocking_publisher_delivers_a_burst_in_order_without_loss(pair):
    server, client = pair
    n = 2000
    inbox = Inbox(n)
    client.subscribe("remaster/cell1/mocap/markers", inbox)
    k = key("cell1", "mocap", "markers")
    pub = server.publisher(k, reliable=True)
    assert pub.wait_matched(5.0)
    for i in range(n):
        server.publish(k, {"i": i, "xyz_mm": [i * 0.1, 0.0, 0.0]})
    assert inbox.done.wait(20.0), f"received {len(inbox.items)} of {n}"
    assert [json.loads(p)["i"] for _, p in inbox.items] == list(range(n))


def test_queries_carry_params_payload_and_attachment_and_errors_come_back(pair):
    server, client = pair
    seen = []

    def handler(k, params, payload, attachment):
        seen.append((k, params, payload, attachment))
        if params.get("fail"):
            raise PermissionError("start refused for this client")
        return {"state": "idle", "echo": json.loads(payload) if payload else None}

    server.queryable(control_key("cell1", "status"), handler)
    assert client.wait_queryable(control_key("cell1", "status"), 5.0)
    assert not client.wait_queryable(control_key("cell1", "pause"), 0.05)
    reply = client.query(control_key("cell1", "status"), {"plan": "p.yaml"}, timeout=5.0, params={"verbose": "1"}, attachment=b"token")
    assert reply == {"state": "idle", "echo": {"plan": "p.yaml"}}
    assert seen[0] == ("remaster/cell1/control/status", {"verbose": "1"}, b'{"plan":"p.yaml"}', b"token")
    with pytest.raises(BusQueryError, match="PermissionError: start refused for this client") as err:
        client.query(control_key("cell1", "status"), params={"fail": "1"}, timeout=5.0)
    assert err.value.error == "PermissionError"
    with pytest.raises(BusTimeoutError, match="no reply to query 'remaster/cell1/control/pause'"):
        client.query(control_key("cell1", "pause"), timeout=0.5)
    with pytest.raises(BusConfigError, match="timeout must be > 0"):
        client.query(control_key("cell1", "status"), timeout=0)


def test_a_stuck_queryable_times_out(pair):
    server, client = pair
    release = threading.Event()
    server.queryable(control_key("cell1", "slow"), lambda *a: (release.wait(5.0), {"late": True})[1])
    assert client.wait_queryable(control_key("cell1", "slow"), 5.0)
    try:
        with pytest.raises(BusTimeoutError, match="did not answer within 0.3 s"):
            client.query(control_key("cell1", "slow"), timeout=0.3)
    finally:
        release.set()


def test_liveliness_tokens_appear_and_vanish(pair):
    server, client = pair
    changes: list[tuple[str, bool]] = []
    appeared, gone = threading.Event(), threading.Event()

    def on_change(k, alive):
        changes.append((k, alive))
        (appeared if alive else gone).set()

    client.watch_liveliness("remaster/cell1/**", on_change)
    token = server.liveliness_token(key("cell1", "tracker", "alive"))
    # A liveliness query answers at once with what the client knows; wait until the token has
    # reached it (the watcher says so), then ask.
    assert appeared.wait(10.0), "the token never reached the other session"
    assert client.alive("remaster/cell1/**", timeout=2.0) == ["remaster/cell1/tracker/alive"]
    token.undeclare()
    assert gone.wait(5.0)
    assert changes == [("remaster/cell1/tracker/alive", True), ("remaster/cell1/tracker/alive", False)]
    assert client.alive("remaster/cell1/**", timeout=0.5) == []


def test_closed_bus_refuses_use_and_close_is_idempotent():
    bus = Bus("cell1", config=EPHEMERAL)
    bus.subscribe("remaster/cell1/**", lambda k, p: None)
    bus.queryable(control_key("cell1", "status"), lambda *a: {})
    bus.close()
    bus.close()
    assert bus.closed
    with pytest.raises(BusError, match="closed"):
        bus.publish(key("cell1", "x"), {"a": 1})
    with pytest.raises(BusError, match="closed"):
        bus.session


def test_bad_keys_and_payloads_are_refused(pair):
    server, _ = pair
    with pytest.raises(BusConfigError, match="concrete"):
        server.publisher("remaster/cell1/*/markers")
    with pytest.raises(BusConfigError, match="invalid key expression"):
        server.subscribe("remaster//x", lambda k, p: None)
    with pytest.raises(ValueError, match="dict .*or bytes"):
        server.publish(key("cell1", "x"), [1, 2, 3])
    with pytest.raises(ValueError, match="not JSON serialisable"):
        server.publish(key("cell1", "x"), {"s": {1, 2}})


# The watch command alone (not the whole CLI, whose other commands import the fitter).
WATCH = (
    "import logging, sys, typer\n"
    "from acquire.commands.watch import register\n"
    "logging.basicConfig(level=logging.INFO)\n"
    "app = typer.Typer()\n"
    "register(app)\n"
    "app(sys.argv[1:])\n"
)


def test_another_process_watches_a_run_live():
    with Bus("cell1", config=EPHEMERAL) as server:
        endpoint = server.locators[0]
        proc = subprocess.Popen(
            [sys.executable, "-c", WATCH, "--raw", "--cell", "cell1", "--connect", endpoint, "--count", "3",
             "--duration", "30"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
        )
        try:
            events = server.publisher(run_key("cell1", "r7", "event"))
            samples = server.publisher(run_key("cell1", "r7", "sample"))
            matched = events.wait_matched(20.0) and samples.wait_matched(5.0)
            if matched:
                events.put({"kind": "moved", "config_id": "p01-b0"})
                samples.put({"config_id": "p01-b0", "q_measured_deg": [1.0, 2.0]})
                events.put({"kind": "settled", "config_id": "p01-b0"})
                out, err = proc.communicate(timeout=30)
        finally:
            if proc.returncode is None:
                proc.kill()
                out, err = proc.communicate()
    assert matched, f"the watcher never subscribed: {err}"
    assert proc.returncode == 0, err
    lines = out.splitlines()
    assert lines == [
        'remaster/cell1/run/r7/event {"kind":"moved","config_id":"p01-b0"}',
        'remaster/cell1/run/r7/sample {"config_id":"p01-b0","q_measured_deg":[1.0,2.0]}',
        'remaster/cell1/run/r7/event {"kind":"settled","config_id":"p01-b0"}',
    ]
    assert f"watching remaster/cell1/** via {endpoint}" in err


def test_watch_rejects_bad_input_before_connecting():
    proc = subprocess.run([sys.executable, "-c", WATCH, "--cell", "Bad Cell", "--duration", "1"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "cell id must match" in proc.stderr
    proc = subprocess.run([sys.executable, "-c", WATCH, "--connect", "tcp/10.1.2.3:7447", "--duration", "1"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "not loopback" in proc.stderr


def test_watch_formats_json_and_binary_payloads():
    assert format_line("remaster/c/x", b'{"a": [1, 2]}') == 'remaster/c/x {"a":[1,2]}'
    assert format_line("remaster/c/x", b"\x00\xff") == "remaster/c/x 2 bytes: 00ff"


def test_release_drops_the_cached_publishers_of_a_prefix(pair):
    server, _ = pair
    for run in ("r1", "r2"):
        server.publish(key("cell1", "run", run, "event"), {"kind": "started"})
    assert server.release(key("cell1", "run", "r1")) == 1
    assert server.release(key("cell1", "run", "r1")) == 0
    assert set(server._publishers) == {key("cell1", "run", "r2", "event")}
    # Publishing on a released key declares afresh.
    server.publish(key("cell1", "run", "r1", "event"), {"kind": "again"})
    assert key("cell1", "run", "r1", "event") in server._publishers


def test_closing_a_bus_whose_token_was_undeclared_logs_cleanly_at_debug():
    """A daemon undeclares its liveliness token before it closes the bus: the close used to log
    the token with ``%r``, which raises for an undeclared zenoh entity — at DEBUG every clean
    stop wrote ``--- Logging error ---`` blocks."""
    records: list[str] = []

    class Formatting(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(self.format(record))  # raises as a real handler's formatting would

        def handleError(self, record: logging.LogRecord) -> None:
            raise AssertionError(f"logging error for {record.msg!r}")

    handler = Formatting(logging.DEBUG)
    bus_log = logging.getLogger("acquire.live.bus")
    old = bus_log.level
    bus_log.addHandler(handler)
    bus_log.setLevel(logging.DEBUG)
    try:
        bus = Bus("cell1", config=EPHEMERAL)
        bus.liveliness_token("remaster/cell1/daemon/alive").undeclare()
        bus.close()
    finally:
        bus_log.removeHandler(handler)
        bus_log.setLevel(old)
    assert any("undeclaring a LivelinessToken" in r for r in records), records
