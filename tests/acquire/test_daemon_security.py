"""Who may control the daemon: tokens on loopback, mTLS and Zenoh access control for remote use.

An unauthorised client on loopback can neither start motion nor read plans; every refusal is
logged. With TLS, a client without a certificate cannot connect, the router's ACL drops a
viewer's ``start`` before it reaches the daemon, and the daemon's handler refuses a stolen token
presented over another subject's TLS link. Certificates are made with ``openssl`` in tmp_path.
"""

from __future__ import annotations

import json
import re
import shutil
import threading

import pytest

from acquire.live.bus import BusError
from acquire.daemon.control import BadRequest, Conflict, ControlClient, NoReply, Refused, Unverified

from daemon_harness import (  # noqa: E402 - tests/acquire is on sys.path under pytest
    CELL,
    OPERATOR_TOKEN,
    VIEWER_TOKEN,
    DaemonProcess,
    NotifySocket,
    control,
    free_port,
    make_certs,
    open_client,
    scram,
    wait_until,
    write_config,
)


@pytest.mark.slow  # ~40 s: a daemon and a run; anonymous refusals are test_control_channel.py's and the stand-in test's (default)
def test_unauthorised_loopback_client_can_neither_start_motion_nor_read_plans(tmp_path, notify):
    port = free_port()
    proc = DaemonProcess(write_config(tmp_path, port), notify)
    try:
        proc.wait_ready()
        with open_client(port) as bus:
            anon = control(bus)
            thief = control(bus, "operator", "Guessed-token-but-long-enough-9")
            viewer = control(bus, "viewer", VIEWER_TOKEN)
            inline = (tmp_path / "plans" / "example.yaml").read_text()
            attempts = [
                (anon, "start", {"plan": "example.yaml"}),
                (anon, "start", {"plan_text": inline}),
                (anon, "resume", None),
                (thief, "start", {"plan": "example.yaml"}),
                (viewer, "start", {"plan": "example.yaml"}),
                (viewer, "resume", None),
            ]
            for who, op, req in attempts:
                # The thief's proof fails, so the daemon's refusal is unsigned: the thief's client
                # cannot attribute it to the daemon and says so.
                with pytest.raises(Unverified if who is thief else Refused,
                                   match=f"{op} refused: needs permission 'motion'"):
                    who.call(op, req)
            with pytest.raises(Unverified, match="wrong token for client 'operator'"):
                thief.call("start", {"plan": "example.yaml"})
            assert anon.call("status")["run"] is None  # nothing started
            assert not (tmp_path / "state" / "plans").exists()  # the inline plan was never written

            # A run the operator started: the others see its progress but not its plan.
            op = control(bus, "operator", OPERATOR_TOKEN)
            run_id = op.call("start", {"plan": "example.yaml"}, timeout=60)["run_id"]
            run = anon.call("status")["run"]
            assert run["run_id"] == run_id and "plan" not in run
            assert op.call("status")["run"]["plan"] == str(tmp_path / "plans" / "example.yaml")
            for who in (anon, thief, viewer):
                with pytest.raises(Unverified if who is thief else Refused,
                                   match="plan refused: needs permission 'read'"):
                    who.call("plan", {"run_id": run_id})
            assert op.call("plan")["plan_text"] == inline
            # The viewer holds 'control': it may stop motion, never cause it.
            viewer.call("abort", {"reason": "viewer stops it"})
            wait_until(lambda: anon.call("status")["run"] is None, 30, "run aborted")
        assert proc.stop() == 0
    finally:
        proc.kill()
    log = proc.log()
    refusals = [line for line in log.splitlines() if line.startswith("WARNING acquire.daemon.control: refused control/")]
    assert len(refusals) == len(attempts) + 1 + 3, "\n".join(refusals)
    assert sum("refused control/plan" in r for r in refusals) == 3
    assert "claimed 'operator'" in log and "wrong token" in log
    assert f"run {run_id} ended: aborted (viewer stops it)" in log


