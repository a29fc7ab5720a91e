"""A client on the cell PC sends nothing to a listener it has not authenticated (issue 32).

While the daemon is down (or restarting), any local process can listen where it listened. Over
TCP on loopback nothing tells a client who listens, so the CLI sends no credential there (and
no operation beyond status and runs, whose replies it marks as unauthenticated). On the
daemon's Unix sockets the kernel does: the control-socket client checks the listener's uid
(SO_PEERCRED) and the Zenoh client checks that only root or the daemon's account can have put
the socket at its path. (The daemon's side, its Zenoh socket in the operators' group, and the
operator's start and abort over it are in test_control_neighbours.py and test_daemon_security.py,
with the daemons those files start anyway.) Accounts are throw-away uids in forked children.
"""

from __future__ import annotations

import json
import os
import re
import socket
import threading
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquire.cli import app
from acquire.daemon.local_sockets import UntrustedPeer, check_socket_path, credential_endpoint_problem, trusted_uids

from daemon_harness import (  # noqa: E402 - tests/acquire is on sys.path under pytest
    CELL,
    NEIGHBOUR_UID,
    OPERATOR_TOKEN,
    as_account,
    free_port,
    needs_root,
    wait_until,
)

FORGED = {"ok": True, "run_id": "FAKE", "state": "aborted", "cell": CELL}


class Impostor:
    """A local process listening on ``endpoint`` while the daemon is down: it announces itself
    as the daemon, keeps every query it gets (key, attachment) and answers each with FORGED."""

    def __init__(self, endpoint: str) -> None:
        from acquire.live.bus import Bus

        self.bus = Bus(CELL, config={"mode": "router", "listen": [endpoint]})
        self.bus.liveliness_token(self.bus.key("daemon"))
        self.seen: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

        def handler(query) -> None:
            with self._lock:
                att = query.attachment.to_bytes() if query.attachment is not None else b""
                self.seen.append((str(query.key_expr), att))
            query.reply(query.key_expr, json.dumps(FORGED))

        self._q = self.bus.session.declare_queryable("**", handler)

    def queries(self) -> list[tuple[str, bytes]]:
        time.sleep(0.3)  # anything still on its way arrives
        with self._lock:
            return list(self.seen)

    def close(self) -> None:
        self._q.undeclare()
        self.bus.close()


def token_file(folder: Path) -> Path:
    path = folder / "token"
    path.write_text(OPERATOR_TOKEN + "\n")
    path.chmod(0o600)
    return path


def cli(*args: str):
    return CliRunner().invoke(app, list(args))


