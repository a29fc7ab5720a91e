"""Authentication of control queries: SCRAM-SHA-256 (RFC 5802, RFC 7677) with ``scramp``.

Why SCRAM, and not Zenoh's mutual TLS alone: Zenoh delivers a query to *every* queryable whose
key expression matches, so any process on the bus that declares ``remaster/<cell>/control/**``
receives what a client sends and may answer. mTLS with a pinned daemon certificate and Zenoh's
access control fix that where TLS is configured — and stay recommended for a network listener
(``daemon_config``; a client with ``cert_common_names`` must come over such a link) — but not
on loopback, the default, where every local account can reach the router. SCRAM is a reviewed
standard (the SASL mechanism of PostgreSQL, MongoDB, XMPP, Kafka), runs over any transport with
nothing to install, never sends the token, and makes *both* sides prove themselves. The daemon's
side is ``scramp``'s server unchanged; the client uses ``scramp`` for its client-first and to parse
and check each server-first, and computes its client-final with RFC 5802 §3's formula from keys it
caches (§5.1) — the same bytes ``scramp``'s client sends (``tests/acquire/test_control_auth.py``
compares them). Nothing here is a cipher, a proof or a message of our own.

One operation is one exchange of two query round trips on ``remaster/<cell>/control/<op>``:

1. client-first (attachment) → server-first. The client nonce is 24 random characters plus
   ``.`` and the SHA-256 of (protocol version, cell, operation, payload): the operation and its
   payload are part of the SCRAM AuthMessage, so the ClientProof covers them. The daemon
   answers with the client's salt and iteration count and a server nonce of its own: this
   daemon instance's random id (drawn at start-up) between ``@`` and ``.``, and 24 random characters. It keeps
   the exchange pending for ``EXCHANGE_TTL_S`` seconds (at most ``MAX_PENDING_PER_SOURCE`` per
   source and ``MAX_PENDING`` at once).
2. client-final (attachment, with the payload) → the reply. The daemon takes the pending
   exchange out of its table (single use: a second client-final with the same nonce finds
   nothing), checks that the operation and payload hash to what the client nonce says, and
   verifies the ClientProof with ``scramp``. Only then does it act. Its reply carries the
   server-final (``v=ServerSignature``) and ``mac``: HMAC-SHA-256 of the canonical reply body
   under ``HMAC(ServerKey, "remaster-control reply" ‖ AuthMessage)``. The client believes a
   reply only after ``scramp`` verified the ServerSignature and the MAC checks: the daemon has
   proved itself before the client acts on anything.

Hence nothing captured can be used again: a client-final names a server nonce that only the
daemon instance that issued it holds pending, for a few seconds, once (a restarted daemon has a
new id and an empty table; another daemon never issued it). A stand-in answering while the
daemon is down gets a ClientProof over *its* nonce, worthless to the real daemon; its reply
cannot carry a valid ServerSignature, so the client reports it (exit 3) and does nothing.

What the daemon's configuration holds per client is what an RFC 5802 server stores: salt,
iteration count (≥ ``MIN_ITERATIONS``), StoredKey = H(ClientKey) and ServerKey. Guessing the
token offline from a captured exchange costs one PBKDF2 of ``iterations`` rounds per candidate,
and tokens are 256 random bits (``acquire.daemon.tokens``). Per RFC 5802 §9, whoever reads
StoredKey and ServerKey can impersonate the *daemon* to clients (compute ServerSignature and
reply MACs) but cannot log in as a client — unless they also see one client-final message or
get a client to talk to them, which reveals ClientKey. Hence: the daemon's router forwards no
control query to any other session (``daemon_config.control_guard``: nobody but the daemon sees a
client-final, whatever it declares), remote clients come over TLS with the daemon's certificate
pinned (a stand-in cannot answer them), local operators use the control socket, which carries no
secret at all (``acquire.daemon.control_socket``), and the configuration is readable by root and the
daemon's group only (``daemon_config.load_daemon_config`` refuses a file others may read).

Anonymous queries (no attachment) keep observe-only access; their replies cannot be
authenticated and the client says so.

The client computes PBKDF2 once per process and (salt, iterations) and keeps ClientKey and
ServerKey in memory (``client_keys``; RFC 5802 §5.1): a station pulling a run chunk by chunk
pays ~0.7 s (600 000 iterations) for its first exchange with a daemon and ~1 ms for each
later one (``tests/bench/bench_control_auth.py``), with fresh nonces and a proof every time.

Limits, by design: an exchange lives ``EXCHANGE_TTL_S`` = 10 s because the client may compute
PBKDF2 between the two round trips — ~0.7 s at 600 000 iterations on an idle cell PC, several
seconds on a loaded one. Whoever can reach the control keys can still delay SCRAM clients: flood
client-firsts (bounded per source: a flood from one source id evicts only its own exchanges; one
that forges a new source id for each query shares ``MAX_PENDING`` with everyone — the operators'
abort goes over the control socket, which holds no such table), or
answer as a stand-in with server-firsts the client then spends up to ``MAX_RESPONDERS`` PBKDF2s
of at most ``MAX_CLIENT_ITERATIONS`` on. Neither makes anything happen that the operator did
not ask for, nor lets the client report a success the daemon did not sign. (Without the
router's guard — a daemon that is a peer of a plant router it does not run — a client-final is
delivered to every matching queryable there; a process that races it to the daemon makes it
perform what the client asked, once, and the client's own copy is refused as used, exit 3.)
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

from scramp import ScramClient, ScramException, ScramMechanism

from acquire.daemon.tokens import check_token

#: Protocol tag; bumping it makes old and new peers refuse each other with a clear message.
VERSION = 3

MECHANISM = "SCRAM-SHA-256"

#: Fewest PBKDF2 iterations a configuration may hold (RFC 7677's minimum).
MIN_ITERATIONS = 4096

#: What ``acquire token new`` uses (OWASP 2023 for PBKDF2-HMAC-SHA256): ~0.7 s per PBKDF2 here.
DEFAULT_ITERATIONS = 600_000

#: Most iterations a client computes for a server-first (a stand-in cannot make it spin longer).
MAX_CLIENT_ITERATIONS = 2_000_000

#: Seconds an exchange stays pending after its server-first.
EXCHANGE_TTL_S = 10.0

#: Most exchanges pending at once; beyond, the oldest of the source holding the most is dropped.
MAX_PENDING = 256

#: Most exchanges pending at once per source (the query's source Zenoh id); beyond, that
#: source's oldest is dropped — a flood from one source never evicts another's exchange.
MAX_PENDING_PER_SOURCE = 8

#: Most responders a client completes an exchange with, per operation.
MAX_RESPONDERS = 4

_REPLY_LABEL = b"remaster-control reply\n"


class ProofError(ValueError):
    """A request whose credentials do not prove the claimed client (text says why; ``client``:
    the name it claimed, when known)."""

    def __init__(self, message: str, client: str | None = None) -> None:
        super().__init__(message)
        self.client = client


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


@dataclass(frozen=True)
class Credentials:
    """What the daemon stores per client (RFC 5802 §3): salt (≥ 12 bytes), PBKDF2 iterations,
    StoredKey and ServerKey (32 bytes each)."""

    salt: bytes
    iterations: int
    stored_key: bytes
    server_key: bytes

    def config(self) -> dict:
        """The ``scram`` mapping of a client in the daemon configuration (base64 fields)."""
        return {"salt": _b64(self.salt), "iterations": self.iterations, "stored_key": _b64(self.stored_key),
                "server_key": _b64(self.server_key)}


def derive_credentials(token: str, iterations: int = DEFAULT_ITERATIONS, salt: bytes | None = None) -> Credentials:
    """The daemon-side credentials of ``token`` with a fresh 16-byte salt (or ``salt``)."""
    check_token(token)
    if iterations < MIN_ITERATIONS:
        raise ValueError(f"iterations must be ≥ {MIN_ITERATIONS}, given {iterations}")
    salt = secrets.token_bytes(16) if salt is None else salt
    s, stored, server, i = ScramMechanism(MECHANISM).make_auth_info(token, iteration_count=iterations, salt=salt)
    return Credentials(s, i, stored, server)


def request_digest(cell: str, op: str, payload: bytes | None) -> str:
    """Hex SHA-256 of what one operation asks: protocol version, cell, operation and payload."""
    head = f"remaster-control\n{VERSION}\n{cell}\n{op}\n".encode()
    return hashlib.sha256(head + (payload or b"")).hexdigest()


def auth_message(client_first_bare: str, server_first: str, client_final: str) -> bytes:
    """RFC 5802's AuthMessage: client-first-bare, server-first, client-final-without-proof."""
    without_proof = client_final.rsplit(",p=", 1)[0]
    return ",".join((client_first_bare, server_first, without_proof)).encode()