def _acl(cell: str) -> dict:
    """Zenoh ACL: the operator's certificate may do everything under remaster/<cell>/; the
    viewer's may query status, runs and plan (the daemon itself refuses it 'plan') and see
    which devices are alive; anything else is denied."""
    msgs_all = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query"]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "everything", "permission": "allow", "flows": ["ingress", "egress"], "messages": msgs_all,
             "key_exprs": [f"remaster/{cell}/**"]},
            {"id": "observe", "permission": "allow", "flows": ["ingress", "egress"], "messages": ["query", "reply", "declare_queryable"],
             "key_exprs": [f"remaster/{cell}/control/{op}" for op in ("status", "runs", "plan")]},
            {"id": "liveliness", "permission": "allow", "flows": ["ingress", "egress"],
             "messages": ["liveliness_query", "declare_liveliness_subscriber", "liveliness_token", "reply"],
             "key_exprs": [f"remaster/{cell}/**"]},
        ],
        "subjects": [{"id": "operators", "cert_common_names": ["operator"]},
                     {"id": "viewers", "cert_common_names": ["viewer"]}],
        "policies": [{"rules": ["everything"], "subjects": ["operators"]},
                     {"rules": ["observe", "liveliness"], "subjects": ["viewers"]}],
    }


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl to make test certificates")
def test_mtls_and_access_control_refuse_strangers_and_viewers(tmp_path, notify):
    pki = make_certs(tmp_path / "pki", ["localhost", "operator", "viewer"])
    ca = str(pki["ca"][0])
    port = free_port()
    config = write_config(
        tmp_path, port,
        zenoh={"listen": [f"tls/127.0.0.1:{port}"],
               "tls": {"root_ca_certificate": ca, "listen_certificate": str(pki["localhost"][0]),
                       "listen_private_key": str(pki["localhost"][1]), "enable_mtls": True},
               "access_control": _acl(CELL)},
        auth={"clients": [
            {"name": "operator", "scram": scram(OPERATOR_TOKEN), "allow": ["observe", "read", "control", "motion"],
             "cert_common_names": ["operator"]},
            {"name": "viewer", "scram": scram(VIEWER_TOKEN), "allow": ["observe"]},
        ]},
    )
    # Zenoh logs its ACL decisions at trace level (see the drop-in example): the refusals the
    # router makes before the daemon sees a query are in the same log.
    acl_log = "warn,zenoh::net::routing::interceptor::access_control=trace"
    proc = DaemonProcess(config, notify, env={"RUST_LOG": acl_log})

    def tls_for(name: str | None) -> dict:
        t = {"root_ca_certificate": ca, "enable_mtls": True}
        if name:
            t.update(connect_certificate=str(pki[name][0]), connect_private_key=str(pki[name][1]))
        return t

    try:
        proc.wait_ready()
        # No client certificate: the TLS handshake fails, no session.
        with pytest.raises(BusError):
            open_client(port, tls=tls_for(None), proto="tls").close()
        with open_client(port, tls=tls_for("viewer"), proto="tls") as bus:
            viewer = control(bus, "viewer", VIEWER_TOKEN)
            assert viewer.call("status")["cell"] == CELL
            # The router's ACL drops the viewer's start: it never reaches the daemon.
            with pytest.raises(NoReply):
                viewer.call("start", {"plan": "example.yaml"}, timeout=2)
            with pytest.raises(Refused, match="needs permission 'read'"):
                viewer.call("plan")
            # The operator's token, stolen, over the viewer's TLS link: refused by the handler.
            stolen = control(bus, "operator", OPERATOR_TOKEN)
            with pytest.raises(Refused, match="the link's CN is 'viewer'"):
                stolen.call("plan")
        with open_client(port, tls=tls_for("operator"), proto="tls") as bus:
            op = control(bus, "operator", OPERATOR_TOKEN)
            with pytest.raises(Conflict, match="no run is active"):
                op.call("plan")  # authorised: it got to the backend
            with pytest.raises(BadRequest, match="not inside the allowed plan folders"):
                op.call("start", {"plan": "/etc/passwd"})
            assert op.call("status")["run"] is None
        assert proc.stop() == 0
    finally:
        proc.kill()
    log = proc.log()
    assert "(mTLS)" in log
    assert "refused control/plan: needs permission 'read'; viewer, TLS CN 'viewer'" in log
    assert "TLS CN 'viewer'" in log and "client 'operator' must connect over TLS" in log
    ours = [line for line in log.splitlines() if "acquire.daemon.control" in line]
    assert not any("control/start" in line and "viewer" in line for line in ours)  # never reached the daemon…
    denied = [line for line in log.splitlines() if "is unauthorized to Query" in line]
    assert any("CertCommonName(viewer)" in d and "remaster/example/control/start" in d for d in denied)  # …it was logged
    # (Zenoh's trace also names the operator's link now: per subject, the daemon's guard —
    # daemon_config.control_guard — says no control query goes *to* it. Its own queries reached
    # the backend: see above.)


