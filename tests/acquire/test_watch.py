"""``acquire watch`` and the run's console: the cell view, discovery of a real run and of the
daemon on the bus, and what a run shows on a terminal (a pseudo-terminal, as an operator's).

The end-to-end tests start real processes (``acquire run --fake``, ``acquire daemon``) on free
loopback ports; nothing here measures time.
"""

from __future__ import annotations

import io
import json
import os
import pty
import re
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from acquire.live.status import CellView, cell_of, sample_text, warning_text

from daemon_harness import CELL, OPERATOR_TOKEN, DaemonProcess, NotifySocket, free_port, write_config  # noqa: E402
from run_helpers import ROOT, acquire_cmd, small_plan  # noqa: E402

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _j(obj: dict) -> bytes:
    return json.dumps(obj).encode()


STATUS = {"state": "running", "run_id": "r1", "done": 3, "total": 10, "measured": 2, "failed": 0, "skipped": 1,
          "eta_s": 125.0, "current": "p04-b1", "log": "/x/r1.mcap", "reason": ""}
SAMPLE = {"config_id": "p03-b0", "q_measured_deg": [10.0, -20.5, 0.0, 90.0, 0.0, 30.0, 0.0],
          "markers": [{"sensor": "mocap", "marker": "sir", "mean_mm": [100.0, 200.0, 300.0],
                       "std_mm": [0.01, 0.02, 0.015], "count": 5}]}


# ----------------------------------------------------------------------------- the view
def test_cell_view_keeps_progress_last_sample_joints_and_warnings_of_its_cell_only():
    t = [100.0]
    v = CellView("lab1", clock=lambda: t[0])
    assert v.feed("remaster/other/run/r9/status", _j(STATUS)) == []  # another cell: ignored
    lines = v.feed("remaster/lab1/run/r1/status", _j(STATUS))
    assert lines == ["run r1 of cell lab1", "run r1: 3/10  measured 2  skipped 1  failed 0  ETA 2m05s  at p04-b1"]
    assert v.feed("remaster/lab1/run/r1/status", _j(dict(STATUS, eta_s=120.0))) == []  # same progress: quiet
    assert v.feed("remaster/lab1/run/r1/sample", _j(SAMPLE)) == [
        "sample p03-b0  q [10.00 -20.50 0.00 90.00 0.00 30.00 0.00]°  mocap/sir [100.00 200.00 300.00] mm ± 0.020 (5)"]
    assert v.feed("remaster/lab1/run/r1/event", _j({"kind": "moved", "config_id": "p04-b1"})) == []
    assert v.feed("remaster/lab1/run/r1/event", _j({"kind": "skipped", "config_id": "p05-b0",
                                                   "reason": "marker not visible"})) == [
        "warning skipped p05-b0: marker not visible"]
    v.feed("remaster/lab1/fri/joint_state", _j({"name": ["A1"], "position_deg": [1.5, 2.5]}))
    assert v.joints == [1.5, 2.5] and v.messages == 6
    assert not v.run_done
    v.feed("remaster/lab1/run/r1/status", _j(dict(STATUS, state="finished", done=10, current=None)))
    assert v.run_done
    # a new run starts afresh
    assert v.feed("remaster/lab1/run/r2/event", _j({"kind": "run_started"}))[0] == "run r2 of cell lab1"
    assert v.run_id == "r2" and v.status == {} and not v.warnings and v.sample is None


def test_cell_view_tracks_the_daemon_and_its_devices_from_liveliness():
    v = CellView("lab1")
    assert v.source == "run"
    assert v.alive("remaster/lab1/daemon", True) == ["daemon of cell lab1: alive"]
    v.alive("remaster/lab1/device/fri", True)
    v.alive("remaster/lab1/device/mocap", True)
    v.alive("remaster/lab1/device/mocap", False)
    v.alive("remaster/lab2/device/x", True)
    assert v.source == "daemon" and v.devices == {"fri"}
    assert v.alive("remaster/lab1/daemon", False) == ["daemon of cell lab1: gone"]