def reply_key(server_key: bytes, message: bytes) -> bytes:
    """The key of one exchange's reply MAC: ``HMAC(ServerKey, label ‖ AuthMessage)``."""
    return hmac.new(server_key, _REPLY_LABEL + message, hashlib.sha256).digest()


def canonical(body: dict) -> bytes:
    """The bytes of a reply body that its MAC covers: the body as its receiver parses it (keys
    as strings, other objects as ``str``), without ``mac``, with sorted keys and no spaces."""
    parsed = json.loads(json.dumps({k: v for k, v in body.items() if k != "mac"}, default=str))
    return json.dumps(parsed, sort_keys=True, separators=(",", ":")).encode()


def reply_mac(key: bytes, body: dict) -> str:
    """Hex HMAC-SHA-256 of ``canonical(body)`` under ``key``."""
    return hmac.new(key, canonical(body), hashlib.sha256).hexdigest()


def attachment(stage: str, message: str) -> bytes:
    """A query attachment carrying one SCRAM message (``stage``: client-first or client-final)."""
    return json.dumps({"v": VERSION, "scram": stage, "msg": message}).encode()


def parse_attachment(data: bytes) -> tuple[str, str]:
    """(stage, SCRAM message) of a query attachment; ProofError when it is not one of ours."""
    try:
        cred = json.loads(bytes(data).decode())
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ProofError(f"attachment is not JSON ({str(exc)[:80]})") from None
    if not isinstance(cred, dict):
        raise ProofError("attachment is not a JSON object")
    if "token" in cred:
        raise ProofError("the client sent its token in clear (a client older than control protocol "
                         f"v{VERSION}); upgrade it — the token should now be considered exposed")
    if cred.get("v") != VERSION:
        raise ProofError(f"control protocol v{str(cred.get('v'))[:20]}; this daemon speaks v{VERSION} "
                         "(SCRAM-SHA-256): upgrade the client")
    stage, msg = cred.get("scram"), cred.get("msg")
    if stage not in ("client-first", "client-final") or not isinstance(msg, str) or not 0 < len(msg) <= 4096:
        raise ProofError("attachment lacks a SCRAM client-first or client-final message")
    return stage, msg