def test_an_impostor_on_the_daemons_tcp_port_gets_no_query_from_the_cli(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    impostor = Impostor(endpoint)
    try:
        creds = ("--cell", CELL, "--client", "operator", "--token-file", str(token_file(tmp_path)),
                 "--connect", endpoint, "--timeout", "3")
        for op in ("start", "abort", "status"):
            res = cli(op, *(["example.yaml"] if op == "start" else []), *creds)
            assert res.exit_code == 2, res.output
            assert "not sending credentials" in res.output and "nothing authenticates a tcp/ listener" in res.output
        # Without credentials: an abort whose reply anyone could write is not sent either.
        res = cli("abort", "--cell", CELL, "--connect", endpoint, "--timeout", "3")
        assert res.exit_code == 2 and "not sending abort (its reply could come from anyone)" in res.output, res.output
        assert "FAKE" not in res.output
        assert impostor.queries() == []  # no client-first, no client-final, no abort
    finally:
        impostor.close()


def test_an_impostor_socket_in_a_folder_others_may_write_gets_nothing_from_the_cli(tmp_path, socket_dir):
    folder = socket_dir / "w"
    folder.mkdir()
    folder.chmod(0o777)  # any account could have put the socket here
    endpoint = f"unixsock-stream/{folder / 'zenoh.sock'}"
    impostor = Impostor(endpoint)
    try:
        res = cli("start", "example.yaml", "--cell", CELL, "--client", "operator", "--token-file",
                  str(token_file(tmp_path)), "--connect", endpoint, "--timeout", "3")
        assert res.exit_code == 2, res.output
        assert f"{folder} (on the way to {folder / 'zenoh.sock'}) has mode 0777" in res.output
        assert "nothing was sent" in res.output and impostor.queries() == []
    finally:
        impostor.close()


def _bind(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    return s


def test_a_socket_path_is_trusted_only_when_no_other_account_could_have_made_it(socket_dir):
    me = trusted_uids()
    good = socket_dir / "ok.sock"
    s = _bind(good)
    try:
        check_socket_path(good, me)  # /tmp is sticky: its entries stay their owners'
        with pytest.raises(UntrustedPeer, match=r"^/ \(on the way to .*\) belongs to uid 0"):
            check_socket_path(good, frozenset({12345}))  # a trust set without root: / is root's
        with pytest.raises(UntrustedPeer, match="no socket at"):
            check_socket_path(socket_dir / "missing.sock", me)
        (socket_dir / "file").write_text("")
        with pytest.raises(UntrustedPeer, match="is not a socket"):
            check_socket_path(socket_dir / "file", me)
        # A link in a folder others may write: they could point it elsewhere after the check.
        shared = socket_dir / "shared"
        shared.mkdir()
        (shared / "link.sock").symlink_to(good)
        shared.chmod(0o777)
        with pytest.raises(UntrustedPeer, match=r"shared \(on the way to .*link.sock\) has mode 0777"):
            check_socket_path(shared / "link.sock", me)
        shared.chmod(0o1777)  # sticky: the link stays its owner's
        check_socket_path(shared / "link.sock", me)
        # A link in a trusted folder to a socket in a folder others may write: the target's folder counts.
        open_dir = socket_dir / "open"
        open_dir.mkdir()
        target = _bind(open_dir / "t.sock")
        open_dir.chmod(0o770)
        (socket_dir / "to-open.sock").symlink_to(open_dir / "t.sock")
        with pytest.raises(UntrustedPeer, match=r"open \(on the way to .*to-open.sock\) has mode 0770"):
            check_socket_path(socket_dir / "to-open.sock", me)
        target.close()
        if os.geteuid() == 0:  # another account's folder, and another account's socket
            theirs = socket_dir / "theirs"
            theirs.mkdir()
            os.chown(theirs, NEIGHBOUR_UID, NEIGHBOUR_UID)
            t = _bind(theirs / "x.sock")
            with pytest.raises(UntrustedPeer, match=rf"theirs \(on the way to .*\) belongs to uid {NEIGHBOUR_UID}"):
                check_socket_path(theirs / "x.sock", me)
            t.close()
            # Their link to our socket in a sticky folder: they could point it elsewhere after the check.
            os.lchown(shared / "link.sock", NEIGHBOUR_UID, NEIGHBOUR_UID)
            with pytest.raises(UntrustedPeer, match=rf"link.sock \(on the way to .*\) belongs to uid {NEIGHBOUR_UID}"):
                check_socket_path(shared / "link.sock", me)
            os.chown(good, NEIGHBOUR_UID, NEIGHBOUR_UID)
            with pytest.raises(UntrustedPeer, match=rf"the socket .*ok.sock belongs to uid {NEIGHBOUR_UID}"):
                check_socket_path(good, me)
    finally:
        s.close()


def test_only_a_checked_socket_or_tls_with_the_daemons_ca_may_carry_credentials(socket_dir, tmp_path):
    me = trusted_uids()
    s = _bind(socket_dir / "z.sock")
    try:
        assert credential_endpoint_problem(f"unixsock-stream/{socket_dir / 'z.sock'}", tls_ca=None, trusted=me) is None
        assert "no socket at" in credential_endpoint_problem(f"unixsock-stream/{socket_dir / 'y.sock'}",
                                                             tls_ca=None, trusted=me)
    finally:
        s.close()
    for ep in ("tls/cellpc:7447", "quic/10.0.0.5:7447"):
        assert credential_endpoint_problem(ep, tls_ca=tmp_path / "ca.pem", trusted=me) is None
        assert "give --tls-ca" in credential_endpoint_problem(ep, tls_ca=None, trusted=me)  # else: Mozilla's roots
    for ep in ("tcp/127.0.0.1:7447", "tcp/[::1]:7447", "udp/127.0.0.1:7447", "ws/127.0.0.1:7447"):
        assert "nothing authenticates" in credential_endpoint_problem(ep, tls_ca=tmp_path / "ca.pem", trusted=me)


@needs_root
def test_the_control_socket_client_sends_nothing_to_a_listener_of_another_account(socket_dir):
    folder = socket_dir / "neighbour"
    folder.mkdir()
    os.chown(folder, NEIGHBOUR_UID, NEIGHBOUR_UID)
    path = folder / "control.sock"

    def impostor() -> dict:  # in the forked child, as the neighbour: syscalls only
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(str(path))
        os.chmod(path, 0o666)
        srv.listen(1)
        srv.settimeout(20)
        conn, _ = srv.accept()
        conn.settimeout(1.0)
        got = b""
        try:
            while chunk := conn.recv(65536):
                got += chunk
        except OSError:
            pass
        try:
            conn.sendall(json.dumps(FORGED).encode() + b"\n")
        except OSError:
            pass
        return {"received": got.decode(errors="replace")}

    result: dict = {}
    child = threading.Thread(target=lambda: result.update(as_account(NEIGHBOUR_UID, [], impostor)))
    child.start()
    try:
        wait_until(lambda: path.exists(), 10, "the impostor's socket")
        res = cli("abort", "--socket", str(path), "--reason", "stop now")
    finally:
        child.join(30)
    assert res.exit_code == 3, res.output
    assert re.search(rf"is served by uid {NEIGHBOUR_UID} \(\S+\), pid \d+, not by the daemon's account", res.output)
    assert "FAKE" not in res.output
    assert result == {"received": ""}, result  # not even the operation's name


def test_watch_reaches_the_daemons_socket_by_default_only_when_the_check_passes(socket_dir, monkeypatch):
    from acquire.commands.watch import DEFAULT_CONNECT, _default_connect
    from acquire.daemon import local_sockets

    endpoint = f"unixsock-stream/{socket_dir / 'zenoh.sock'}"
    monkeypatch.setattr(local_sockets, "DEFAULT_LOCAL_ENDPOINT", endpoint)
    assert _default_connect() == [DEFAULT_CONNECT]  # no daemon there
    s = _bind(socket_dir / "zenoh.sock")
    try:
        assert _default_connect() == [DEFAULT_CONNECT, endpoint]
        socket_dir.chmod(0o777)  # anyone could have made it
        assert _default_connect() == [DEFAULT_CONNECT]
    finally:
        socket_dir.chmod(0o755)
        s.close()
