"""The operators' control socket (``acquire.daemon.control_socket``) on its own: what it answers, what
it refuses, how it bounds one caller, and the CLI's use of it. A real Unix socket under
``tmp_path``; the daemon behind it is a recording stand-in for ``ControlServer.perform``."""

from __future__ import annotations

import os
import socket
import stat
import threading
import time

import pytest
from typer.testing import CliRunner

from acquire.cli import app
from acquire.daemon.control import Conflict, Identity, NoReply
from acquire.daemon.control_socket import MAX_PER_UID, ControlSocketServer, SocketClient


class Performed:
    """What the server was asked to do, by whom; abort and status answer, start is refused."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, bytes | None, Identity]] = []

    def __call__(self, op: str, payload: bytes | None, identity: Identity) -> dict:
        self.calls.append((op, payload, identity))
        if op == "start":
            raise Conflict("a run is active")
        return {"state": "aborting"} if op == "abort" else {"cell": "lab1", "run": None}


@pytest.fixture
def served(tmp_path):
    performed = Performed()
    server = ControlSocketServer(tmp_path / "control.sock", os.getgid(), ["observe", "control"], performed)
    yield server, performed
    server.close()


def test_a_request_is_performed_as_the_kernel_names_the_caller(served):
    server, performed = served
    st = os.stat(server.path)
    assert stat.S_ISSOCK(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o660 and st.st_gid == os.getgid()
    client = SocketClient(server.path)
    assert client.call("abort", {"reason": "r"}) == {"ok": True, "state": "aborting"}
    op, payload, identity = performed.calls[-1]
    assert (op, payload) == ("abort", b'{"reason": "r"}')
    assert identity.client.startswith(f"uid {os.getuid()} (") and identity.permissions == {"observe", "control"}
    with pytest.raises(Conflict, match="a run is active"):
        client.call("start", {"plan": "x.yaml"})


def _raw(path, data: bytes) -> bytes:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(path))
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out


@pytest.mark.parametrize("data, why", [
    (b"not json\n", b"not one JSON object"),
    (b'{"op": "format-disk"}\n', b"unknown operation"),
    (b'{"op": "abort", "request": [1]}\n', b"must be a JSON object"),
    (b"{" * 2_000_000, b"longer than"),
], ids=["not-json", "unknown-op", "request-not-object", "too-long"])
def test_malformed_requests_get_a_bad_request_reply_and_perform_nothing(served, data, why):
    server, performed = served
    reply = _raw(server.path, data)
    assert b'"bad-request"' in reply and why in reply, reply[:200]
    assert performed.calls == []


def test_one_caller_cannot_hold_more_than_its_share(served):
    server, performed = served
    idle = []
    try:
        for _ in range(MAX_PER_UID):  # connections that send nothing keep their slot until the read timeout
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(server.path))
            idle.append(s)
        deadline = time.monotonic() + 10
        while server._open < MAX_PER_UID and time.monotonic() < deadline:  # noqa: SLF001 - wait for the threads
            time.sleep(0.01)
        with pytest.raises(Conflict, match="busy"):
            SocketClient(server.path).call("abort")
    finally:
        for s in idle:
            s.close()
    # Slots come back as the idle connections close.
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            assert SocketClient(server.path).call("abort")["ok"]
            break
        except Conflict:
            time.sleep(0.05)
    else:
        raise AssertionError("the slots never came back")


def test_a_stale_socket_is_replaced_and_a_live_one_is_not_taken_over(tmp_path):
    path = tmp_path / "control.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # the file stays: a daemon that died
    first = ControlSocketServer(path, os.getgid(), ["observe"], Performed())
    try:
        with pytest.raises(OSError, match="another daemon serves"):
            ControlSocketServer(path, os.getgid(), ["observe"], Performed())
        assert SocketClient(path).call("status")["cell"] == "lab1"  # the first one still answers
    finally:
        first.close()
    assert not path.exists()
    with pytest.raises(NoReply, match="no daemon serves the control socket"):
        SocketClient(path).call("status")


def test_the_cli_uses_the_socket_without_credentials(served, tmp_path):
    server, performed = served
    res = CliRunner().invoke(app, ["abort", "--socket", str(server.path), "--reason", "from the CLI"])
    assert res.exit_code == 0, res.output
    assert performed.calls[-1][:2] == ("abort", b'{"reason": "from the CLI"}')
    res = CliRunner().invoke(app, ["status", "--json"], env={"REMASTER_CONTROL_SOCKET": str(server.path)})
    assert res.exit_code == 0 and '"cell": "lab1"' in res.output, res.output
    res = CliRunner().invoke(app, ["start", "x.yaml", "--socket", str(server.path)])
    assert res.exit_code == 2 and "a run is active" in res.output
    res = CliRunner().invoke(app, ["pause", "--socket", str(tmp_path / "nothing.sock")])
    assert res.exit_code == 4 and "no daemon serves the control socket" in res.output


def test_a_slow_caller_does_not_hold_up_another(served):
    server, performed = served
    slow = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    slow.connect(str(server.path))
    slow.sendall(b'{"op": "status"')  # and nothing more for now
    try:
        done = threading.Event()
        threading.Thread(target=lambda: (SocketClient(server.path).call("abort"), done.set()), daemon=True).start()
        assert done.wait(4), "abort waited behind a caller that had not finished its request"
    finally:
        slow.close()