# ------------------------------------------------------------------------------------ client
#: Most (token, salt, iterations) whose keys a client process keeps (a stand-in's odd salts
#: cannot make the cache grow without bound).
KEY_CACHE_SIZE = 1024

_client_keys: "OrderedDict[tuple[bytes, bytes, int], tuple[bytes, bytes]]" = OrderedDict()
_client_keys_lock = threading.Lock()


def client_keys(token: str, salt: bytes, iterations: int) -> tuple[bytes, bytes]:
    """(ClientKey, ServerKey) of ``token`` for ``salt`` and ``iterations``: one PBKDF2 per
    process and (salt, iterations), then from memory.

    RFC 5802 §5.1 allows exactly this ("the client can store the SaltedPassword, ClientKey,
    ServerKey for the given salt and iteration count to avoid recomputing them"): every exchange
    still has fresh nonces on both sides and a proof over its own AuthMessage, so nothing is
    replayable; what is saved is only the PBKDF2 (~0.7 s at 600 000 iterations). The keys live
    in this process's memory beside the token they derive from — no new exposure.
    """
    tag = (hashlib.sha256(token.encode()).digest(), bytes(salt), int(iterations))
    with _client_keys_lock:
        keys = _client_keys.get(tag)
        if keys is not None:
            _client_keys.move_to_end(tag)
            return keys
    salted = hashlib.pbkdf2_hmac("sha256", token.encode(), bytes(salt), int(iterations))   # Hi() of RFC 5802
    keys = (hmac.new(salted, b"Client Key", hashlib.sha256).digest(),
            hmac.new(salted, b"Server Key", hashlib.sha256).digest())
    with _client_keys_lock:
        _client_keys[tag] = keys
        while len(_client_keys) > KEY_CACHE_SIZE:
            _client_keys.popitem(last=False)
    return keys


def _client_final(client_key: bytes, server_key: bytes, bare_first: str, server_first: str,
                  nonce: str) -> tuple[str, bytes, bytes]:
    """(client-final, ServerSignature, AuthMessage) of RFC 5802 §3 from cached keys, without
    channel binding (GS2 header ``n,,`` → ``c=biws``): ClientProof = ClientKey XOR
    HMAC(H(ClientKey), AuthMessage); ServerSignature = HMAC(ServerKey, AuthMessage). The same
    bytes ``scramp``'s client computes (tests/acquire/test_control_auth.py checks it)."""
    without_proof = f"c={_b64(b'n,,')},r={nonce}"
    message = ",".join((bare_first, server_first, without_proof)).encode()
    stored_key = hashlib.sha256(client_key).digest()
    signature = hmac.new(stored_key, message, hashlib.sha256).digest()
    proof = bytes(a ^ b for a, b in zip(client_key, signature))
    server_signature = hmac.new(server_key, message, hashlib.sha256).digest()
    return f"{without_proof},p={_b64(proof)}", server_signature, message


