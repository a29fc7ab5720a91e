"""Control queries of the daemon (``remaster/<cell>/control/<operation>``) and who may send them.

Operations and the permission each needs (``acquire.daemon.config.PERMISSIONS``):

=========  ==========  ===========================================================
operation  permission  what it does
=========  ==========  ===========================================================
status     observe     the daemon's and the current run's state (no plan text)
runs       observe     the runs in the state folder
plan       read        the plan text of a run (``{"run_id": …}``; default: current)
pause      control     finish the current configuration, then hold
abort      control     stop safely now (``{"reason": …}``)
start      motion      start a run: ``{"plan": "/path/on/the/cell/pc.yaml"}`` (inside
                       ``plan_dirs``; relative: from the first) or ``{"plan_text": "…"}``
                       (saved in ``<state_dir>/plans/``; its relative paths resolve
                       from there); optional ``{"resume": RUN_ID}``
resume     motion      continue a paused run
confirm    motion      socket calibration: the ball sits in the socket, record now (the
                       run then moves on)
archive-*  archive     the plant's station: ``archive-list`` (finished runs not yet
                       confirmed), ``archive-chunk`` (a file's bytes), ``archive-confirm``
                       (stored: keep no longer pending) — ``acquire.daemon.archive``
=========  ==========  ===========================================================

Operators on the cell PC do not come this way: they use the control socket
(``acquire.daemon.control_socket``), where the kernel authenticates them and ``ControlServer.perform``
acts for them. On Zenoh, two lines of defence. First, Zenoh itself: loopback-only listeners by
default; remote listeners need mTLS or an access-control block (see ``daemon_config``), so the
router drops a query from a subject the ACL does not allow before it reaches us, and it sends
no control query to any session but ours (``daemon_config.control_guard``). Second, this module checks
every query in its handler. An authenticated operation is one SCRAM-SHA-256 exchange
(``acquire.daemon.control_auth``) over two queries on the operation's key: the first's attachment is a
client-first, answered with a server-first carrying a fresh nonce of this daemon instance; the
second carries the client-final (with the payload), and only once its proof verifies does the
daemon act. The token never travels; the operation and payload are bound to the proof; an
exchange is single-use, expires after seconds and is unknown to any other or restarted daemon.
A client configured with ``cert_common_names`` must moreover come over a TLS link whose
certificate common name is one of them (the link of the query's source Zenoh id, as the session
sees it). Without a valid proof the query holds only ``auth.anonymous`` (default: observe).
Every refusal and bad request is logged as one warning line naming the operation, the claimed
client and the reason, rate-limited per source (``acquire.live.logthrottle``), never a traceback.

Replies are JSON objects. A success is ``{"ok": true, …}``; a failure is an error reply
``{"ok": false, "error": KIND, "message": …}`` with KIND one of ``refused``, ``bad-request``,
``conflict``, ``failed``. A reply to an authenticated request carries ``scram`` (the SCRAM
server-final, ``v=ServerSignature``) and ``mac`` (over the body, keyed from that exchange), and
the client believes no reply without both valid (``Unverified``).
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Protocol

from acquire.daemon import control_auth
from acquire.live.bus import control_key, key as bus_key
from acquire.live.logthrottle import Throttle, clip
from acquire.daemon.tokens import check_token

if TYPE_CHECKING:  # pydantic and YAML stay out of the thin clients' start-up (acquire status)
    from acquire.daemon.config import AuthSection

log = logging.getLogger(__name__)

#: Operation → the permission it needs.
OPERATIONS: dict[str, str] = {
    "status": "observe",
    "runs": "observe",
    "plan": "read",
    "pause": "control",
    "abort": "control",
    "start": "motion",
    "resume": "motion",
    "confirm": "motion",
    "archive-list": "archive",
    "archive-chunk": "archive",
    "archive-confirm": "archive",
}

#: Operations that can make the robot move.
MOTION_OPERATIONS = frozenset(op for op, perm in OPERATIONS.items() if perm == "motion")

#: Largest accepted request payload or attachment (bytes): an inline plan fits easily.
MAX_REQUEST_BYTES = 1 << 20


class ControlError(Exception):
    """A control query that failed; ``kind`` is the reply's ``error`` field."""

    kind = "failed"


