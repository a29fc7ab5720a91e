"""A neighbour on the cell PC can neither jam nor read the control plane (issue 32).

- Abort and pause over the operators' control socket get through while another process floods
  the daemon's Zenoh router with anonymous SCRAM client-firsts (the flood that once evicted an
  operator's pending abort), and a SCRAM client on another source still completes.
- A local account without the operators' group gets EACCES from the kernel on the control socket
  and on the daemon's Zenoh socket, and the daemon's own check of the kernel's peer groups refuses
  it even through a control socket opened wider by hand; a member is served and named by its uid. (Accounts are throw-away uids in a forked child.)
- Nothing on the Zenoh router besides the daemon receives a control query: a session that
  declares ``**`` sees no client-first and no client-final — so a reader of the daemon's
  configuration (StoredKey, ServerKey) has no client-final to turn into the client's key
  (RFC 5802 §9), and the keys themselves do not log in.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import re
import secrets
import socket
import stat
import threading
import time
from pathlib import Path

import pytest
import yaml

from acquire.daemon import control_auth as auth
from acquire.daemon.control import Conflict, ControlError, Refused, Unverified
from acquire.daemon.control_socket import SocketClient

from daemon_harness import (  # noqa: E402 - tests/acquire is on sys.path under pytest
    CELL,
    MEMBER_UID,
    NEIGHBOUR_UID,
    OPERATOR_TOKEN,
    OPERATORS_GID,
    DaemonProcess,
    as_account,
    control,
    free_port,
    needs_root,
    open_client,
    wait_until,
    write_config,
)

def socket_call(path: Path, op: str = "status", request: dict | None = None):
    """A function for ``as_account``: the control socket's answer to ``op``, or the refusal."""

    def call() -> dict:
        try:
            return {"reply": SocketClient(path).call(op, request, timeout=10)}
        except Refused as exc:
            return {"refused": str(exc)}
        except ControlError as exc:
            return {"error": f"{type(exc).__name__}: {exc}"}

    return call


def raw_connect(path: Path):
    """A function for ``as_account``: connect(2) to the Unix socket ``path`` and close."""

    def call() -> dict:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.connect(str(path))
        return {"connected": True}

    return call


def socket_config(tmp_path: Path, port: int, sock: Path, group: int) -> Path:
    return write_config(tmp_path, port, control_socket={"path": str(sock), "group": str(group)})


class Sniffer:
    """A session that declared every key: keeps the SCRAM attachments of the queries it gets."""

    def __init__(self, bus) -> None:
        self.attachments: list[tuple[str, dict]] = []
        self._lock = threading.Lock()

        def handler(query) -> None:
            att = query.attachment.to_bytes() if query.attachment is not None else b""
            with self._lock:
                self.attachments.append((str(query.key_expr), json.loads(att) if att.startswith(b"{") else {}))

        # Both forms: a rule on declarations would miss "**" (see daemon_config.control_guard).
        self._qs = [bus.session.declare_queryable(k, handler) for k in ("**", "remaster/**")]

    def seen(self, stage: str | None = None) -> list[tuple[str, dict]]:
        with self._lock:
            return [(k, a) for k, a in self.attachments if stage is None or a.get("scram") == stage]

    def exchanges(self) -> list[tuple[dict, dict]]:
        """(client-first, client-final) pairs seen, each final with the last first on its key."""
        last_first: dict[str, dict] = {}
        pairs = []
        for key, att in self.seen():
            if att.get("scram") == "client-first":
                last_first[key] = att
            elif att.get("scram") == "client-final" and key in last_first:
                pairs.append((last_first[key], att))
        return pairs

    def close(self) -> None:
        for q in self._qs:
            q.undeclare()


# ------------------------------------------------------------------------------- flood
def _flood(port: int, stop: threading.Event, counter: list[int], rate_hz: float = 400.0, max_s: float = 8.0) -> None:
    """Anonymous SCRAM client-firsts for the operator at ``rate_hz`` on the daemon's router,
    replies ignored, until ``stop`` or ``max_s`` (it stops by itself)."""
    import zenoh

    from acquire.live.bus import Bus

    with Bus(CELL, config={"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"], "zenoh": {}}) as bus:
        t0 = time.monotonic()
        while not stop.is_set() and time.monotonic() - t0 < max_s:
            first = f"n,,n=operator,r={secrets.token_urlsafe(18)}.x"
            bus.session.get(f"remaster/{CELL}/control/abort", handler=lambda reply: None,
                            attachment=auth.attachment("client-first", first), target=zenoh.QueryTarget.ALL,
                            timeout=5)
            counter[0] += 1
            time.sleep(max(0.0, t0 + counter[0] / rate_hz - time.monotonic()))


