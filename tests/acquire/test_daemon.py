"""``acquire daemon``: configuration, sd_notify, health, and the service end to end.

The end-to-end tests start the daemon as a subprocess with a fake notify socket (NOTIFY_SOCKET,
WATCHDOG_USEC), drive the example plan on the simulated cell through the control queries, and
check the log, the run's MCAP file and the notifications.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from acquire.commands.daemon import JournalFormatter
from acquire.daemon.control import BadRequest, Conflict
from acquire.daemon.service import Daemon
from acquire.daemon.config import ConfigError, DaemonConfig, endpoint_is_loopback, load_daemon_config
from acquire.daemon.sdnotify import SdNotifier, socket_address, watchdog_interval_s

from daemon_harness import (  # noqa: E402 - tests/acquire is on sys.path under pytest
    CELL,
    OPERATOR_TOKEN,
    NotifySocket,
    control,
    free_port,
    open_client,
    wait_until,
    write_config,
)


# ----------------------------------------------------------------------------- configuration
def test_config_refuses_remote_listener_without_authentication(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(
        "cell: lab1\nfake: true\nzenoh:\n  listen:\n    - tcp/127.0.0.1:7447\n    - tcp/0.0.0.0:7447\n"
    )
    with pytest.raises(ConfigError) as exc:
        load_daemon_config(path)
    msg = str(exc.value)
    assert f"{path}:6:7: zenoh.listen.1:" in msg
    assert "'tcp/0.0.0.0:7447' is reachable from other hosts without authentication" in msg
    assert "enable_mtls" in msg and "access_control" in msg


def test_config_accepts_remote_tls_with_mtls_and_resolves_paths(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(
        "cell: lab1\nfake: true\nstate_dir: state\nzenoh:\n  listen: [tls/0.0.0.0:7447]\n  tls:\n"
        "    root_ca_certificate: pki/ca.pem\n    listen_certificate: pki/srv.pem\n"
        "    listen_private_key: pki/srv.key\n"
    )
    cfg = load_daemon_config(path)
    assert cfg.state_dir == tmp_path / "state"
    tls = cfg.zenoh.zenoh_config()["transport"]["link"]["tls"]
    assert tls == {"root_ca_certificate": str(tmp_path / "pki/ca.pem"), "listen_certificate": str(tmp_path / "pki/srv.pem"),
                   "listen_private_key": str(tmp_path / "pki/srv.key"), "enable_mtls": True}
    # …but the same endpoint over plain TCP is refused even with TLS files configured.
    path.write_text(path.read_text().replace("tls/0.0.0.0", "tcp/0.0.0.0"))
    with pytest.raises(ConfigError, match="reachable from other hosts"):
        load_daemon_config(path)


def test_config_anonymous_may_not_move_and_names_the_line(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text("cell: lab1\nfake: true\nauth:\n  anonymous: [observe, motion]\n")
    with pytest.raises(ConfigError) as exc:
        load_daemon_config(path)
    assert f"{path}:4:14: auth.anonymous:" in str(exc.value)
    assert "given ['observe', 'motion']" in str(exc.value)


def test_config_needs_devices_or_fake(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text("cell: lab1\n")
    with pytest.raises(ConfigError, match="no devices"):
        load_daemon_config(path)
    path.write_text("cell: lab1\ncommander: {name: robot, driver: rsi, url: 'rsi://0.0.0.0:49152'}\n")
    with pytest.raises(ConfigError, match="needs 'robot'"):
        load_daemon_config(path)


def test_shipped_example_configuration_is_valid_and_loopback_only(tmp_path):
    shipped = Path(__file__).parents[2] / "systemd" / "daemon.yaml.example"
    installed = tmp_path / "daemon.yaml"
    installed.write_text(shipped.read_text())
    installed.chmod(0o644)  # as a plain copy would leave it: it holds client keys, so refused
    with pytest.raises(ConfigError, match="UNPROTECTED CONFIGURATION: mode 0644.*chmod 0640"):
        load_daemon_config(installed)
    installed.chmod(0o640)  # as systemd/README.md installs it
    cfg = load_daemon_config(installed)
    assert cfg.zenoh.mode == "router" and cfg.zenoh.remote_endpoints == []
    # On the cell PC: the Unix socket a client sends credentials to, given to the operators only.
    assert cfg.zenoh.socket_paths == [Path("/run/remaster/zenoh.sock")]
    assert cfg.zenoh.socket_group == cfg.control_socket.group == "remaster-operators"
    assert not any(ep.startswith("tcp/") for ep in cfg.zenoh.listen)
    assert cfg.auth.anonymous == ["observe"] and cfg.fake_cell is None and cfg.commander.driver == "fri"


def test_cli_daemon_bad_config_exits_2_naming_the_line(tmp_path):
    bad = tmp_path / "d.yaml"
    bad.write_text("cell: Lab 1\nfake: true\n")
    out = subprocess.run([sys.executable, "-m", "acquire", "daemon", "--config", str(bad)],
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert out.returncode == 2
    assert f"{bad}:1:7: cell: String should match pattern" in out.stderr and "given: 'Lab 1'" in out.stderr
    # Under systemd (JOURNAL_STREAM set) every line carries its syslog priority for journald.
    env = dict(os.environ, JOURNAL_STREAM="8:12345")
    out = subprocess.run([sys.executable, "-m", "acquire", "daemon", "--config", str(bad)], env=env,
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    lines = out.stderr.splitlines()
    assert lines[0].startswith("<3>ERROR acquire.commands.daemon: configuration not valid:")
    assert all(line.startswith("<3>") for line in lines), lines


def test_cli_client_without_daemon_reports_no_reply(tmp_path):
    out = subprocess.run([sys.executable, "-m", "acquire", "status", "--cell", CELL, "--connect",
                          f"tcp/127.0.0.1:{free_port()}", "--timeout", "1"],
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert out.returncode == 1 and "cannot open the Zenoh session" in out.stderr


@pytest.mark.parametrize("endpoint, loopback", [
    ("tcp/127.0.0.1:7447", True), ("tcp/[::1]:7447", True), ("tls/localhost:7447", True),
    ("unixsock-stream//run/remaster.sock", True), ("tcp/0.0.0.0:7447", False), ("tcp/[::]:7447", False),
    ("tls/192.168.10.2:7447#iface=eth0", False), ("tcp/cellpc.lan:7447", False),
])
def test_endpoint_loopback_classification(endpoint, loopback):
    assert endpoint_is_loopback(endpoint) is loopback


# ----------------------------------------------------------------------------- sd_notify client
def test_sdnotify_sends_datagrams_to_abstract_and_path_sockets(tmp_path):
    abstract = NotifySocket()
    path_sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path_sock.bind(str(tmp_path / "notify"))
    try:
        n = SdNotifier(env={"NOTIFY_SOCKET": abstract.name})
        assert n.ready("up") and n.watchdog() and n.status("busy") and n.stopping()
        abstract.wait_for(lambda f: f.get("STOPPING") == "1", 2)
        assert abstract.all_fields() == [{"READY": "1", "STATUS": "up"}, {"WATCHDOG": "1"}, {"STATUS": "busy"},
                                         {"STOPPING": "1"}]
        p = SdNotifier(env={"NOTIFY_SOCKET": str(tmp_path / "notify")})
        assert p.notify(STATUS="x", EXTEND_TIMEOUT_USEC=5)
        assert path_sock.recv(100) == b"STATUS=x\nEXTEND_TIMEOUT_USEC=5"
        with pytest.raises(ValueError, match="one line"):
            n.status("two\nlines")
        n.close()
        p.close()
    finally:
        abstract.close()
        path_sock.close()


def test_sdnotify_disabled_and_failures_do_not_raise(tmp_path, caplog):
    assert SdNotifier(env={}).ready() is False
    gone = SdNotifier(env={"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    with caplog.at_level(logging.WARNING):
        assert gone.watchdog() is False
        assert gone.watchdog() is False
    gone.close()
    assert len([r for r in caplog.records if "sd_notify" in r.getMessage()]) == 1  # logged once
    with pytest.raises(ValueError, match="not supported"):
        socket_address("vsock:2:1234")


def test_watchdog_interval_from_environment():
    assert watchdog_interval_s({"WATCHDOG_USEC": "2500000"}) == 2.5
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}, pid=2) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "2"}, pid=2) == 0.001
    with pytest.raises(ValueError, match="given 'ten'"):
        watchdog_interval_s({"WATCHDOG_USEC": "ten"})


def test_journal_formatter_prefixes_every_line_with_its_priority():
    fmt = JournalFormatter("%(levelname)s %(name)s: %(message)s")
    rec = logging.LogRecord("acquire.daemon.service", logging.WARNING, __file__, 1, "late\nanswers", None, None)
    assert fmt.format(rec) == "<4>WARNING acquire.daemon.service: late\n<4>answers"
    rec = logging.LogRecord("x", logging.INFO, __file__, 1, "ok", None, None)
    assert fmt.format(rec) == "<6>INFO x: ok"


# ----------------------------------------------------------------------------- health (in-process)
def test_watchdog_pings_stop_when_the_controller_stops_sending(tmp_path):
    """In-process daemon on the simulated cell: pings while the FRI exchange streams, none once
    the fake controller falls silent, and STATUS says why."""
    notify = NotifySocket()
    port = free_port()
    cfg = load_daemon_config(write_config(tmp_path, port))
    from acquire.commands.fake import daemon_cell

    sim = daemon_cell(cfg.fake_cell).start()  # as `acquire daemon` starts it for `fake`
    d = Daemon(cfg, notifier=SdNotifier(env={"NOTIFY_SOCKET": notify.name, "WATCHDOG_USEC": "400000"}), cell=sim)
    t = threading.Thread(target=d.run, name="daemon-under-test")
    t.start()
    try:
        notify.wait_for(lambda f: f.get("READY") == "1", 30)
        wait_until(lambda: notify.count("WATCHDOG", "1") >= 3, 10, "three watchdog pings")
        sim.launch.inject("packet_loss", "controller", 60.0, 1.0)  # the controller falls silent
        # (a loaded machine may add a late-answer complaint first; the silence must follow)
        unhealthy = notify.wait_for(lambda f: "UNHEALTHY" in f.get("STATUS", "") and (
            "old" in f["STATUS"] or "no monitoring" in f["STATUS"]), 10)
        assert "UNHEALTHY" in unhealthy.fields["STATUS"]
        pings = notify.count("WATCHDOG", "1")
        time.sleep(4 * d.tick_s)  # four health checks, no pings
        assert notify.count("WATCHDOG", "1") == pings
        assert d.status(include_plan=False)["healthy"] is False
    finally:
        d.request_stop()
        t.join(30)
        notify.close()
        sim.close()
    assert not t.is_alive()
    assert notify.all_fields()[-2].get("STOPPING") == "1"


def test_device_host_brings_up_configured_real_drivers_against_the_fakes(tmp_path):
    """The non-fake path: the configured FRI commander and NatNet sensor, connected over
    loopback to the simulated cell's fake Sunrise and fake Motive, as to real devices."""
    from acquire.daemon.service import DeviceHost
    from drivers.sim.cell import SimCell
    from drivers.sim.clock import SimClock
    from drivers.sim.config import DEFAULT_CONFIG_PATH
    from drivers.sim.launch import SimLaunch

    fri_port = free_port()
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=0, clock=SimClock(1.0))
    repo = Path(__file__).parents[2]
    with SimLaunch(cell, fri_port=fri_port, max_runtime_s=60) as launch:
        cfg = DaemonConfig(
            cell=CELL, state_dir=tmp_path, robot=repo / "fixtures/robots/kuka_iiwa14_r820.yaml",
            commander={"name": "robot", "driver": "fri", "url": f"fri://127.0.0.1:{fri_port}?rt_priority=0"},
            sensors=[{"name": "bar", "driver": "natnet", "url": launch.addresses["mocap"].url,
                      "markers": {"sir": "ms:tool:sir"}}],
        )
        host = DeviceHost(cfg)
        try:
            assert host.open() == ["robot", "bar"]
            assert host.expect_stream is False  # a real controller streams only while its program runs
            state = wait_until(lambda: _fresh_state(host.commander), 10, "FRI monitoring state")
            assert state.position_rad.shape == (7,)
            assert [s.name for s in host.sensors] == ["bar"]
        finally:
            host.close()
        assert host.commander is None and host.sensors == []
        # the port is free again for a run to bind
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", fri_port))