def test_cell_view_renders_one_panel_with_everything_an_operator_looks_for():
    from rich.console import Console

    t = [50.0]
    v = CellView("lab1", clock=lambda: t[0])
    v.alive("remaster/lab1/daemon", True)
    v.alive("remaster/lab1/device/fri", True)
    v.feed("remaster/lab1/run/r1/status", _j(STATUS))
    v.feed("remaster/lab1/run/r1/sample", _j(SAMPLE))
    v.feed("remaster/lab1/run/r1/event", _j({"kind": "suspended", "config_id": "p04-b1", "sensor": "tracker",
                                            "marker": "smr", "reason": "beam lost"}))
    t[0] = 53.0
    out = io.StringIO()
    Console(file=out, width=160, color_system=None).print(v.renderable("Ctrl-C to quit"))
    text = out.getvalue()
    for expected in ("cell lab1 — daemon", "alive, devices fri", "r1", "running", "3/10", "ETA 2m05s", "p04-b1",
                     "p03-b0", "mocap/sir", "(3s ago)", "suspended p04-b1: tracker/smr beam lost", "Ctrl-C to quit"):
        assert expected in text, f"{expected!r} not in\n{text}"


def test_helpers_name_cells_samples_and_warnings():
    assert cell_of("remaster/c1/run/r/status") == "c1" and cell_of("other/c1/x") is None and cell_of("remaster") is None
    assert warning_text({"kind": "searched", "found": False, "sensor": "tracker", "radius_mm": 20}) == (
        "search: tracker did not find the target within 20 mm")
    assert warning_text({"kind": "searched", "found": True}) is None
    assert warning_text({"kind": "retry", "config_id": "c", "step": "move", "reason": "late"}) == "retry c (move): late"
    assert warning_text({"kind": "suspended", "config_id": "c", "cause": "device_fault", "device": "fri",
                         "reason": "move: fri: drives not ACTIVE", "allowance_s": 30.0}) == (
        "suspended c: move: fri: drives not ACTIVE (waiting up to 30.0 s for fri)")
    assert "mocap/sir" in sample_text(SAMPLE) and "± 0.020" in sample_text(SAMPLE)


# ----------------------------------------------------------------------------- end to end
class Pty:
    """A process whose stdout and stderr are a pseudo-terminal (as in an operator's terminal)."""

    def __init__(self, args: list[str], *, cwd: Path, columns: int = 160) -> None:
        master, slave = pty.openpty()
        env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS=str(columns), LINES="50", TERM="xterm-256color")
        self.proc = subprocess.Popen(args, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=slave, stderr=slave)
        os.close(slave)
        self._master = master
        self._chunks: list[bytes] = []
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while True:
            r, _, _ = select.select([self._master], [], [], 0.2)
            if r:
                try:
                    data = os.read(self._master, 65536)
                except OSError:  # EIO: the child closed the terminal
                    return
                if not data:
                    return
                self._chunks.append(data)
            elif self.proc.poll() is not None:
                return

    def wait(self, timeout: float) -> tuple[int, str]:
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            raise
        self._thread.join(10)
        os.close(self._master)
        return rc, ANSI.sub("", b"".join(self._chunks).decode("utf-8", "replace")).replace("\r", "\n")


