"""Control queries of the daemon (``remaster/<cell>/control/<operation>``) and who may send them.

Operations and the permission each needs (``acquire.daemon_config.PERMISSIONS``):

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
=========  ==========  ===========================================================

Two lines of defence. First, Zenoh itself: loopback-only listeners by default; remote
listeners need mTLS or an access-control block (see ``daemon_config``), so the router drops a
query from a subject the ACL does not allow before it reaches us. Second, this module checks
every query in its handler: the query's attachment carries a proof that the sender knows the
token of the client it names (``acquire.control_auth``: the token itself never travels, so a
rogue queryable that also matches the key learns nothing usable), a fresh nonce and a time
stamp (a captured request cannot be replayed). The daemon checks it against the SHA-256 the
configuration holds for that client; a client configured with ``cert_common_names`` must
moreover come over a TLS link whose certificate common name is one of them (the link of the
query's source Zenoh id, as the session sees it). Without a valid proof the query holds only
``auth.anonymous`` (default: observe). Every refusal is logged as a warning naming the
operation, the claimed client and the reason.

Replies are JSON objects. A success is ``{"ok": true, …}``; a failure is an error reply
``{"ok": false, "error": KIND, "message": …}`` with KIND one of ``refused``, ``bad-request``,
``conflict``, ``failed``. A reply to an authenticated request carries ``mac``, an HMAC bound to
that request, and the client believes no reply without a valid one (``Unverified``).
"""

from __future__ import annotations

import hmac
import json
import logging
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Protocol

from acquire import control_auth
from acquire.bus import control_key

