"""Who may control the daemon: tokens on loopback, mTLS and Zenoh access control for remote use.

An unauthorised client on loopback can neither start motion nor read plans; every refusal is
logged. With TLS, a client without a certificate cannot connect, the router's ACL drops a
viewer's ``start`` before it reaches the daemon, and the daemon's handler refuses a stolen token
presented over another subject's TLS link. Certificates are made with ``openssl`` in tmp_path.
"""

from __future__ import annotations

import shutil

import pytest

from acquire.bus import BusError
from acquire.control import BadRequest, Conflict, NoReply, Refused, Unverified

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


@pytest.fixture
def notify():
    n = NotifySocket()
    yield n
    n.close()


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
            run_id = op.call("start", {"plan": "example.yaml"})["run_id"]
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
    refusals = [line for line in log.splitlines() if line.startswith("WARNING acquire.control: refused control/")]
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
    ours = [line for line in log.splitlines() if "acquire.control" in line]
    assert not any("control/start" in line and "viewer" in line for line in ours)  # never reached the daemon…
    denied = [line for line in log.splitlines() if "is unauthorized to Query" in line]
    assert any("CertCommonName(viewer)" in d and "remaster/example/control/start" in d for d in denied)  # …it was logged
    assert not any("CertCommonName(operator)" in d for d in denied)
