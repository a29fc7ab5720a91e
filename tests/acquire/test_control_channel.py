"""The control channel leaks nothing: a rogue queryable on ``remaster/<cell>/control/**`` learns
no usable credential, cannot replay what it captured, and a client never believes its reply.

Real Zenoh sessions on loopback: the daemon's ``ControlServer`` on one, a rogue process's
queryable on another, the client on a third.
"""

from __future__ import annotations

import hashlib
import json
import threading

import pytest

from acquire.daemon import control_auth as auth
from acquire.live.bus import Bus
from acquire.daemon.control import Authorizer, ControlClient, ControlServer, Refused, Unverified
from acquire.daemon.config import AuthSection

CELL = "lab1"
TOKEN = "s3cret-Operator-token-4f1b-Xq9"
CREDS = auth.derive_credentials(TOKEN, auth.MIN_ITERATIONS)


class Backend:
    """The daemon's side of the queries, reduced to what the channel needs."""

    def __init__(self) -> None:
        self.paused = 0
        self.confirmed = 0

    def status(self, *, include_plan: bool) -> dict:
        return {"cell": CELL, "daemon": "ready", "run": None, "who": "daemon"}

    def runs(self) -> dict:
        return {"runs": []}

    def plan(self, run_id):
        return {"plan_text": "…"}

    def start(self, request, identity):
        return {"run_id": "r1"}

    def pause(self) -> dict:
        self.paused += 1
        return {"state": "paused"}

    def resume(self) -> dict:
        return {"state": "running"}

    def abort(self, reason: str) -> dict:
        return {"state": "aborting"}

    def confirm(self) -> dict:
        self.confirmed += 1
        return {"state": "running", "confirmed": ["socket: socket 0 of placement front"]}


class Rogue:
    """A process that declared the control keys: records what it gets and answers first."""

    def __init__(self, bus: Bus, reply: dict) -> None:
        self.seen: list[tuple[str, bytes | None, bytes | None]] = []
        self._lock = threading.Lock()
        self._reply = reply

        def handler(query) -> None:
            with self._lock:
                self.seen.append((str(query.key_expr), _bytes(query.payload), _bytes(query.attachment)))
            query.reply(query.key_expr, json.dumps(self._reply))

        self._q = bus.session.declare_queryable(f"remaster/{CELL}/control/**", handler)

    def wait_for(self, n: int, timeout: float) -> bool:
        """True once ``n`` queries with credentials have arrived (within ``timeout`` s)."""
        import time

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if sum(a is not None for _, _, a in self.seen) >= n:
                    return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        self._q.undeclare()


def _bytes(z) -> bytes | None:
    return None if z is None else z.to_bytes()


@pytest.fixture()
def cell():
    """Three sessions on loopback: daemon, rogue (a peer of the daemon) and a client connected to both."""
    daemon = Bus(CELL, config={"listen": ["tcp/127.0.0.1:0"]})
    rogue = Bus(CELL, config={"listen": ["tcp/127.0.0.1:0"], "connect": daemon.locators})
    client = Bus(CELL, config={"listen": [], "connect": daemon.locators + rogue.locators})
    yield daemon, rogue, client
    for b in (client, rogue, daemon):
        b.close()


def _server(bus: Bus, backend: Backend) -> ControlServer:
    section = AuthSection.model_validate({
        "anonymous": ["observe"],
        "clients": [{"name": "operator", "scram": CREDS.config(),
                     "allow": ["observe", "read", "control", "motion"]}],
    })
    return ControlServer(bus.session, CELL, backend, Authorizer(section))


def _wait_routes(client: Bus, n_responders: int) -> None:
    """Until ``n_responders`` queryables answer an anonymous status (the routes are up)."""
    import time

    import zenoh

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        q = client.session.declare_querier(f"remaster/{CELL}/control/status", target=zenoh.QueryTarget.ALL,
                                           consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0)
        try:
            if len(list(q.get())) >= n_responders:
                return
        finally:
            q.undeclare()
        time.sleep(0.05)
    raise AssertionError(f"{n_responders} control responders not reachable")