def _watch(*args: str, cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen(acquire_cmd("watch", *args), cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_line(stream, pattern: str, timeout: float) -> list[str]:
    """Lines read from ``stream`` up to and including the first containing ``pattern``."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = stream.readline()
        if not line:
            break
        seen.append(line)
        if pattern in line:
            return seen
    raise AssertionError(f"{pattern!r} not seen in {seen}")


@pytest.mark.slow  # a whole fake run; following a run to its end is test_watch_against_the_daemon_… (default)
@pytest.mark.timeout(240)
def test_watch_finds_a_real_run_by_itself_and_follows_it_to_the_end(tmp_path):
    plan = small_plan(tmp_path, n=4)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    watcher = _watch("--connect", endpoint, "--until-done", "--duration", "200", cwd=tmp_path)
    run = None
    try:
        _wait_for_line(watcher.stderr, "watching remaster/**", 60)  # subscribed before the run starts
        run = Pty(acquire_cmd("run", str(plan), "--fake", "--no-fit", "--listen", endpoint), cwd=tmp_path)
        rc, console = run.wait(200)
        out, err = watcher.communicate(timeout=60)
    finally:
        if watcher.poll() is None:
            watcher.kill()
    assert rc == 0, console
    assert watcher.returncode == 0, err
    assert f"found cell example via {endpoint}" in err
    run_id = re.search(r"run (\S+): finished", console).group(1)
    lines = out.splitlines()
    assert lines[0] == f"run {run_id} of cell example"
    status = [ln for ln in lines if ln.startswith(f"run {run_id}: ")]
    assert status[-1].endswith("finished")
    done, total = re.search(r": (\d+)/(\d+)", status[-1]).groups()
    assert done == total and int(total) > 0
    measured = int(re.search(r"(\d+) measured", console).group(1))
    assert len([ln for ln in lines if ln.startswith("sample ")]) == measured > 0
    # the run's terminal: a bar with the configuration being measured, no INFO lines, clean paths
    assert "measured" in console and "ETA" in console and re.search(r"at p\d+-b\d+ +pose p\d+", console)
    assert "INFO" not in console, console
    assert "/../" not in console and "log: " in console
    text_log = next((tmp_path / "runs").rglob(f"{run_id}.log"))
    logged = text_log.read_text()
    assert "INFO remaster.device.fri" in logged and "INFO acquire.run" in logged
    assert f"text log: {text_log.relative_to(tmp_path)}" in console  # relative to the working folder


@pytest.mark.slow  # ~20 s: a whole fake run for what -v prints; watching a run stays in the default selection
@pytest.mark.timeout(200)
def test_run_with_v_shows_device_logs_on_the_terminal(tmp_path):
    plan = small_plan(tmp_path, n=4)
    run = Pty(acquire_cmd("run", str(plan), "--fake", "--no-fit", "--no-bus", "-v"), cwd=tmp_path)
    rc, console = run.wait(180)
    assert rc == 0, console
    assert "INFO remaster.device.fri" in console and "finished" in console


@pytest.mark.timeout(300)
def test_watch_against_the_daemon_finds_its_cell_follows_its_run_and_never_claims_to_be_disconnected(
        tmp_path, socket_dir):
    notify = NotifySocket()
    port = free_port()
    local = f"unixsock-stream/{socket_dir / 'zenoh.sock'}"  # the endpoint a client sends credentials to
    daemon = DaemonProcess(write_config(tmp_path, port, zenoh={"listen": [f"tcp/127.0.0.1:{port}", local]}),
                           notify, watchdog_usec=1_000_000)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    try:
        daemon.wait_ready(90)
        endpoint = f"tcp/127.0.0.1:{port}"
        watcher = _watch("--connect", endpoint, "--until-done", "--duration", "240", cwd=tmp_path)
        try:
            seen = _wait_for_line(watcher.stdout, f"daemon of cell {CELL}: alive", 60)
            # a key nothing publishes on: silence for longer than the "not connected" delay
            quiet = subprocess.run(acquire_cmd("watch", "--raw", f"remaster/{CELL}/nothing/here", "--connect",
                                               endpoint, "--duration", "4"),
                                   cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60,
                                   stdin=subprocess.DEVNULL)
            token = tmp_path / "token"
            token.write_text(OPERATOR_TOKEN)
            token.chmod(0o600)  # the CLI refuses a token file others may read
            plan = small_plan(tmp_path, n=4, name="small.yaml")
            started = subprocess.run(acquire_cmd("start", "--inline", str(plan), "--cell", CELL, "--connect", local,
                                                 "--client", "operator", "--token-file", str(token)),
                                     cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60,
                                     stdin=subprocess.DEVNULL)
            assert started.returncode == 0, started.stderr
            out, err = watcher.communicate(timeout=200)  # --until-done: exits when the daemon's run ends
        finally:
            if watcher.poll() is None:
                watcher.kill()
    finally:
        daemon.kill()
        notify.close()
    assert seen[-1].strip() == f"daemon of cell {CELL}: alive"
    assert watcher.returncode == 0, err
    assert f"found cell {CELL} via {endpoint}" in err
    assert "not connected" not in err
    run_id = re.search(r"run_id (\S+)", started.stdout).group(1)
    lines = out.splitlines()
    assert f"run {run_id} of cell {CELL}" in lines
    last = [ln for ln in lines if ln.startswith(f"run {run_id}: ")][-1]
    done, total = re.search(r": (\d+)/(\d+)", last).groups()
    # four poses are too few for a fit, so the daemon's run ends "failed" (no result) after
    # measuring everything; watch must follow it to its end either way
    assert last.split()[-1] in ("finished", "failed") and done == total
    assert any(ln.startswith("sample ") for ln in lines)
    assert quiet.returncode == 0, quiet.stderr
    assert quiet.stdout == "" and "not connected" not in quiet.stderr, quiet.stderr
