"""Test harness for ``acquire daemon``: a fake systemd notify socket, a daemon subprocess, a
control client, and test certificates made with ``openssl``.

Everything on loopback. The notify socket is a real Unix datagram socket in the abstract
namespace (``NOTIFY_SOCKET=@name``), read by a thread that keeps every datagram with its
arrival time, as systemd would receive them.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
PLANS = REPO / "fixtures" / "plans"
CELL = "example"  # the cell id of fixtures/plans/example.yaml
# Strong tokens (acquire.daemon.tokens refuses weak ones), fixed so a failing test can be re-run by hand.
OPERATOR_TOKEN = "op-7Qm2vX9kLp4RtZ8wYc3NbF6hJd"
VIEWER_TOKEN = "vw-Hs5gT1qWe8RuI3oPa6SdF9jKl2"

#: PBKDF2 iterations of the test configurations: the least a configuration may hold (fast).
TEST_ITERATIONS = 4096


def scram(token: str, iterations: int = TEST_ITERATIONS) -> dict:
    """The ``scram`` mapping of a daemon-configuration client with ``token`` (as `acquire token new` prints)."""
    from acquire.daemon.control_auth import derive_credentials

    return derive_credentials(token, iterations).config()


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Notification:
    t: float
    fields: dict[str, str]


class NotifySocket:
    """A stand-in for systemd's notification socket (abstract namespace)."""

    def __init__(self) -> None:
        self.name = f"@remaster-test-{uuid.uuid4().hex[:12]}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + self.name[1:])
        self.sock.settimeout(0.05)
        self.messages: list[Notification] = []
        self._cond = threading.Condition()
        self._run = True
        self._thread = threading.Thread(target=self._loop, name="notify-socket", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while self._run:
            try:
                data = self.sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().splitlines() if "=" in line)
            with self._cond:
                self.messages.append(Notification(time.monotonic(), fields))
                self._cond.notify_all()

    def wait_for(self, pred: Callable[[dict], bool], timeout: float) -> Notification:
        """The first notification (past or future) whose fields satisfy ``pred``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for m in self.messages:
                    if pred(m.fields):
                        return m
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"no matching notification in {timeout} s; got {self.all_fields()}")
                self._cond.wait(left)

    def all_fields(self) -> list[dict]:
        with self._cond:
            return [m.fields for m in self.messages]

    def count(self, key: str, value: str | None = None) -> int:
        return sum(1 for f in self.all_fields() if key in f and (value is None or f[key] == value))

    def close(self) -> None:
        self._run = False
        self._thread.join(2)
        self.sock.close()


#: Throw-away ids (no account needs to exist): the operators' group, a member, a neighbour.
OPERATORS_GID = 65531
MEMBER_UID = 65532
NEIGHBOUR_UID = 65533

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as other uids (setuid in a child)")


def as_account(uid: int, groups: list[int], fn) -> dict:
    """``fn()``'s JSON-able result, computed in a forked child that runs as ``uid`` (gid ``uid``)
    with supplementary ``groups`` — system calls and already-imported modules only."""
    read_fd, write_fd = os.pipe()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # fork() with threads: the child only makes syscalls
        pid = os.fork()
    if pid == 0:  # the child
        try:
            os.close(read_fd)
            os.setgroups(groups)
            os.setgid(uid)
            os.setuid(uid)
            result = fn()
        except BaseException as exc:  # noqa: BLE001 - reported to the parent
            result = {"error": f"{type(exc).__name__}: {exc}"}
        os.write(write_fd, json.dumps(result).encode())
        os._exit(0)
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as pipe:
        data = pipe.read()
    os.waitpid(pid, 0)
    return json.loads(data)


def copy_example_plan(folder: Path) -> Path:
    """fixtures/plans/example.yaml copied into ``folder`` (its relative paths made absolute), so
    a test reads back exactly the plan text it ran."""
    folder.mkdir(parents=True, exist_ok=True)
    text = (PLANS / "example.yaml").read_text()
    for rel in ("../robots/", "../sim/"):
        text = text.replace(rel, str((PLANS / rel).resolve()) + "/")
    dst = folder / "example.yaml"
    dst.write_text(text)
    return dst


def write_config(tmp_path: Path, port: int, **extra) -> Path:
    """A daemon.yaml for the simulated cell on loopback with an operator and a viewer client;
    its plan folder holds a copy of the example plan."""
    copy_example_plan(tmp_path / "plans")
    cfg = {
        "cell": CELL,
        "state_dir": str(tmp_path / "state"),
        "plan_dirs": [str(tmp_path / "plans")],
        "fake": {"time_scale": 3.0},  # the daemon's cell runs every plan: as fast as the example's fake section
        "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
        "auth": {
            "clients": [
                {"name": "operator", "scram": scram(OPERATOR_TOKEN),
                 "allow": ["observe", "read", "control", "motion"]},
                {"name": "viewer", "scram": scram(VIEWER_TOKEN), "allow": ["observe", "control"]},
            ],
        },
        "shutdown": {"on_sigterm": "pause", "timeout_s": 30},
    }
    for k, v in extra.items():
        cfg[k] = v
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    path.chmod(0o600)  # it holds client keys: the daemon refuses a file other users may read
    return path


def unit_environment(unit: str = "remaster.service") -> dict[str, str]:
    """The ``Environment=`` assignments of a shipped systemd unit (``systemd/<unit>``): the daemon
    under test runs with the environment its unit gives it in a cell."""
    env = {}
    for line in (REPO / "systemd" / unit).read_text().splitlines():
        if line.startswith("Environment="):
            for item in line.removeprefix("Environment=").split():
                key, _, value = item.partition("=")
                env[key] = value
    return env


class DaemonProcess:
    """``python -m acquire daemon --config …`` with a fake notify socket and a watchdog, in the
    environment of its systemd unit (``unit_environment``) plus ``env``."""

    def __init__(self, config: Path, notify: NotifySocket, *, watchdog_usec: int = 1_000_000,
                 env: dict | None = None) -> None:
        self.log_path = config.parent / "daemon.log"
        e = dict(os.environ, **unit_environment(), NOTIFY_SOCKET=notify.name, WATCHDOG_USEC=str(watchdog_usec))
        e.pop("JOURNAL_STREAM", None)
        e.update(env or {})
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "acquire", "daemon", "--config", str(config)],
            cwd=REPO, env=e, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
        )
        self.pid = self.proc.pid
        self.notify = notify

    def wait_ready(self, timeout: float = 30.0) -> Notification:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited with {self.proc.returncode}:\n{self.log()}")
            try:
                return self.notify.wait_for(lambda f: f.get("READY") == "1", 0.2)
            except AssertionError:
                continue
        raise AssertionError(f"daemon not READY in {timeout} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 40.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        finally:
            self._log.close()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()

    # /proc figures of the daemon process
    def threads(self) -> int:
        return len(os.listdir(f"/proc/{self.pid}/task"))

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.pid}/fd"))

    def rss_kb(self) -> int:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise AssertionError("no VmRSS in /proc status")

    def sockets(self) -> int:
        n = 0
        for fd in os.listdir(f"/proc/{self.pid}/fd"):
            try:
                n += os.readlink(f"/proc/{self.pid}/fd/{fd}").startswith("socket:")
            except OSError:  # closed meanwhile
                pass
        return n


def start_abort_cycles(proc: DaemonProcess, op, cycles: int) -> list[tuple]:
    """Start the example plan and abort it once running, ``cycles`` times; after each, the row
    (cycle, threads, fds, sockets, rss_kb, python_heap_kb) of the daemon (heap: run it with
    ``PYTHONTRACEMALLOC=1``)."""
    rows = []
    for cycle in range(cycles):
        run_id = op.call("start", {"plan": "example.yaml"}, timeout=60)["run_id"]
        wait_until(lambda: (op.call("status")["run"] or {}).get("state") == "running", 30, f"run {run_id} running")
        op.call("abort", {"reason": f"soak cycle {cycle}"})
        st = wait_until(lambda: (s := op.call("status"))["run"] is None and s, 30, f"run {run_id} ended")
        assert st["healthy"], st["health"]
        rows.append((cycle, proc.threads(), proc.fds(), proc.sockets(), proc.rss_kb(), st["memory"]["python_heap_kb"]))
    return rows


def leak_figures(rows: list[tuple], warm_up: int) -> dict:
    """Growth from row ``warm_up`` to the end and robust (Theil–Sen) slopes per cycle of the
    rows of ``start_abort_cycles``; ``line``: the figures for a person."""
    from scipy.stats import theilslopes

    base, end = rows[warm_up], rows[-1]
    steady = rows[warm_up:]
    cycles = [r[0] for r in steady]
    heap_slope = theilslopes([r[5] for r in steady], cycles)[0]
    rss_slope = theilslopes([r[4] for r in steady], cycles)[0]
    line = (f"after {len(rows)} start/abort cycles (baseline = cycle {warm_up}): threads {base[1]}→{end[1]}, "
            f"fds {base[2]}→{end[2]}, sockets {base[3]}→{end[3]}, "
            f"Python heap {base[5] / 1024:.2f}→{end[5] / 1024:.2f} MiB (robust slope {heap_slope:+.1f} kB/cycle), "
            f"RSS {base[4] / 1024:.1f}→{end[4] / 1024:.1f} MiB ({(end[4] - base[4]) / 1024:+.1f} MiB, "
            f"robust slope {rss_slope:+.0f} kB/cycle)")
    return {"base": base, "end": end, "heap_slope": heap_slope, "rss_slope": rss_slope, "line": line}


def open_client(port: int, *, tls: dict | None = None, proto: str = "tcp"):
    """A client-mode Bus connected to the daemon's router, returned once the daemon's
    liveliness token is visible through it (the route is up)."""
    from acquire.live.bus import Bus

    config = {"mode": "client", "connect": [f"{proto}/127.0.0.1:{port}"], "zenoh": {}}
    if tls:
        config["zenoh"]["transport/link/tls"] = tls
    bus = Bus(CELL, config=config)
    try:
        wait_until(lambda: bus.alive(f"remaster/{CELL}/daemon", timeout=1.0), 10, "the daemon's liveliness token")
    except BaseException:
        bus.close()
        raise
    return bus


def control(bus, client: str | None = None, token: str | None = None):
    from acquire.daemon.control import ControlClient

    return ControlClient(bus.session, CELL, client=client, token=token)


def wait_until(fn: Callable[[], object], timeout: float, what: str, poll: float = 0.05):
    """Poll ``fn`` until it returns something truthy; that value, or AssertionError naming ``what``."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = fn()
        if last:
            return last
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