class ClientExchange:
    """The client's side of one operation's exchange (with one or more responders).

    ``scramp`` builds the client-first and parses and checks each server-first (our nonce
    echoed, salt, iteration count); the client-final is computed from the keys cached per
    (salt, iterations) (``client_keys``), so the second and later exchanges of a process with
    a daemon cost HMACs only."""

    def __init__(self, token: str, client: str, cell: str, op: str, payload: bytes | None) -> None:
        self._token = check_token(token, (client, cell))
        self._client = client
        self.nonce = f"{secrets.token_urlsafe(18)}.{request_digest(cell, op, payload)}"
        self._first = ScramClient([MECHANISM], client, token, c_nonce=self.nonce).get_client_first()

    def first_attachment(self) -> bytes:
        return attachment("client-first", self._first)

    def answer(self, server_first: str) -> "ClientResponder":
        """The exchange with the responder that sent ``server_first``; ProofError if it is not
        a server-first for our nonce with an iteration count we accept."""
        scram = ScramClient([MECHANISM], self._client, self._token, c_nonce=self.nonce)
        bare_first = scram.get_client_first().split(",", 2)[2]
        try:
            scram.set_server_first(server_first)
        except ScramException as exc:
            raise ProofError(f"not a server-first for this exchange ({exc})") from None
        iterations = int(scram.iterations)
        if iterations > MAX_CLIENT_ITERATIONS:
            raise ProofError(f"server-first asks {iterations} iterations (this client computes at most "
                             f"{MAX_CLIENT_ITERATIONS})")
        client_key, server_key = client_keys(self._token, bytes(scram.salt), iterations)
        final, server_signature, message = _client_final(client_key, server_key, bare_first, server_first,
                                                         str(scram.nonce))
        return ClientResponder(server_signature, final, reply_key(server_key, message))


class ClientResponder:
    """One responder's exchange after our client-final: builds it, then judges its reply."""

    def __init__(self, server_signature: bytes, client_final: str, key: bytes) -> None:
        self._server_signature = server_signature
        self.client_final = client_final
        self._key = key

    def final_attachment(self) -> bytes:
        return attachment("client-final", self.client_final)

    def verify(self, body: dict) -> bool:
        """True when ``body`` carries this exchange's ServerSignature (server-final ``v=…``,
        RFC 5802 §7) and a MAC of its content under the exchange's reply key."""
        final, mac = body.get("scram"), body.get("mac")
        if not isinstance(final, str) or not isinstance(mac, str) or not final.startswith("v="):
            return False
        try:
            signature = base64.b64decode(final[2:], validate=True)
        except ValueError:
            return False
        if not hmac.compare_digest(signature, self._server_signature):
            return False
        return hmac.compare_digest(mac, reply_mac(self._key, body))


# ------------------------------------------------------------------------------------ daemon
@dataclass
class _Pending:
    scram: object          # scramp.ScramServer after get_server_first
    client: str
    client_nonce: str
    known: bool            # a configured client (False: decoy credentials, the proof fails)
    deadline: float
    source: str            # who sent the client-first (source Zenoh id, or "unknown")


@dataclass(frozen=True)
class Verified:
    """A client-final the daemon verified: who, and the key its reply must be signed with."""

    client: str
    server_final: str
    reply_key: bytes