class Refused(ControlError, PermissionError):
    """The sender may not do this (no or wrong token, missing permission, wrong TLS subject)."""

    kind = "refused"


class BadRequest(ControlError, ValueError):
    """The request is malformed or names something not allowed (e.g. a plan outside plan_dirs)."""

    kind = "bad-request"


class Conflict(ControlError, RuntimeError):
    """The request does not fit the current state (start while a run is active, …)."""

    kind = "conflict"


class NoReply(ControlError, TimeoutError):
    """No daemon answered within the timeout (not running, or a router dropped the query)."""

    kind = "no-reply"


class Unverified(ControlError, PermissionError):
    """No reply could be attributed to the daemon: unsigned or wrongly signed replies only (a
    wrong token, or another process answering on the control keys), or, without credentials,
    different replies from more than one responder."""

    kind = "unverified"


_KINDS = {cls.kind: cls for cls in (ControlError, Refused, BadRequest, Conflict, NoReply)}


@dataclass(frozen=True)
class Identity:
    """Who sent a query, as far as the daemon can tell."""

    client: str | None          # authenticated client name, None for anonymous
    claimed: str | None         # the name the attachment claimed (even if the token was wrong)
    cert_cn: str | None         # TLS certificate common name of the source link, if known
    permissions: frozenset = field(default_factory=frozenset)

    def describe(self) -> str:
        who = self.client or (f"unauthenticated (claimed {self.claimed!r})" if self.claimed else "anonymous")
        return who + (f", TLS CN {self.cert_cn!r}" if self.cert_cn else "")


class Authorizer:
    """Decides what a query may do from its attachment and (when known) its TLS subject.

    link_subject: source Zenoh id (hex str) → TLS certificate CN of that peer's link, or None.
    exchanges: the pending SCRAM exchanges (default: a new table, i.e. a new daemon instance).
    throttle: limits the warnings about what clients send (``acquire.live.logthrottle``).
    """

    def __init__(self, auth: AuthSection, link_subject: Callable[[str], str | None] | None = None, *,
                 exchanges: control_auth.ExchangeTable | None = None, throttle: Throttle | None = None) -> None:
        self.auth = auth
        self._link_subject = link_subject or (lambda zid: None)
        self.refusals = 0
        self._lock = threading.Lock()
        decoy = next((c.scram.iterations for c in auth.clients), control_auth.DEFAULT_ITERATIONS)
        self.exchanges = exchanges or control_auth.ExchangeTable(self._credentials, decoy_iterations=decoy)
        self.throttle = throttle or Throttle()

    def _credentials(self, name: str) -> control_auth.Credentials | None:
        client = next((c for c in self.auth.clients if c.name == name), None)
        return client.scram.credentials() if client else None

    def warn(self, source: str | None, fmt: str, *args: object) -> None:
        """One warning line about what ``source`` sent, unless its rate is exceeded (then counted;
        the next line admitted for it says how many were suppressed)."""
        source = source or "unknown source"
        with self._lock:
            self.refusals += 1
        dropped = self.throttle.admit(source)
        if dropped is None:
            return
        line = clip(fmt % args if args else fmt, 600)
        suffix = f" [{dropped} similar lines from {source} suppressed]" if dropped else ""
        log.warning("%s%s", line, suffix)

    def flush_warnings(self) -> None:
        """Log, per source, the count of warnings the throttle still holds back (at the close: a
        flood that ended quietly is still counted in the log)."""
        for source, n in self.throttle.drain().items():
            log.warning("[%d similar lines from %s suppressed, not logged before the close]", n, source)

    def open_exchange(self, message: str, source: str | None = None) -> str:
        """The server-first answering a SCRAM client-first from ``source`` (ProofError if malformed)."""
        server_first, _ = self.exchanges.first(message, source)
        return server_first

    def identify(self, attachment: bytes | None, source_zid: str | None, *, cell: str = "", op: str = "",
                 payload: bytes | None = None) -> tuple[Identity, str | None, tuple[bytes, str] | None]:
        """The sender's identity; if its credentials were rejected, why; and, when they were
        accepted, the (reply key, server-final) its reply must carry."""
        cert_cn = self._link_subject(source_zid) if source_zid else None
        anonymous = frozenset(self.auth.anonymous)
        if not attachment:
            return Identity(None, None, cert_cn, anonymous), None, None
        try:
            stage, message = control_auth.parse_attachment(attachment)
            if stage != "client-final":
                raise control_auth.ProofError("a SCRAM client-first cannot carry an operation")
            verified = self.exchanges.final(message, cell=cell, op=op, payload=payload)
        except control_auth.ProofError as exc:
            return Identity(None, exc.client, cert_cn, anonymous), clip(exc, 300), None
        name = verified.client
        client = next(c for c in self.auth.clients if c.name == name)
        key = (verified.reply_key, verified.server_final)
        if client.cert_common_names and cert_cn not in client.cert_common_names:
            # The proof holds (the reply is signed), but the token came over the wrong link.
            return Identity(None, name, cert_cn, anonymous), (
                f"client {name!r} must connect over TLS with a certificate CN in "
                f"{client.cert_common_names}; the link's CN is {cert_cn!r}"
            ), key
        return Identity(name, name, cert_cn, frozenset(client.allow) | anonymous), None, key

    def check(self, operation: str, identity: Identity, credential_problem: str | None,
              source: str | None = None) -> None:
        """Raise Refused (and log it, rate-limited per source) unless ``identity`` may perform ``operation``."""
        need = OPERATIONS[operation]
        if need in identity.permissions:
            if credential_problem:  # e.g. a wrong proof for status: answered, unsigned, as anonymous
                self.warn(source, "control/%s answered as %s: credentials refused (%s)", operation,
                          identity.describe(), credential_problem)
            return
        reason = f"needs permission {need!r}; {identity.describe()} holds {sorted(identity.permissions)}"
        if credential_problem:
            reason += f" ({credential_problem})"
        self.warn(source, "refused control/%s: %s", operation, reason)
        raise Refused(f"{operation} refused: {reason}")