# ------------------------------------------------------------------ attacks of issue 21
class Recorder:
    """A local process that declared the control keys: keeps every query it sees (key, payload,
    attachment) and, with ``answer``, answers it as a stand-in daemon would."""

    def __init__(self, bus, answer=None) -> None:
        self.seen: list[tuple[str, bytes | None, bytes | None]] = []
        self._lock = threading.Lock()
        self._answer = answer

        def handler(query) -> None:
            item = (str(query.key_expr), _bytes(query.payload), _bytes(query.attachment))
            with self._lock:
                self.seen.append(item)
            if self._answer is not None:
                query.reply(query.key_expr, json.dumps(self._answer(*item)))

        self._q = bus.session.declare_queryable(f"remaster/{CELL}/control/**", handler)

    def stages(self, op: str) -> dict[str, tuple[bytes | None, bytes]]:
        """The last (payload, attachment) seen for ``op`` per SCRAM stage."""
        with self._lock:
            out = {}
            for key, payload, att in self.seen:
                if key.endswith("/" + op) and att:
                    out[json.loads(att)["scram"]] = (payload, att)
            return out

    def close(self) -> None:
        self._q.undeclare()


class CapturingClient(ControlClient):
    """A control client that keeps every (payload, attachment) it sends, per operation and stage."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.sent: list[tuple[str, bytes | None, bytes | None]] = []

    def _get(self, op, payload, attachment, timeout):
        self.sent.append((op, payload, attachment))
        return super()._get(op, payload, attachment, timeout)

    def stages(self, op: str) -> dict[str, tuple[bytes | None, bytes]]:
        """The last (payload, attachment) sent for ``op`` per SCRAM stage."""
        return {json.loads(att)["scram"]: (payload, att) for o, payload, att in self.sent if o == op and att}


def _bytes(z) -> bytes | None:
    return None if z is None else (z.to_bytes() or None)


def raw_query(bus, op: str, payload: bytes | None, attachment: bytes | None, timeout: float = 10.0) -> list[dict]:
    """Every reply body to one hand-made query (what an attacker replaying bytes gets)."""
    import zenoh

    kwargs = {k: v for k, v in (("payload", payload), ("attachment", attachment)) if v}
    out = []
    for reply in bus.session.get(f"remaster/{CELL}/control/{op}", target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout, **kwargs):
        sample = reply.ok if reply.ok is not None else reply.err
        out.append(json.loads(sample.payload.to_bytes()))
    return out


def _run_dirs(tmp_path) -> list[str]:
    """The run folders the daemon made in its state folder."""
    runs = tmp_path / "state" / "runs"
    return sorted(p.name for p in runs.iterdir() if p.is_dir()) if runs.is_dir() else []


def _replay(bus, op: str, captured: dict) -> list[dict]:
    """Send a captured exchange again: its client-first, then its client-final with its payload."""
    replies = raw_query(bus, op, None, captured["client-first"][1])
    assert any("server_first" in r for r in replies), replies  # a new exchange, with a new nonce…
    return raw_query(bus, op, *captured["client-final"])  # …which the captured proof is not for


@pytest.mark.slow  # ~30 s: two daemon starts; replay against one daemon is test_a_stand_in_daemon's
def test_a_captured_start_is_refused_after_a_restart_and_by_the_same_daemon(tmp_path, notify):
    port = free_port()
    config = write_config(tmp_path, port)
    proc = DaemonProcess(config, notify)
    second = NotifySocket()
    proc2 = None
    try:
        proc.wait_ready()
        with open_client(port) as bus:
            # No other session receives a control query (the daemon's ACL guard; see
            # test_control_neighbours.py): the bytes are captured where they leave the client, as
            # on a link whose TLS was broken.
            op = CapturingClient(bus.session, CELL, client="operator", token=OPERATOR_TOKEN)
            run_id = op.call("start", {"plan": "example.yaml"}, timeout=60)["run_id"]
            captured = op.stages("start")
            assert set(captured) == {"client-first", "client-final"}
            op.call("abort", {"reason": "test"})
            wait_until(lambda: op.call("status")["run"] is None, 30, "run aborted")
            runs_before = _run_dirs(tmp_path)
            # The same daemon: the exchange was used.
            replies = raw_query(bus, "start", *captured["client-final"])
            assert [r["error"] for r in replies] == ["refused"] and "used before" in replies[0]["message"]
            assert all("scram" not in r for r in _replay(bus, "start", captured))
        proc.kill()  # as a watchdog restart does (kill -9)
        first_log = proc.log()
        proc2 = DaemonProcess(config, second)
        proc2.wait_ready()
        with open_client(port) as bus:
            for replies in (raw_query(bus, "start", *captured["client-final"]), _replay(bus, "start", captured)):
                assert [r["error"] for r in replies] == ["refused"], replies
                assert "not issued by this daemon instance" in replies[0]["message"]
            anon = control(bus)
            assert anon.call("status")["run"] is None
            assert _run_dirs(tmp_path) == runs_before  # no second run
        assert proc2.stop() == 0
    finally:
        proc.kill()
        if proc2 is not None:
            proc2.kill()
        second.close()
    assert f"run {run_id} started by operator" in first_log
    log = proc2.log()
    assert "refused control/start" in log and " started by " not in log and "Traceback" not in log


def _stand_in_answer(key: str, payload: bytes | None, att: bytes | None) -> dict:
    """What a stand-in daemon answers: a server-first with its own nonce (it knows no keys),
    then success."""
    from scramp import ScramMechanism

    stage, msg = (json.loads(att)["scram"], json.loads(att)["msg"]) if att else (None, None)
    if stage == "client-first":
        mech = ScramMechanism("SCRAM-SHA-256")
        server = mech.make_server(lambda name: (b"s" * 16, b"k" * 32, b"k" * 32, 4096))
        server.set_client_first(msg)
        return {"ok": True, "server_first": server.get_server_first()}
    return {"ok": True, "run_id": "FAKE", "state": "running", "cell": CELL, "daemon": "ready", "run": None}


def test_a_stand_in_daemon_gets_nothing_the_real_one_accepts_and_the_client_does_not_believe_it(
        tmp_path, notify, socket_dir):
    from typer.testing import CliRunner

    from acquire.cli import app
    from acquire.live.bus import Bus

    port = free_port()
    local = f"unixsock-stream/{socket_dir / 'zenoh.sock'}"  # where the CLI sends a token on the cell PC
    config = write_config(tmp_path, port, zenoh={"listen": [f"tcp/127.0.0.1:{port}", local]})
    token_file = tmp_path / "token"
    token_file.write_text(OPERATOR_TOKEN + "\n")
    token_file.chmod(0o600)
    # The daemon is down; a local process listens on the cell's router port and answers.
    stand_in = Bus(CELL, config={"listen": [f"tcp/127.0.0.1:{port}"]})
    proc = None
    try:
        stand_in.liveliness_token(stand_in.key("daemon"))
        rec = Recorder(stand_in, answer=_stand_in_answer)
        with open_client(port) as bus:
            op = control(bus, "operator", OPERATOR_TOKEN)
            with pytest.raises(Unverified, match="no reply to control/start could be attributed to the daemon"):
                op.call("start", {"plan": "example.yaml"}, timeout=5)
            assert not op.last_reply_verified
        captured = rec.stages("start")
        assert set(captured) == {"client-first", "client-final"}
        # The CLI sends nothing at all over plain TCP, which no one authenticates: exit 2, and the
        # stand-in saw no query from it (test_control_local.py holds the rest of that claim).
        seen = len(rec.seen)
        creds = ["--cell", CELL, "--client", "operator", "--token-file", str(token_file)]
        cli = CliRunner().invoke(app, ["start", "example.yaml", *creds, "--connect", f"tcp/127.0.0.1:{port}"])
        assert cli.exit_code == 2 and "not sending credentials" in cli.output, cli.output
        assert "FAKE" not in cli.output and len(rec.seen) == seen
        cli = CliRunner().invoke(app, ["start", "example.yaml", *creds, "--connect", local])  # the daemon's socket
        assert cli.exit_code == 4 and "no socket at" in cli.output, cli.output
        rec.close()
        stand_in.close()

        proc = DaemonProcess(config, notify)
        proc.wait_ready()
        with open_client(port) as bus:
            for replies in (raw_query(bus, "start", *captured["client-final"]), _replay(bus, "start", captured)):
                assert [r["error"] for r in replies] == ["refused"], replies
                assert "not issued by this daemon instance" in replies[0]["message"]
            anon = control(bus)
            assert anon.call("status")["run"] is None and " started by " not in proc.log()
            # The operator retries once over the daemon's socket: exactly one run, signed replies.
            started = CliRunner().invoke(app, ["start", "example.yaml", *creds, "--connect", local])
            assert started.exit_code == 0, started.output
            run_id = re.search(r"run_id (\S+)", started.output).group(1)
            wait_until(lambda: (anon.call("status")["run"] or {}).get("state") == "running", 30, "run running")
            aborted = CliRunner().invoke(app, ["abort", "--reason", "test", *creds, "--connect", local])
            assert aborted.exit_code == 0 and "reply not authenticated" not in aborted.output, aborted.output
            wait_until(lambda: anon.call("status")["run"] is None, 30, "run aborted")
        assert proc.stop() == 0
    finally:
        stand_in.close()
        if proc is not None:
            proc.kill()
    assert re.findall(r"run (\S+) started by", proc.log()) == [run_id]  # exactly the retry's run


@pytest.mark.slow  # ~30 s: a daemon flooded; abort under a flood is test_control_neighbours.py's (default)
def test_a_flood_of_malformed_queries_makes_a_bounded_log_without_tracebacks(tmp_path, notify):
    port = free_port()
    proc = DaemonProcess(write_config(tmp_path, port), notify)
    bad = [
        ("status", b"[" * 50_000, None),                                   # nested past the recursion limit
        ("start", b"not json", b"\xff\xfe garbage"),                        # attachment not UTF-8
        ("pause", None, b"[1, 2]"),                                         # not an object
        ("start", None, json.dumps({"v": 2, "client": "operator", "nonce": "n", "ts": "1", "proof": "00"}).encode()),
        ("start", None, json.dumps({"v": 3, "scram": "client-first", "msg": "n,,garbage"}).encode()),
        ("start", None, json.dumps({"v": 3, "scram": "client-final", "msg": "c=biws,r=x@dead.beef,p=AAAA"}).encode()),
        ("abort", b'{"reason": ' + b"1" * 5000 + b"}", None),
        ("plan", b'{"run_id": {"a": [1, 2, 3]}}', None),
    ]
    try:
        proc.wait_ready()
        with open_client(port) as bus:
            for i in range(2000):
                op, payload, att = bad[i % len(bad)]
                assert raw_query(bus, op, payload, att), f"no reply to malformed query {i}"
            assert control(bus).call("status")["daemon"]  # still answering

            def counted():
                raw_query(bus, "pause", None, b"[1, 2]")
                return "similar lines from" in proc.log()

            wait_until(counted, 60, "a line with the count of suppressed lines", poll=0.5)
        assert proc.stop() == 0, proc.log()[-3000:]
    finally:
        proc.kill()
    log = proc.log()
    ours = [line for line in log.splitlines() if "acquire.daemon.control" in line]
    assert "Traceback" not in log
    assert 10 <= len(ours) <= 80, f"{len(ours)} lines:\n" + "\n".join(ours[:100])
    assert len(log.encode()) < 100_000
    # each admitted line reports the lines suppressed since the one before (a loaded machine
    # spreads the flood over more admitted lines), and the close logs what is still held back:
    # their sum is every suppressed line
    suppressed = sum(int(m) for m in re.findall(r"\[(\d+) similar lines from", log))
    print(f"2000 malformed queries: {len(ours)} acquire.daemon.control log lines, {len(log.encode())} bytes of log, "
          f"{suppressed} lines suppressed (counted)")
    assert suppressed >= 1500