def test_rogue_queryable_learns_nothing_usable_and_its_reply_is_refused(cell):
    daemon_bus, rogue_bus, client_bus = cell
    backend = Backend()
    server = _server(daemon_bus, backend)
    rogue = Rogue(rogue_bus, {"ok": True, "cell": CELL, "daemon": "ready", "run": {"run_id": "FAKE"}, "who": "rogue"})
    try:
        _wait_routes(client_bus, 2)
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN)
        for _ in range(4):
            reply = op.call("status")
            assert reply["who"] == "daemon" and reply["run"] is None and op.last_reply_verified
        assert op.call("pause") == {"ok": True, "state": "paused"}
        assert backend.paused == 1

        # What the rogue captured: no token, no hash or key derived from it, in any form. (The
        # client returned on the daemon's reply; the rogue's copy of the last query may still be
        # on its way.) Each operation is two queries: client-first, then client-final.
        assert rogue.wait_for(10, timeout=20), rogue.seen
        captured = [(k, p, a) for k, p, a in rogue.seen if a is not None]
        secret_forms = [TOKEN.encode(), TOKEN.encode().hex().encode(), hashlib.sha256(TOKEN.encode()).hexdigest().encode(),
                        hashlib.sha256(TOKEN.encode()).digest()]
        for key_bytes in (CREDS.stored_key, CREDS.server_key):
            secret_forms += [key_bytes, key_bytes.hex().encode(), auth._b64(key_bytes).encode()]
        for _, _, attachment in captured:
            assert not any(form in attachment for form in secret_forms)
            assert "token" not in json.loads(attachment)

        # Replaying a captured client-final to the daemon: refused (its exchange is used up), nothing moves.
        finals = [c for c in captured if c[0].endswith("/pause") and json.loads(c[2])["scram"] == "client-final"]
        key, payload, attachment = finals[0]
        replay = server.authorizer.identify(attachment, None, cell=CELL, op="pause", payload=payload)
        assert replay[0].client is None and "used before, or expired" in replay[1]
        with pytest.raises(Refused, match="used before, or expired"):
            server.dispatch("pause", payload, attachment, None)
        # Replaying the captured client-first gets a new server-first, with a new server nonce:
        # the captured client-final does not match it.
        first = next(a for k, _, a in captured if k.endswith("/pause") and json.loads(a)["scram"] == "client-first")
        fresh = server.dispatch("pause", None, first, None)[0]["server_first"]
        assert fresh not in [json.loads(a)["msg"] for _, _, a in captured]
        with pytest.raises(Refused, match="used before, or expired"):
            server.dispatch("pause", payload, attachment, None)
        assert backend.paused == 1
        assert server.authorizer.refusals >= 2
    finally:
        rogue.close()
        server.close()


def test_confirm_needs_the_motion_permission(cell):
    """Socket calibration's confirm (the ball sits in the socket) lets the run move on: an
    operator with ``motion`` may send it, an anonymous observer may not."""
    daemon_bus, _, client_bus = cell
    backend = Backend()
    server = _server(daemon_bus, backend)
    try:
        _wait_routes(client_bus, 1)
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN)
        assert op.call("confirm")["confirmed"] == ["socket: socket 0 of placement front"]
        assert backend.confirmed == 1
        with pytest.raises(Refused, match="motion"):
            server.dispatch("confirm", None, None, None)
        assert backend.confirmed == 1
    finally:
        server.close()


def test_client_refuses_replies_it_cannot_attribute_to_the_daemon(cell):
    _, rogue_bus, client_bus = cell
    rogue = Rogue(rogue_bus, {"ok": True, "cell": CELL, "daemon": "ready", "run": {"run_id": "FAKE"}})
    try:
        _wait_routes(client_bus, 1)
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN)
        with pytest.raises(Unverified, match="no reply to control/status could be attributed to the daemon"):
            op.call("status", timeout=3)
        assert op.rejected_replies == 1 and not op.last_reply_verified
        # A forged MAC does not help either.
        rogue._reply = {**rogue._reply, "mac": "0" * 64}
        with pytest.raises(Unverified):
            op.call("pause", timeout=3)
        # Without credentials nothing can be verified: the reply comes back marked as such.
        anon = ControlClient(client_bus.session, CELL)
        assert anon.call("status", timeout=3)["run"] == {"run_id": "FAKE"}
        assert not anon.last_reply_verified
    finally:
        rogue.close()


def test_anonymous_client_refuses_conflicting_responders(cell):
    daemon_bus, rogue_bus, client_bus = cell
    server = _server(daemon_bus, Backend())
    rogue = Rogue(rogue_bus, {"ok": True, "cell": CELL, "daemon": "ready", "run": {"run_id": "FAKE"}})
    try:
        _wait_routes(client_bus, 2)
        anon = ControlClient(client_bus.session, CELL)
        with pytest.raises(Unverified, match="2 different replies .* from more than one responder"):
            anon.call("status", timeout=5)
    finally:
        rogue.close()
        server.close()


class StandIn(Rogue):
    """A rogue that plays the daemon's part of SCRAM with keys of its own (it knows none)."""

    def __init__(self, bus: Bus) -> None:
        from scramp import ScramMechanism

        mech = ScramMechanism("SCRAM-SHA-256")

        def answer(key: str, att: bytes | None) -> dict:
            cred = json.loads(att) if att else {}
            if cred.get("scram") == "client-first":
                server = mech.make_server(lambda name: (b"s" * 16, b"k" * 32, b"k" * 32, 4096))
                server.set_client_first(cred["msg"])
                return {"ok": True, "server_first": server.get_server_first()}
            return {"ok": True, "state": "paused", "who": "stand-in", "scram": "v=" + "A" * 43 + "=", "mac": "0" * 64}

        super().__init__(bus, {})
        self._q.undeclare()

        def handler(query) -> None:
            att = _bytes(query.attachment)
            with self._lock:
                self.seen.append((str(query.key_expr), _bytes(query.payload), att))
            query.reply(query.key_expr, json.dumps(answer(str(query.key_expr), att)))

        self._q = bus.session.declare_queryable(f"remaster/{CELL}/control/**", handler)