@pytest.mark.slow  # ~25 s: a daemon, a run and a 5 s flood; the per-source bound is tested without one
def test_abort_and_pause_get_through_a_flood_of_unauthenticated_client_firsts(tmp_path, notify, socket_dir):
    port = free_port()
    sock = socket_dir / "control.sock"
    proc = DaemonProcess(socket_config(tmp_path, port, sock, os.getgid()), notify)
    stop, sent = threading.Event(), [0]
    flood = threading.Thread(target=_flood, args=(port, stop, sent), daemon=True)
    try:
        proc.wait_ready()
        ops = SocketClient(sock)
        run_id = ops.call("start", {"plan": "example.yaml"}, timeout=60)["run_id"]
        wait_until(lambda: (ops.call("status")["run"] or {}).get("state") == "running", 30, "run running")
        flood.start()
        # Past the daemon's whole table of pending exchanges (MAX_PENDING = 256), the rate sustained.
        wait_until(lambda: sent[0] >= 2 * auth.MAX_PENDING, 20, "the flood under way", poll=0.02)
        assert ops.call("pause")["ok"]
        with open_client(port) as bus:  # a SCRAM client from another source completes too
            assert control(bus, "operator", OPERATOR_TOKEN).call("status", timeout=10)["run"]["run_id"] == run_id
        assert ops.call("abort", {"reason": "abort under flood"})["ok"]
        flooded = sent[0]
        assert not stop.is_set() and flood.is_alive(), "the flood ended before the abort: not a test of it"
        wait_until(lambda: ops.call("status")["run"] is None, 30, "run aborted")
    finally:
        stop.set()
        flood.join(10)
        proc.stop()
        proc.kill()
    log = proc.log()
    print(f"{flooded} anonymous client-firsts before the abort went through")
    assert f"run {run_id} ended: aborted (abort under flood)" in log
    assert re.search(rf"run {run_id} started by uid {os.getuid()} \(", log)  # the kernel's word, no token


def test_pending_exchanges_are_bounded_per_source():
    creds = auth.derive_credentials(OPERATOR_TOKEN, auth.MIN_ITERATIONS)
    table = auth.ExchangeTable(lambda name: creds if name == "operator" else None, decoy_iterations=4096)
    operator = auth.ClientExchange(OPERATOR_TOKEN, "operator", CELL, "abort", None)
    server_first, _ = table.first(json.loads(operator.first_attachment())["msg"], source="operator-zid")
    for _ in range(2 * auth.MAX_PENDING):  # one source floods, past the whole table
        table.first(f"n,,n=operator,r={secrets.token_urlsafe(18)}", source="flooder-zid")
    assert table.pending() == 1 + auth.MAX_PENDING_PER_SOURCE
    final = operator.answer(server_first).client_final
    assert table.final(final, cell=CELL, op="abort", payload=None).client == "operator"
    # A source id forged per query: the table stays bounded (it shares MAX_PENDING with everyone:
    # the operators' abort goes over the control socket), and each first stays cheap.
    t0 = time.perf_counter()
    for i in range(4 * auth.MAX_PENDING):
        table.first(f"n,,n=x,r={secrets.token_urlsafe(18)}", source=f"zid-{i}")
    assert table.pending() == auth.MAX_PENDING
    print(f"{4 * auth.MAX_PENDING} client-firsts from as many sources into a full table: "
          f"{(time.perf_counter() - t0) / (4 * auth.MAX_PENDING) * 1e3:.2f} ms each")


# ------------------------------------------------------------------------ neighbours
@needs_root
def test_a_neighbour_without_the_group_can_neither_use_the_socket_nor_see_a_client_final(
        tmp_path, notify, socket_dir):
    port = free_port()
    sock = socket_dir / "control.sock"
    zsock = socket_dir / "zenoh.sock"  # the daemon's Zenoh listener on the cell PC, for the same group
    proc = DaemonProcess(write_config(tmp_path, port, control_socket={"path": str(sock), "group": str(OPERATORS_GID)},
                                      zenoh={"listen": [f"tcp/127.0.0.1:{port}", f"unixsock-stream/{zsock}"],
                                             "socket_group": str(OPERATORS_GID)}), notify)
    try:
        proc.wait_ready()
        for path in (sock, zsock):
            st = os.stat(path)
            assert stat.S_IMODE(st.st_mode) == 0o660 and st.st_gid == OPERATORS_GID, path
        # The kernel refuses the neighbour before a byte is exchanged; a member is served.
        neighbour = as_account(NEIGHBOUR_UID, [], socket_call(sock, "abort"))
        assert "permission denied on the control socket" in neighbour.get("refused", ""), neighbour
        member = as_account(MEMBER_UID, [OPERATORS_GID], socket_call(sock))
        assert member.get("reply", {}).get("cell") == CELL, member
        # The same on the Zenoh socket: connect(2) itself fails for the neighbour.
        assert as_account(NEIGHBOUR_UID, [], raw_connect(zsock)).get("error", "").startswith("PermissionError")
        assert as_account(MEMBER_UID, [OPERATORS_GID], raw_connect(zsock)) == {"connected": True}
        # A socket someone opened wider by hand: the daemon's check of the kernel's peer groups.
        os.chmod(sock, 0o666)
        neighbour = as_account(NEIGHBOUR_UID, [], socket_call(sock, "abort"))
        os.chmod(sock, 0o660)
        assert f"not in group {OPERATORS_GID}" in neighbour.get("refused", ""), neighbour

        # On Zenoh (TCP loopback knows no uids: any account connects): a session declaring every
        # key gets no control query, while the operator's SCRAM exchanges complete and the
        # daemon's announcements still reach everyone.
        with open_client(port) as spy_bus, open_client(port) as bus:
            sniffer = Sniffer(spy_bus)
            op = control(bus, "operator", OPERATOR_TOKEN)
            for what in ("status", "runs", "plan"):
                try:
                    op.call(what, timeout=10)
                except ControlError as exc:  # no run yet: 'plan' answers bad-request, signed
                    assert op.last_reply_verified, exc
            assert op.call("status")["cell"] == CELL and op.last_reply_verified
            assert spy_bus.alive(f"remaster/{CELL}/daemon", timeout=2.0)
            time.sleep(0.5)  # let anything routed to the sniffer arrive
            assert sniffer.seen() == [], sniffer.seen()[:3]
            sniffer.close()
        assert proc.stop() == 0
    finally:
        proc.kill()
    log = proc.log()
    assert f"refused uid {NEIGHBOUR_UID}" in log and f"not in group {OPERATORS_GID}" in log