if TYPE_CHECKING:  # pydantic and YAML stay out of the thin clients' start-up (acquire status)
    from acquire.daemon_config import AuthSection

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
    """

    def __init__(self, auth: AuthSection, link_subject: Callable[[str], str | None] | None = None) -> None:
        self.auth = auth
        self._link_subject = link_subject or (lambda zid: None)
        self.refusals = 0
        self._lock = threading.Lock()
        self._replays = control_auth.ReplayGuard()

    def identify(self, attachment: bytes | None, source_zid: str | None, *, cell: str = "", op: str = "",
                 payload: bytes | None = None) -> tuple[Identity, str | None, tuple[bytes, bytes] | None]:
        """The sender's identity; if its credentials were rejected, why; and, when they were
        accepted, the (key, auth message) its reply must be signed with."""
        cert_cn = self._link_subject(source_zid) if source_zid else None
        anonymous = frozenset(self.auth.anonymous)
        if not attachment:
            return Identity(None, None, cert_cn, anonymous), None, None
        try:
            req = control_auth.parse_attachment(attachment)
        except control_auth.ProofError as exc:
            return Identity(None, None, cert_cn, anonymous), str(exc), None
        name = req.client
        client = next((c for c in self.auth.clients if c.name == name), None)
        # Check against a dummy key for unknown names too: the answer takes the same time.
        stored = bytes.fromhex(client.token_sha256) if client else b"\0" * 32
        message = control_auth.auth_message(cell, op, name, req.nonce, req.ts, payload)
        if not control_auth.verify_proof(req, stored, message) or client is None:
            return Identity(None, name, cert_cn, anonymous), f"wrong token for client {name!r}", None
        try:
            # Every request's time stamp must be fresh; nonces are remembered (for the skew
            # window) for requests with an effect. Replaying a status query gains nothing: its
            # signed reply is bound to the original request, whose client already has it.
            if OPERATIONS.get(op) == "observe":
                self._replays.check_time(req)
            else:
                self._replays.check(req)
        except control_auth.ProofError as exc:
            return Identity(None, name, cert_cn, anonymous), f"client {name!r}: {exc}", None
        if client.cert_common_names and cert_cn not in client.cert_common_names:
            # The proof holds (the reply is signed), but the token came over the wrong link.
            return Identity(None, name, cert_cn, anonymous), (
                f"client {name!r} must connect over TLS with a certificate CN in "
                f"{client.cert_common_names}; the link's CN is {cert_cn!r}"
            ), (stored, message)
        return Identity(name, name, cert_cn, frozenset(client.allow) | anonymous), None, (stored, message)

    def check(self, operation: str, identity: Identity, credential_problem: str | None) -> None:
        """Raise Refused (and log it) unless ``identity`` may perform ``operation``."""
        need = OPERATIONS[operation]
        if need in identity.permissions:
            return
        reason = f"needs permission {need!r}; {identity.describe()} holds {sorted(identity.permissions)}"
        if credential_problem:
            reason += f" ({credential_problem})"
        with self._lock:
            self.refusals += 1
        log.warning("refused control/%s: %s", operation, reason)
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

    def __init__(self, session, cell: str, backend: ControlBackend, authorizer: Authorizer) -> None:
        self.session = session
        self.cell = cell
        self.backend = backend
        self.authorizer = authorizer
        self.handled = 0
        self._queryables = []
        for op in OPERATIONS:
            self._queryables.append(
                session.declare_queryable(control_key(cell, op), self._make_handler(op))
            )

    def close(self) -> None:
        """Undeclare every queryable (idempotent)."""
        while self._queryables:
            q = self._queryables.pop()
            q.undeclare()

    def _make_handler(self, op: str) -> Callable:
        def handler(query) -> None:
            self._handle(op, query)

        return handler

    def _handle(self, op: str, query) -> None:
        """Answer one query, signed when its sender was authenticated; never raises into Zenoh's thread."""
        self.handled += 1
        key = None
        try:
            payload = _payload_bytes(query.payload)
            reply, key = self.dispatch(op, payload, _payload_bytes(query.attachment), _zid_hex(query.source_info))
            query.reply(query.key_expr, _signed({"ok": True, **reply}, key))
        except ControlError as exc:
            key = getattr(exc, "reply_key", None)
            query.reply_err(_signed({"ok": False, "error": exc.kind, "message": str(exc)}, key))
        except Exception as exc:  # noqa: BLE001 - a bug must become an error reply, never a hang
            log.exception("control/%s failed", op)
            query.reply_err(_signed({"ok": False, "error": "failed", "message": f"{type(exc).__name__}: {exc}"}, key))

    def dispatch(self, op: str, payload: bytes | None, attachment: bytes | None,
                 source_zid: str | None) -> tuple[dict, tuple[bytes, bytes] | None]:
        """Authorise and perform ``op``; returns the reply body and the key to sign it with (None
        for an unauthenticated sender), or raises ControlError (``exc.reply_key`` set likewise)."""
        if op not in OPERATIONS:
            raise BadRequest(f"unknown operation {op!r}; allowed: {', '.join(OPERATIONS)}")
        for what, data in (("payload", payload), ("attachment", attachment)):
            if data is not None and len(data) > MAX_REQUEST_BYTES:
                log.warning("refused control/%s: %s of %d bytes (limit %d)", op, what, len(data), MAX_REQUEST_BYTES)
                raise BadRequest(f"{what} of {len(data)} bytes is too large (limit {MAX_REQUEST_BYTES})")
        identity, problem, key = self.authorizer.identify(attachment, source_zid, cell=self.cell, op=op,
                                                          payload=payload)
        try:
            return self._perform(op, identity, problem, payload), key
        except ControlError as exc:
            exc.reply_key = key
            raise

    def _perform(self, op: str, identity: Identity, problem: str | None, payload: bytes | None) -> dict:
        self.authorizer.check(op, identity, problem)
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
        return b.abort(_opt_str(request, "reason") or f"aborted by {identity.describe()}")


def _signed(body: dict, key: tuple[bytes, bytes] | None) -> str:
    """``body`` as JSON, with its MAC when the request was authenticated."""
    if key is not None:
        body = {**body, "mac": control_auth.reply_mac(key[0], key[1], body)}
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
    except (UnicodeDecodeError, ValueError) as exc:
        raise BadRequest(f"request payload is not JSON: {exc}") from exc
    if not isinstance(req, dict):
        raise BadRequest(f"request payload must be a JSON object, given {type(req).__name__}")
    return req


def _opt_str(req: dict, name: str) -> str | None:
    value = req.get(name)
    if value is not None and not isinstance(value, str):
        raise BadRequest(f"{name} must be a string, given {value!r}")
    return value