def _fresh_state(cmd):
    from drivers.errors import DeviceTimeoutError

    try:
        return cmd.joint_state()
    except DeviceTimeoutError:
        return None


def test_health_monitor_flags_new_late_real_time_answers_and_a_silent_recorder(tmp_path):
    """A real RSI commander answering a fake KR C4 on loopback: healthy while it answers in
    time; unhealthy in the check after it answered late; healthy again once it keeps up."""
    from acquire.daemon.service import HealthMonitor
    from acquire.daemon.config import HealthSection
    from calib.robot.model import load_robot_model
    from drivers.kuka_rsi.commander import RsiCommander
    from drivers.kuka_rsi.fake import FakeKrc4
    from drivers.protocols import JointLimits

    model = load_robot_model(Path(__file__).parents[2] / "fixtures/robots/kuka_kr6_r900_2.yaml")
    cmd = RsiCommander(JointLimits.from_model(model), host="127.0.0.1", port=0, rt_priority=0, connect_timeout=30.0)
    fake = FakeKrc4(cmd.bind(), initial_deg=[0, -90, 90, 0, 45, 0], late_limit=100000, max_runtime_s=30)
    mon = HealthMonitor(HealthSection(max_late_answers_per_check=0, max_state_age_s=0.5))
    try:
        fake.start()
        cmd.connect()
        wait_until(lambda: _fresh_state(cmd), 30, "RSI state")
        assert mon.check(cmd, expect_stream=True, run_status=None).ok  # baseline
        # the exchange process is not scheduled for ~8 cycles (SIGSTOP): its answers come late
        os.kill(cmd.exchange_pid, signal.SIGSTOP)
        try:
            time.sleep(0.03)
        finally:
            os.kill(cmd.exchange_pid, signal.SIGCONT)
        wait_until(lambda: cmd.link_stats().late_answers >= 3, 30, "late answers")
        bad = mon.check(cmd, expect_stream=True, run_status=None)
        assert not bad.ok and "late real-time answers since the last check" in bad.reason
        # healthy again at the first check with no new late answer since the one before
        wait_until(lambda: mon.check(cmd, expect_stream=True, run_status=None).ok, 30, "healthy again", poll=0.1)
    finally:
        cmd.close()
        fake.close()
    # Without a stream, a commander whose controller is silent is stale.
    stale = mon.check(cmd, expect_stream=True, run_status=None)
    assert not stale.ok and "rsi" in stale.reason

    log_file = tmp_path / "run.mcap"
    log_file.write_bytes(b"\x89MCAP0\r\n")
    running = {"state": "running", "log": str(log_file)}
    assert mon.check(None, expect_stream=False, run_status=running).ok
    old = time.time() - 600
    os.utime(log_file, (old, old))
    silent = mon.check(None, expect_stream=False, run_status=running)
    assert not silent.ok and "not written for 6" in silent.reason
    assert mon.check(None, expect_stream=False, run_status=dict(running, state="paused")).ok  # paused: no writes due
    log_file.unlink()
    assert "No such file" in mon.check(None, expect_stream=False, run_status=running).reason