def _client_key(captured: dict, keys: dict, first: dict) -> bytes:
    """RFC 5802 §9: the ClientKey that a reader of StoredKey recovers from one client-final
    (ClientProof XOR HMAC(StoredKey, AuthMessage); the server-first is rebuilt from the
    configuration's salt and iterations)."""
    final = captured["msg"]
    nonce = re.search(r"r=([^,]+)", final).group(1)
    server_first = f"r={nonce},s={keys['salt']},i={keys['iterations']}"
    message = auth.auth_message(first["msg"].split(",", 2)[2], server_first, final)
    signature = hmac.new(base64.b64decode(keys["stored_key"]), message, hashlib.sha256).digest()
    proof = base64.b64decode(final.rsplit(",p=", 1)[1])
    return bytes(a ^ b for a, b in zip(proof, signature))


def _act_as(bus, client_key: bytes, server_key: bytes, op: str, request: dict) -> list[dict]:
    """A SCRAM exchange as 'operator' made from keys, not a token: what the attacker sends."""
    from test_daemon_security import raw_query

    payload = json.dumps(request).encode()
    bare = f"n=operator,r={secrets.token_urlsafe(18)}.{auth.request_digest(CELL, op, payload)}"
    replies = raw_query(bus, op, None, auth.attachment("client-first", "n,," + bare))
    server_first = next(r["server_first"] for r in replies if "server_first" in r)
    nonce = re.search(r"r=([^,]+)", server_first).group(1)
    final, _, _ = auth._client_final(client_key, server_key, bare, server_first, nonce)
    return raw_query(bus, op, payload, auth.attachment("client-final", final))


def test_a_config_reader_cannot_act_as_a_client(tmp_path, notify):
    port = free_port()
    config = write_config(tmp_path, port)
    keys = yaml.safe_load(config.read_text())["auth"]["clients"][0]["scram"]  # what the reader holds
    stored_key, server_key = base64.b64decode(keys["stored_key"]), base64.b64decode(keys["server_key"])
    proc = DaemonProcess(config, notify)
    try:
        proc.wait_ready()
        with open_client(port) as spy_bus, open_client(port) as bus:
            sniffer = Sniffer(spy_bus)
            op = control(bus, "operator", OPERATOR_TOKEN)
            assert op.call("status")["run"] is None
            with pytest.raises(Conflict):  # complete exchanges, signed replies: nothing to pause
                op.call("pause")
            time.sleep(0.5)
            # With one client-first and client-final seen, the reader would be the client:
            for first, final in sniffer.exchanges():
                client_key = _client_key(final, keys, first)
                if hashlib.sha256(client_key).digest() == stored_key:  # it holds: act as the operator
                    _act_as(bus, client_key, server_key, "start", {"plan": "example.yaml"})
                    break
            assert sniffer.seen() == [], sniffer.seen()[:2]
            # The configuration's keys themselves are no token and no ClientKey.
            for guess in (keys["stored_key"], keys["server_key"]):
                with pytest.raises(Unverified, match="wrong token"):
                    control(bus, "operator", guess).call("start", {"plan": "example.yaml"})
            for key_guess in (stored_key, server_key):
                replies = _act_as(bus, key_guess, server_key, "start", {"plan": "example.yaml"})
                assert [r.get("error") for r in replies] == ["refused"], replies
            assert op.call("status")["run"] is None
            sniffer.close()
        assert proc.stop() == 0
    finally:
        proc.kill()
    assert " started by " not in proc.log()  # the attacker started nothing