def test_with_a_stand_in_answering_too_the_client_completes_with_the_daemon_only(cell):
    daemon_bus, rogue_bus, client_bus = cell
    backend = Backend()
    server = _server(daemon_bus, backend)
    stand_in = StandIn(rogue_bus)
    try:
        _wait_routes(client_bus, 2)
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN)
        assert op.call("pause") == {"ok": True, "state": "paused"} and op.last_reply_verified
        assert backend.paused == 1  # performed once, by the daemon
        assert op.call("status")["who"] == "daemon"
        # What the stand-in collected: client-finals over the daemon's nonces (used up) and, when
        # the client tried the stand-in's server-first before the daemon's, over its own; none
        # gets anything done by the daemon.
        assert stand_in.wait_for(4, timeout=20), stand_in.seen
        finals = [(k, p, a) for k, p, a in stand_in.seen if a and json.loads(a)["scram"] == "client-final"]
        assert len(finals) >= 2
        for key, payload, attachment in finals:
            op_name = key.rsplit("/", 1)[1]
            with pytest.raises(Refused, match="exchange unknown to this daemon"):
                server.dispatch(op_name if op_name != "status" else "pause", payload, attachment, None)
        assert backend.paused == 1
    finally:
        stand_in.close()
        server.close()


def test_an_exchange_that_outlived_its_allowance_is_told_as_such_not_as_a_wrong_token(cell):
    """A busy host: the daemon's clock moves past the exchange's allowance between the client's
    two round trips. The client refuses the daemon's error reply (it carries no proof), and its
    message says what happened and what to do, with the site in the key — not "is the token right?"."""
    daemon_bus, _, client_bus = cell
    now = [0.0]

    def clock() -> float:  # every look at the clock is 11 s later: each exchange has expired when answered
        now[0] += 11.0
        return now[0]

    section = AuthSection.model_validate({
        "anonymous": ["observe"],
        "clients": [{"name": "operator", "scram": CREDS.config(), "allow": ["observe", "read", "control", "motion"]}],
    })
    authorizer = Authorizer(section)
    authorizer.exchanges = auth.ExchangeTable(authorizer._credentials, ttl_s=10.0, clock=clock)
    server = ControlServer(daemon_bus.session, CELL, Backend(), authorizer, site="plant-a")
    try:
        import time

        import zenoh

        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # the routes are up once an anonymous status is answered
            q = client_bus.session.declare_querier(f"remaster/plant-a/{CELL}/control/status",
                                                   target=zenoh.QueryTarget.ALL, timeout=2.0)
            try:
                if list(q.get()):
                    break
            finally:
                q.undeclare()
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN, site="plant-a")
        with pytest.raises(Unverified) as err:
            op.call("pause", timeout=5)
        text = str(err.value)
        assert "outlived its allowance" in text and "try again" in text and "expired" in text
        assert "is the token right" not in text
    finally:
        server.close()


def test_a_reply_from_another_responder_names_the_key_with_the_site(cell):
    _, rogue_bus, client_bus = cell
    q = rogue_bus.session.declare_queryable(
        f"remaster/plant-a/{CELL}/control/**",
        lambda query: query.reply(query.key_expr, json.dumps({"ok": True, "run": None})))
    try:
        import time

        deadline = time.monotonic() + 20
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN, site="plant-a")
        while True:
            try:
                op.call("status", timeout=2)
            except Unverified as exc:
                assert f"remaster/plant-a/{CELL}/control/**" in str(exc) and "is the token right" in str(exc)
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
    finally:
        q.undeclare()


def test_a_responder_too_slow_for_the_timeout_is_no_reply_not_an_unauthenticated_one(cell):
    """Zenoh answers a query that outlives its timeout with an error of its own ("Timeout"): that is
    no reply (is the daemon running? busy?), not a reply to refuse ("is the token right?")."""
    import time

    from acquire.daemon.control import NoReply

    _, rogue_bus, client_bus = cell
    slow = rogue_bus.session.declare_queryable(f"remaster/{CELL}/control/**", lambda query: time.sleep(1.5))
    try:
        deadline = time.monotonic() + 20
        while not list(client_bus.session.get(f"remaster/{CELL}/control/status", timeout=0.3)):
            assert time.monotonic() < deadline, "the slow responder is not reachable"  # (its route is up once Zenoh times it out)
        op = ControlClient(client_bus.session, CELL, client="operator", token=TOKEN)
        with pytest.raises(NoReply, match="no reply to control/status"):
            op.call("status", timeout=0.5)
        assert op.rejected_replies == 0
    finally:
        slow.undeclare()