class ControlBackend(Protocol):
    """What the control queries act on (the daemon)."""

    def status(self, *, include_plan: bool) -> dict: ...

    def runs(self) -> dict: ...

    def plan(self, run_id: str | None) -> dict: ...

    def start(self, request: dict, identity: Identity) -> dict: ...

    def pause(self) -> dict: ...

    def resume(self) -> dict: ...

    def abort(self, reason: str) -> dict: ...

    def confirm(self) -> dict: ...

    def archive_list(self) -> dict: ...

    def archive_chunk(self, request: dict) -> dict: ...

    def archive_confirm(self, request: dict, identity: Identity) -> dict: ...


def _zid_hex(source_info) -> str | None:
    if source_info is None:
        return None
    try:
        return str(source_info.source_id.zid)
    except AttributeError:
        return None


class ControlServer:
    """Declares one queryable per operation on a Zenoh session and dispatches to ``backend``.

    Declared on the session directly (not through ``Bus.queryable``) because the handler needs
    the query's source info to find the TLS subject of the sender's link.
    """

    def __init__(self, session, cell: str, backend: ControlBackend, authorizer: Authorizer, *,
                 site: str | None = None) -> None:
        self.session = session
        self.cell = cell
        self.site = site
        self.backend = backend
        self.authorizer = authorizer
        self.handled = 0
        self._queryables = []
        for op in OPERATIONS:
            self._queryables.append(
                session.declare_queryable(control_key(cell, op, site), self._make_handler(op))
            )

    def close(self) -> None:
        """Undeclare every queryable (idempotent), then log the count of warnings the throttle
        still holds back, per source: a flood that ended quietly is still counted in the log."""
        while self._queryables:
            q = self._queryables.pop()
            q.undeclare()
        self.authorizer.flush_warnings()

    def _make_handler(self, op: str) -> Callable:
        def handler(query) -> None:
            self._handle(op, query)

        return handler

    def _handle(self, op: str, query) -> None:
        """Answer one query (signed when its sender was authenticated); never raises into
        Zenoh's thread, and what a client sent costs at most one rate-limited log line."""
        self.handled += 1
        key = None
        source = _zid_hex(query.source_info)
        try:
            payload = _payload_bytes(query.payload)
            reply, key = self.dispatch(op, payload, _payload_bytes(query.attachment), source)
            query.reply(query.key_expr, _signed({"ok": True, **reply}, key))
        except ControlError as exc:
            key = getattr(exc, "reply_key", None)
            if isinstance(exc, BadRequest):
                self.authorizer.warn(source, "bad control/%s request from %s: %s", op, source or "unknown source",
                                     clip(exc))
            query.reply_err(_signed({"ok": False, "error": exc.kind, "message": str(exc)}, key))
        except Exception as exc:  # noqa: BLE001 - a bug must become an error reply, never a hang
            # One line (rate-limited); the traceback only at debug level: a client must not be
            # able to fill the log with them.
            self.authorizer.warn(source, "control/%s from %s failed: %s: %s (traceback at debug level)", op,
                                 source or "unknown source", type(exc).__name__, clip(exc))
            log.debug("control/%s failed", op, exc_info=True)
            try:
                query.reply_err(_signed({"ok": False, "error": "failed",
                                         "message": f"{type(exc).__name__}: {clip(exc)}"}, key))
            except Exception:  # noqa: BLE001 - the query may be gone; nothing more to say
                log.debug("control/%s: could not reply", op, exc_info=True)

    def perform(self, op: str, payload: bytes | None, identity: Identity) -> dict:
        """Perform ``op`` for a caller another transport already identified (the control
        socket: the kernel's peer credentials); raises ControlError."""
        if op not in OPERATIONS:
            raise BadRequest(f"unknown operation {clip(op, 40)!r}; allowed: {', '.join(OPERATIONS)}")
        if payload is not None and len(payload) > MAX_REQUEST_BYTES:
            raise BadRequest(f"payload of {len(payload)} bytes is too large (limit {MAX_REQUEST_BYTES})")
        return self._perform(op, identity, None, payload, identity.client)

    def dispatch(self, op: str, payload: bytes | None, attachment: bytes | None,
                 source_zid: str | None) -> tuple[dict, tuple[bytes, str] | None]:
        """Authorise and perform ``op``; returns the reply body and the (key, server-final) to
        sign it with (None for an unauthenticated sender), or raises ControlError
        (``exc.reply_key`` set likewise). A SCRAM client-first is answered with a server-first
        (``{"server_first": …}``) and performs nothing."""
        if op not in OPERATIONS:
            raise BadRequest(f"unknown operation {clip(op, 40)!r}; allowed: {', '.join(OPERATIONS)}")
        for what, data in (("payload", payload), ("attachment", attachment)):
            if data is not None and len(data) > MAX_REQUEST_BYTES:
                raise BadRequest(f"{what} of {len(data)} bytes is too large (limit {MAX_REQUEST_BYTES})")
        first = _client_first(attachment)
        if first is not None:
            try:
                return {"v": control_auth.VERSION, "server_first": self.authorizer.open_exchange(first, source_zid)}, None
            except control_auth.ProofError as exc:
                raise BadRequest(str(exc)) from None
        identity, problem, key = self.authorizer.identify(attachment, source_zid, cell=self.cell, op=op,
                                                          payload=payload)
        try:
            return self._perform(op, identity, problem, payload, source_zid), key
        except ControlError as exc:
            exc.reply_key = key
            raise

    def _perform(self, op: str, identity: Identity, problem: str | None, payload: bytes | None,
                 source: str | None = None) -> dict:
        self.authorizer.check(op, identity, problem, source)
        request = _request(payload)
        log.log(logging.DEBUG if op in ("status", "runs") else logging.INFO, "control/%s from %s", op,
                identity.describe())
        b = self.backend
        if op == "status":
            return b.status(include_plan="read" in identity.permissions)
        if op == "runs":
            return b.runs()
        if op == "plan":
            return b.plan(_opt_str(request, "run_id"))
        if op == "start":
            return b.start(request, identity)
        if op == "pause":
            return b.pause()
        if op == "resume":
            return b.resume()
        if op == "confirm":
            return b.confirm()
        if op == "archive-list":
            return b.archive_list()
        if op == "archive-chunk":
            return b.archive_chunk(request)
        if op == "archive-confirm":
            return b.archive_confirm(request, identity)
        return b.abort(_opt_str(request, "reason") or f"aborted by {identity.describe()}")