def make_certs(folder: Path, names: list[str]) -> dict[str, tuple[Path, Path]]:
    """A throw-away CA and one certificate per name (CN=name, SAN localhost/127.0.0.1), made
    with ``openssl`` in ``folder``. Returns {"ca": (cert, key), name: (cert, key), …}."""
    folder.mkdir(parents=True, exist_ok=True)

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=folder)

    run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", "ca.key",
        "-out", "ca.pem", "-days", "1", "-subj", "/CN=remaster-test-ca")
    (folder / "ext.cnf").write_text(
        "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
        "extendedKeyUsage=serverAuth,clientAuth\n"
    )
    out = {"ca": (folder / "ca.pem", folder / "ca.key")}
    for n in names:
        run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", f"{n}.key",
            "-out", f"{n}.csr", "-subj", f"/CN={n}")
        run("x509", "-req", "-in", f"{n}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{n}.pem", "-days", "1", "-extfile", "ext.cnf")
        out[n] = (folder / f"{n}.pem", folder / f"{n}.key")
    return out


# ----------------------------------------------------------------------------- fixtures
# (offered to every test in tests/acquire by its conftest.py)
@pytest.fixture
def notify():
    """A fake systemd notification socket, closed after the test."""
    n = NotifySocket()
    yield n
    n.close()


@pytest.fixture
def socket_dir():
    """A short folder every account may traverse but not write, as systemd makes /run/remaster
    (RuntimeDirectoryMode=0755): tmp_path's ancestors are private to root, and its path can be
    longer than a Unix socket's 107 bytes."""
    folder = Path(tempfile.mkdtemp(prefix="remaster-ctl-", dir="/tmp"))
    folder.chmod(0o755)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def daemon(tmp_path, notify):
    """An ``acquire daemon`` subprocess on a free loopback port with the test configuration
    (``write_config``) in ``tmp_path``, watchdog 1 s; yields (process, port, tmp_path). Call
    ``wait_ready()`` on the process before talking to it. Killed after the test."""
    port = free_port()
    proc = DaemonProcess(write_config(tmp_path, port), notify, watchdog_usec=1_000_000)
    try:
        yield proc, port, tmp_path
    finally:
        proc.kill()