def test_start_refuses_plans_outside_plan_dirs_and_second_runs(tmp_path):
    """The control backend's own checks, without Zenoh in between."""
    from acquire.daemon.control import Identity

    cfg = DaemonConfig(cell=CELL, fake=True, state_dir=tmp_path / "state", plan_dirs=[tmp_path / "plans"])
    d = Daemon(cfg, notifier=SdNotifier(env={}))
    d._state = "ready"
    who = Identity("operator", "operator", None, frozenset({"motion"}))
    (tmp_path / "plans").mkdir()
    (tmp_path / "elsewhere.yaml").write_text("cell: example\n")
    with pytest.raises(BadRequest, match="not inside the allowed plan folders"):
        d.start({"plan": str(tmp_path / "elsewhere.yaml")}, who)
    with pytest.raises(BadRequest, match="not inside"):
        d.start({"plan": "../elsewhere.yaml"}, who)
    with pytest.raises(BadRequest, match="exactly one of"):
        d.start({}, who)
    with pytest.raises(Conflict, match="no active run"):
        d.pause()


# ----------------------------------------------------------------------------- end to end
# (the `daemon` fixture: daemon_harness.py, offered by conftest.py)
def _run_state(ctl) -> dict:
    return ctl.call("status")["run"] or {}


def test_daemon_runs_pauses_resumes_aborts_a_fake_plan_and_stops_on_sigterm(daemon):
    proc, port, tmp_path = daemon
    ready = proc.wait_ready()
    notify = proc.notify
    # READY only after the devices were up, and they are announced on the bus.
    assert "devices up: controller, mocap, tracker" in proc.log()
    with open_client(port) as bus:
        alive = bus.alive(f"remaster/{CELL}/**")
        assert alive == sorted(f"remaster/{CELL}/{k}" for k in
                               ("daemon", "device/controller", "device/mocap", "device/tracker"))
        op = control(bus, "operator", OPERATOR_TOKEN)
        st = op.call("status")
        assert st["daemon"] == "ready" and st["healthy"] and st["run"] is None
        assert st["memory"]["rss_kb"] > 10_000 and st["memory"]["python_heap_kb"] is None  # no tracemalloc
        # Over plain TCP the CLI sends no credentials (test_control_local.py): an anonymous status.
        cli = subprocess.run([sys.executable, "-m", "acquire", "status", "--cell", CELL, "--connect",
                              f"tcp/127.0.0.1:{port}"],
                             capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
        assert cli.returncode == 0 and "reply not authenticated" in cli.stderr, cli.stderr
        lines = cli.stdout.splitlines()
        assert lines[0] == f"cell {CELL}: daemon ready, healthy, devices controller, mocap, tracker (fake)", lines
        assert lines[1].startswith("up ") and "resident memory" in lines[1] and lines[2] == "no run", lines
        wait_until(lambda: notify.count("WATCHDOG", "1") >= 2, 5, "watchdog pings after READY")
        assert all(m.t >= ready.t for m in notify.messages if m.fields.get("WATCHDOG"))

        started = op.call("start", {"plan": "example.yaml"}, timeout=60)
        run_id = started["run_id"]
        assert run_id.startswith(f"{CELL}-")
        wait_until(lambda: _run_state(op).get("done", 0) >= 2, 60, "two configurations measured")

        op.call("pause")
        paused = wait_until(lambda: (s := _run_state(op)).get("state") == "paused" and s, 30, "paused")
        done_at_pause = paused["done"]
        time.sleep(1.0)  # paused: nothing more is measured
        assert _run_state(op)["done"] == done_at_pause
        notify.wait_for(lambda f: f"run {run_id} paused" in f.get("STATUS", ""), 5)

        op.call("resume")
        pings_at_resume = notify.count("WATCHDOG", "1")
        wait_until(lambda: _run_state(op).get("done", 0) > done_at_pause, 30, "progress after resume")
        # The watchdog is fed during the run (the run's own commander and log are watched).
        pings_before_abort = notify.count("WATCHDOG", "1")
        assert pings_before_abort > pings_at_resume

        op.call("abort", {"reason": "test abort"})
        wait_until(lambda: op.call("status")["run"] is None, 30, "run ended and devices taken back")
        st = op.call("status")
        assert st["healthy"] and st["devices"] == ["controller", "mocap", "tracker"]
        runs = op.call("runs")["runs"]
        assert [r["run_id"] for r in runs] == [run_id] and runs[0]["bytes"] > 0
        plan = op.call("plan", {"run_id": run_id})
        assert plan["plan_text"] == (tmp_path / "plans" / "example.yaml").read_text()
        # The watchdog is fed again once the devices are back.
        wait_until(lambda: notify.count("WATCHDOG", "1") > pings_before_abort, 5, "pings after the run")

    from acquire.record.recorder import read_run

    contents = read_run(tmp_path / "state" / "runs" / run_id / f"{run_id}.mcap")
    assert contents.complete and contents.run_id == run_id
    assert len(contents.samples) >= done_at_pause + 1
    kinds = [e.get("kind") for e in contents.events]
    states = [e.get("state") for e in contents.events if e.get("kind") == "state"]
    assert states[:3] == ["running", "paused", "running"], states
    aborted = [e for e in contents.events if e.get("kind") == "aborted"]
    assert [e["reason"] for e in aborted] == ["test abort"], kinds

    assert proc.stop(signal.SIGTERM) == 0
    fields = notify.all_fields()
    stopping = [i for i, f in enumerate(fields) if f.get("STOPPING") == "1"]
    assert stopping and stopping[0] > [i for i, f in enumerate(fields) if f.get("READY") == "1"][0]
    log = proc.log()
    for line in (f"control/start from operator", f"run {run_id} started by operator", "run {} ended: aborted",
                 "stopping", "stopped"):
        assert line.replace("{}", run_id) in log, line
    assert "\x1b[" not in log  # no colour when not on a terminal
    assert all(line.split(" ", 1)[0] in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL") or line.startswith(("  ", "Traceback"))
               for line in log.splitlines() if line), log


def test_sigterm_during_a_run_finishes_the_configuration_and_closes_the_log(daemon):
    proc, port, tmp_path = daemon
    proc.wait_ready()
    with open_client(port) as bus:
        op = control(bus, "operator", OPERATOR_TOKEN)
        run_id = op.call("start", {"plan": "example.yaml"}, timeout=60)["run_id"]
        wait_until(lambda: _run_state(op).get("done", 0) >= 1, 60, "one configuration measured")
    assert proc.stop(signal.SIGTERM) == 0
    log = proc.log()
    assert f"stopping: pausing run {run_id} after its current configuration" in log
    assert f"run {run_id} aborted; log" in log
    proc.notify.wait_for(lambda f: f.get("STOPPING") == "1", 1)
    from acquire.record.recorder import read_run

    contents = read_run(tmp_path / "state" / "runs" / run_id / f"{run_id}.mcap")
    assert contents.complete, "the run's log was not closed cleanly"
    states = [e.get("state") for e in contents.events if e.get("kind") == "state"]
    assert "paused" in states, states  # it finished the configuration it was at, then held
    assert [e["reason"] for e in contents.events if e.get("kind") == "aborted"] == ["daemon stopping (SIGTERM)"]
    # every configuration that was moved to was also measured: nothing left half-done
    moved = {e["config_id"] for e in contents.events if e.get("kind") == "moved"}
    assert moved and moved == {s["config_id"] for s in contents.samples}


def test_runs_lists_a_resumed_run_once_with_all_its_segments(tmp_path):
    cfg = DaemonConfig(cell=CELL, fake=True, state_dir=tmp_path / "state", plan_dirs=[tmp_path / "plans"])
    d = Daemon(cfg, notifier=SdNotifier(env={}))
    run = d.runs_dir / "example-1"
    run.mkdir(parents=True)
    for name, size in (("example-1.mcap", 100), ("example-1.resume1.mcap", 40), ("example-1.resume2.mcap", 10)):
        (run / name).write_bytes(b"x" * size)
    (d.runs_dir / "example-2").mkdir()
    (d.runs_dir / "example-2" / "example-2.mcap").write_bytes(b"y" * 7)
    runs = {r["run_id"]: r for r in d.runs()["runs"]}
    assert set(runs) == {"example-1", "example-2"}
    assert (runs["example-1"]["segments"], runs["example-1"]["bytes"]) == (3, 150)
    assert (runs["example-2"]["segments"], runs["example-2"]["bytes"]) == (1, 7)