def _client_first(attachment: bytes | None) -> str | None:
    """The SCRAM client-first message an attachment carries, else None (also when malformed:
    ``Authorizer.identify`` then says what is wrong)."""
    if not attachment:
        return None
    try:
        stage, message = control_auth.parse_attachment(attachment)
    except control_auth.ProofError:
        return None
    return message if stage == "client-first" else None


def _signed(body: dict, key: tuple[bytes, str] | None) -> str:
    """``body`` as JSON; when the request was authenticated, with the exchange's server-final
    (``scram``) and a MAC of both under the exchange's reply key (``mac``)."""
    if key is not None:
        body = {**body, "scram": key[1]}
        body["mac"] = control_auth.reply_mac(key[0], body)
    return json.dumps(body, default=str)


def _payload_bytes(z) -> bytes | None:
    if z is None:
        return None
    data = z.to_bytes()
    return data or None


def _request(payload: bytes | None) -> dict:
    if not payload:
        return {}
    try:
        req = json.loads(payload.decode())
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise BadRequest(f"request payload is not JSON: {clip(exc, 120)}") from None
    if not isinstance(req, dict):
        raise BadRequest(f"request payload must be a JSON object, given {type(req).__name__}")
    return req


def _opt_str(req: dict, name: str) -> str | None:
    value = req.get(name)
    if value is not None and not isinstance(value, str):
        raise BadRequest(f"{name} must be a string, given {clip(repr(value), 80)}")
    return value