class ControlClient:
    """A thin client of the control queries over an open Zenoh session.

    client / token: the credentials to prove (None: anonymous). The token never leaves this
    object: each request carries a one-time proof of it (``acquire.control_auth``), and only a
    reply signed for that request is believed. An anonymous client cannot authenticate replies;
    ``last_reply_verified`` says whether the last reply was.
    """

    def __init__(self, session, cell: str, *, client: str | None = None, token: str | None = None) -> None:
        if (client is None) != (token is None):
            raise ValueError("give both client and token, or neither")
        self.session = session
        self.cell = cell
        self._client = client
        self._token = token
        self.last_reply_verified = False
        #: Replies refused so far because they could not be attributed to the daemon.
        self.rejected_replies = 0

    def call(self, op: str, request: dict[str, Any] | None = None, *, timeout: float = 10.0) -> dict:
        """Send ``op`` and return the daemon's reply body; raise the matching ControlError on an
        error reply, Unverified when no reply can be attributed to the daemon, and NoReply when
        nothing answers within ``timeout`` seconds."""
        import zenoh  # a thin client needs nothing else of the daemon

        if op not in OPERATIONS:
            raise ValueError(f"unknown operation {op!r}; allowed: {', '.join(OPERATIONS)}")
        payload = json.dumps(request).encode() if request else None
        kwargs: dict[str, Any] = {}
        if payload:
            kwargs["payload"] = payload
        key = None
        if self._token is not None:
            creds, message = control_auth.make_request(self._token, self._client, self.cell, op, payload)
            kwargs["attachment"] = creds.attachment()
            key = (control_auth.stored_key(self._token), message)
        self.last_reply_verified = False
        # Every responder's reply, unconsolidated: a rogue answering first must not hide the daemon's.
        querier = self.session.declare_querier(control_key(self.cell, op), target=zenoh.QueryTarget.ALL,
                                               consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
        unverified: list[dict] = []
        try:
            # A querier has an entity id; sending it as source info lets the daemon find our link
            # (and its TLS subject). The daemon never trusts it alone: the proof decides.
            kwargs["source_info"] = zenoh.SourceInfo(querier.id, 0)
            for reply in querier.get(**kwargs):
                sample = reply.ok if reply.ok is not None else reply.err
                body = _reply_body(sample.payload.to_bytes())
                if key is not None and body is not None and _mac_ok(body, key):
                    self.last_reply_verified = True
                    return _outcome(body)
                unverified.append(body if body is not None else {"ok": False, "error": "failed",
                                                                 "message": "reply is not a JSON object"})
        finally:
            querier.undeclare()
        if key is None and unverified:
            distinct = {control_auth.canonical(b) for b in unverified}
            if len(distinct) == 1:
                return _outcome(unverified[0])
            self.rejected_replies += len(unverified)
            raise Unverified(f"{len(unverified)} different replies to control/{op} from more than one responder on "
                             f"cell {self.cell!r}; without credentials none can be attributed to the daemon — give "
                             "--client and a token")
        if unverified:
            self.rejected_replies += len(unverified)
            first = unverified[0]
            raise Unverified(
                f"no reply to control/{op} could be attributed to the daemon of cell {self.cell!r} "
                f"({len(unverified)} unsigned or wrongly signed; is the token right? is another process answering "
                f"on remaster/{self.cell}/control/**?); the first said: {first.get('message', first)}")
        raise NoReply(
            f"no reply to control/{op} for cell {self.cell!r} within {timeout:g} s "
            f"(is the daemon running, and are you allowed by its access control?)"
        )


def _reply_body(data: bytes) -> dict | None:
    try:
        body = json.loads(data)
    except (UnicodeDecodeError, ValueError):
        return None
    return body if isinstance(body, dict) else None


def _mac_ok(body: dict, key: tuple[bytes, bytes]) -> bool:
    mac = body.get("mac")
    return isinstance(mac, str) and hmac.compare_digest(mac, control_auth.reply_mac(key[0], key[1], body))


def _outcome(body: dict) -> dict:
    """The reply body of a success (without its MAC); raise the matching ControlError otherwise."""
    body = {k: v for k, v in body.items() if k != "mac"}
    if body.get("ok"):
        return body
    cls = _KINDS.get(body.get("error"), ControlError)
    raise cls(body.get("message", "control query failed"))