class ExchangeTable:
    """The daemon's side: pending exchanges of this daemon instance (thread-safe).

    lookup: client name → its Credentials, or None for an unknown name (which then gets decoy
    credentials: a salt stable per name and ``decoy_iterations``, so the server-first does not
    tell which names exist; give the configured clients' count).
    """

    def __init__(self, lookup: Callable[[str], Credentials | None], *, ttl_s: float = EXCHANGE_TTL_S,
                 max_pending: int = MAX_PENDING, clock: Callable[[], float] = time.monotonic,
                 decoy_iterations: int = DEFAULT_ITERATIONS) -> None:
        self._lookup = lookup
        self.decoy_iterations = decoy_iterations
        self.ttl_s = ttl_s
        self.max_pending = max_pending
        self._clock = clock
        #: This daemon instance's id: the head of every server nonce it issues.
        self.instance = secrets.token_hex(8)
        self._decoy_secret = secrets.token_bytes(32)
        self._pending: dict[str, _Pending] = {}  # nonce → exchange, oldest first
        self._per_source: dict[str, int] = {}     # source → its pending exchanges
        self._lock = threading.Lock()
        self._mech = ScramMechanism(MECHANISM)

    def _credentials(self, name: str) -> tuple[tuple, bool]:
        creds = self._lookup(name)
        if creds is not None:
            return (creds.salt, creds.stored_key, creds.server_key, creds.iterations), True
        salt = hmac.new(self._decoy_secret, name.encode(), hashlib.sha256).digest()[:16]
        return (salt, secrets.token_bytes(32), secrets.token_bytes(32), self.decoy_iterations), False

    def first(self, client_first: str, source: str | None = None) -> tuple[str, str]:
        """(server-first, client name) for a client-first from ``source``; the exchange is then
        pending (bounded per source: ``MAX_PENDING_PER_SOURCE``, and in all: ``max_pending``)."""
        found: dict = {}

        def auth_fn(name: str):
            found["name"] = name
            found["info"], found["known"] = self._credentials(name)
            return found["info"]

        scram = self._mech.make_server(auth_fn, s_nonce=f"@{self.instance}.{secrets.token_urlsafe(18)}")
        try:
            scram.set_client_first(client_first)
            server_first = scram.get_server_first()
        except ScramException as exc:
            raise ProofError(f"malformed SCRAM client-first ({str(exc)[:120]})") from None
        nonce = str(scram.nonce)
        c_nonce = nonce[: -len(str(scram.s_nonce))]
        now = self._clock()
        source = source or "unknown"
        with self._lock:
            self._expire(now)
            if self._per_source.get(source, 0) >= MAX_PENDING_PER_SOURCE:
                self._drop_oldest(source)
            if len(self._pending) >= self.max_pending:
                self._drop_oldest(max(self._per_source, key=self._per_source.__getitem__))
            self._pending[nonce] = _Pending(scram, found["name"], c_nonce, found["known"], now + self.ttl_s, source)
            self._per_source[source] = self._per_source.get(source, 0) + 1
        return server_first, found["name"]

    def _take(self, nonce: str) -> _Pending | None:
        """Remove and return the exchange of ``nonce`` (None if unknown); lock held."""
        pending = self._pending.pop(nonce, None)
        if pending is not None:
            left = self._per_source[pending.source] - 1
            if left:
                self._per_source[pending.source] = left
            else:
                del self._per_source[pending.source]
        return pending

    def _drop_oldest(self, source: str) -> None:
        self._take(next(n for n, p in self._pending.items() if p.source == source))

    def _expire(self, now: float) -> None:
        for nonce in [n for n, p in self._pending.items() if p.deadline < now]:
            self._take(nonce)

    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    def final(self, client_final: str, *, cell: str, op: str, payload: bytes | None) -> Verified:
        """Verify a client-final for ``op`` with ``payload``; the exchange is used up either way.

        Raises ProofError naming the client (when known) and why.
        """
        nonce = next((part[2:] for part in client_final.split(",") if part.startswith("r=")), None)
        if not nonce:
            raise ProofError("malformed SCRAM client-final (no nonce)")
        now = self._clock()
        with self._lock:
            pending = self._take(nonce)
            self._expire(now)
        if pending is None:
            mine = f"@{self.instance}." in nonce
            raise ProofError("SCRAM exchange unknown to this daemon: " + (
                "used before, or expired (replayed?)" if mine else
                "not issued by this daemon instance (captured before a restart, sent to another responder, or "
                "replayed)"))
        if pending.deadline < now:
            raise ProofError(f"client {pending.client!r}: SCRAM exchange expired (older than {self.ttl_s:g} s)",
                             pending.client)
        if not pending.client_nonce.endswith("." + request_digest(cell, op, payload)):
            raise ProofError(f"client {pending.client!r}: the exchange was opened for another operation or payload",
                             pending.client)
        try:
            pending.scram.set_client_final(client_final)
            server_final = pending.scram.get_server_final()
        except ScramException as exc:
            raise ProofError(f"wrong token for client {pending.client!r} ({str(exc)[:80]})", pending.client) from None
        if not pending.known:
            raise ProofError(f"wrong token for client {pending.client!r}", pending.client)
        message = auth_message(pending.scram.client_first_bare, pending.scram.server_first, client_final)
        return Verified(pending.client, server_final, reply_key(pending.scram.server_key, message))