def _unverified_hint(said: str, keys: str) -> str:
    """What to do about replies that could not be attributed to the daemon, from what the first
    one ``said`` (the daemon's ProofError text when it was the daemon refusing our proof)."""
    if "expired" in said:
        return ("the daemon answered, but our login exchange outlived its allowance: the host was busy "
                "between the two round trips; try again")
    if "wrong token" in said:
        return "the daemon refused the token: check the client name and its token file"
    return f"is the token right? is another process answering on {keys}?"


class ControlClient:
    """A thin client of the control queries over an open Zenoh session.

    client / token: the credentials to prove (None: anonymous); a weak token is refused
    (``acquire.daemon.tokens.WeakToken``). The token never leaves this object: each operation is one
    SCRAM-SHA-256 exchange (``acquire.daemon.control_auth``) and only a reply carrying that exchange's
    ServerSignature and MAC is believed. An anonymous client cannot authenticate replies;
    ``last_reply_verified`` says whether the last reply was.
    """

    def __init__(self, session, cell: str, *, client: str | None = None, token: str | None = None,
                 site: str | None = None) -> None:
        if (client is None) != (token is None):
            raise ValueError("give both client and token, or neither")
        if token is not None:
            check_token(token, (client or "", cell))
        self.session = session
        self.cell = cell
        self.site = site
        self._client = client
        self._token = token
        self.last_reply_verified = False
        #: Replies refused so far because they could not be attributed to the daemon.
        self.rejected_replies = 0

    def call(self, op: str, request: dict[str, Any] | None = None, *, timeout: float = 10.0) -> dict:
        """Send ``op`` and return the daemon's reply body; raise the matching ControlError on an
        error reply, Unverified when no reply can be attributed to the daemon, and NoReply when
        nothing answers within ``timeout`` seconds (per round trip; an authenticated operation
        takes two)."""
        if op not in OPERATIONS:
            raise ValueError(f"unknown operation {op!r}; allowed: {', '.join(OPERATIONS)}")
        payload = json.dumps(request).encode() if request else None
        self.last_reply_verified = False
        if self._token is None:
            return self._anonymous(op, payload, timeout)
        exchange = control_auth.ClientExchange(self._token, self._client, self.cell, op, payload)
        unverified: list[dict] = []
        firsts: list[str] = []
        for body in self._get(op, None, exchange.first_attachment(), timeout):
            first = body.get("server_first") if body.get("ok") else None
            if isinstance(first, str):
                if first not in firsts:
                    firsts.append(first)
            else:
                unverified.append(body)
        # Every responder gets its own client-final; only the daemon that issued a server-first
        # can prove itself in its reply. (A stand-in learns a proof over its own nonce: useless.)
        for first in firsts[:control_auth.MAX_RESPONDERS]:
            try:
                responder = exchange.answer(first)
            except control_auth.ProofError as exc:
                unverified.append({"ok": False, "error": "failed", "message": str(exc)})
                continue
            for body in self._get(op, payload, responder.final_attachment(), timeout):
                if responder.verify(body):
                    self.last_reply_verified = True
                    return outcome(body)
                unverified.append(body)
        if unverified:
            self.rejected_replies += len(unverified)
            first = unverified[0]
            said = str(first.get("message", first))
            raise Unverified(
                f"no reply to control/{op} could be attributed to the daemon of cell {self.cell!r} "
                f"({len(unverified)} unauthenticated; {_unverified_hint(said, bus_key(self.cell, 'control', site=self.site) + '/**')}); "
                f"the first said: {said}")
        raise NoReply(
            f"no reply to control/{op} for cell {self.cell!r} within {timeout:g} s "
            f"(is the daemon running, and are you allowed by its access control?)"
        )

    def _anonymous(self, op: str, payload: bytes | None, timeout: float) -> dict:
        bodies = self._get(op, payload, None, timeout)
        if not bodies:
            raise NoReply(
                f"no reply to control/{op} for cell {self.cell!r} within {timeout:g} s "
                f"(is the daemon running, and are you allowed by its access control?)"
            )
        distinct = {control_auth.canonical(b) for b in bodies}
        if len(distinct) == 1:
            return outcome(bodies[0])
        self.rejected_replies += len(bodies)
        raise Unverified(f"{len(bodies)} different replies to control/{op} from more than one responder on "
                         f"cell {self.cell!r}; without credentials none can be attributed to the daemon — give "
                         "--client and a token")

    def _get(self, op: str, payload: bytes | None, attachment: bytes | None, timeout: float) -> list[dict]:
        """Every responder's reply body to one query (unconsolidated: a rogue answering first must
        not hide the daemon's); a reply that is not a JSON object becomes an error body."""
        import zenoh  # a thin client needs nothing else of the daemon

        kwargs: dict[str, Any] = {}
        if payload:
            kwargs["payload"] = payload
        if attachment:
            kwargs["attachment"] = attachment
        querier = self.session.declare_querier(control_key(self.cell, op, self.site), target=zenoh.QueryTarget.ALL,
                                               consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
        bodies: list[dict] = []
        try:
            # A querier has an entity id; sending it as source info lets the daemon find our link
            # (and its TLS subject). The daemon never trusts it alone: the proof decides.
            kwargs["source_info"] = zenoh.SourceInfo(querier.id, 0)
            for reply in querier.get(**kwargs):
                sample = reply.ok if reply.ok is not None else reply.err
                body = _reply_body(sample.payload.to_bytes())
                if body is None and reply.ok is None:
                    continue  # Zenoh's own error (the query's timeout), not a responder's: no reply
                bodies.append(body if body is not None else {"ok": False, "error": "failed",
                                                             "message": "reply is not a JSON object"})
        finally:
            querier.undeclare()
        return bodies


def _reply_body(data: bytes) -> dict | None:
    try:
        body = json.loads(data)
    except (UnicodeDecodeError, ValueError):
        return None
    return body if isinstance(body, dict) else None


def outcome(body: dict) -> dict:
    """The reply body of a success (without its MAC); raise the matching ControlError otherwise."""
    body = {k: v for k, v in body.items() if k not in ("mac", "scram")}
    if body.get("ok"):
        return body
    cls = _KINDS.get(body.get("error"), ControlError)
    raise cls(body.get("message", "control query failed"))
