"""Proofs for control queries: the token never leaves the client, and replies are attributable.

Why this design (and not the token in the attachment, nor mutual TLS alone): Zenoh delivers a
query to *every* queryable whose key expression matches, so any process on the bus that declares
``remaster/<cell>/control/**`` receives what a client sends and may answer first. mTLS with a
pinned daemon certificate would fix that only where TLS is configured (not on loopback, the
default). A proof in the style of SCRAM (RFC 5802), over one round trip, works on every
transport with nothing to install:

- The daemon's configuration keeps only ``stored = SHA-256(token)`` per client (as before).
- The client sends ``proof = token XOR mask``, where ``mask`` is expanded from
  ``HMAC(stored, "client" ‖ auth_message)`` and ``auth_message`` binds the protocol version, the
  cell, the operation, the client name, a fresh random nonce, a time stamp and the SHA-256 of
  the request payload. Who does not know ``stored`` learns nothing from the proof; the daemon
  computes the mask, recovers the token and checks its SHA-256 against ``stored`` (constant time).
  A stolen daemon configuration is still not a client credential.
- The daemon refuses a time stamp more than ``MAX_SKEW_S`` from its clock and a nonce it has
  already seen (a rogue queryable that captured a request cannot replay it).
- Every reply carries ``mac = HMAC(stored, "daemon" ‖ auth_message ‖ body)``. A client believes
  only a reply whose MAC it can check: a rogue that does not know ``stored`` cannot forge one,
  and a reply to another request cannot be passed off for this one.

An anonymous client (no token) has no shared secret: its replies cannot be authenticated, which
the client reports (``ControlClient.last_reply_verified``) and the CLI prints.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import threading
import time
from dataclasses import dataclass

#: Protocol tag; bumping it makes old and new peers refuse each other with a clear message.
VERSION = 2

#: Largest difference (s) between a request's time stamp and the daemon's clock.
MAX_SKEW_S = 60.0

#: Longest accepted token (bytes).
MAX_TOKEN_BYTES = 4096


def stored_key(token: str) -> bytes:
    """``SHA-256(token)``: the 32 bytes the daemon's configuration holds (as hex) per client."""
    return hashlib.sha256(token.encode()).digest()


def auth_message(cell: str, op: str, client: str, nonce: str, ts: str, payload: bytes | None) -> bytes:
    """The bytes a proof and a reply MAC are bound to."""
    digest = hashlib.sha256(payload or b"").hexdigest()
    return "\n".join(("remaster-control", str(VERSION), cell, op, client, nonce, ts, digest)).encode()


def _mask(stored: bytes, message: bytes, n: int) -> bytes:
    """``n`` bytes expanded from ``HMAC(stored, "client" ‖ message)`` (HKDF-expand style)."""
    prk = hmac.new(stored, b"client\n" + message, hashlib.sha256).digest()
    out, block, counter = b"", b"", 1
    while len(out) < n:
        block = hmac.new(prk, block + bytes([counter & 0xFF]), hashlib.sha256).digest()
        out += block
        counter += 1
    return out[:n]


def _xor(a: bytes, b: bytes) -> bytes:
    return bytes(x ^ y for x, y in zip(a, b))


def canonical(body: dict) -> bytes:
    """The bytes of a reply body that its MAC covers: the body as its receiver parses it (keys
    as strings, other objects as ``str``), without ``mac``, with sorted keys and no spaces."""
    parsed = json.loads(json.dumps({k: v for k, v in body.items() if k != "mac"}, default=str))
    return json.dumps(parsed, sort_keys=True, separators=(",", ":")).encode()


def reply_mac(stored: bytes, message: bytes, body: dict) -> str:
    """Hex ``HMAC(stored, "daemon" ‖ message ‖ canonical(body))``."""
    return hmac.new(stored, b"daemon\n" + message + b"\n" + canonical(body), hashlib.sha256).hexdigest()


@dataclass(frozen=True)
class Request:
    """One request's credentials as sent in the query attachment."""

    client: str
    nonce: str
    ts: str
    proof: str

    def attachment(self) -> bytes:
        return json.dumps({"v": VERSION, "client": self.client, "nonce": self.nonce, "ts": self.ts,
                           "proof": self.proof}).encode()


def make_request(token: str, client: str, cell: str, op: str, payload: bytes | None) -> tuple[Request, bytes]:
    """The client's credentials for one request, and the auth message its reply must be bound to."""
    secret = token.encode()
    if not secret or len(secret) > MAX_TOKEN_BYTES:
        raise ValueError(f"a token must be 1–{MAX_TOKEN_BYTES} bytes, given {len(secret)}")
    nonce = secrets.token_hex(16)
    ts = f"{time.time():.3f}"
    message = auth_message(cell, op, client, nonce, ts, payload)
    proof = _xor(secret, _mask(stored_key(token), message, len(secret))).hex()
    return Request(client, nonce, ts, proof), message


class ProofError(ValueError):
    """A request whose credentials do not prove the claimed client (text says why)."""


def parse_attachment(attachment: bytes) -> Request:
    """The credentials in a query attachment; ProofError when it is not a version-2 proof."""
    try:
        cred = json.loads(bytes(attachment).decode())
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProofError(f"attachment is not JSON ({exc})") from exc
    if not isinstance(cred, dict):
        raise ProofError("attachment is not a JSON object")
    if "token" in cred:
        raise ProofError("the client sent its token in clear (a client older than control protocol "
                         f"v{VERSION}); upgrade it — the token should now be considered exposed")
    if cred.get("v") != VERSION:
        raise ProofError(f"control protocol v{cred.get('v')!r}; this daemon speaks v{VERSION}")
    fields = {k: cred.get(k) for k in ("client", "nonce", "ts", "proof")}
    bad = [k for k, v in fields.items() if not isinstance(v, str) or not v]
    if bad:
        raise ProofError(f"attachment lacks {', '.join(bad)}")
    return Request(**fields)


class ReplayGuard:
    """Remembers the nonces seen within the skew window (thread-safe)."""

    def __init__(self, max_skew_s: float = MAX_SKEW_S, clock=time.time) -> None:
        self.max_skew_s = max_skew_s
        self._clock = clock
        self._seen: dict[str, float] = {}
        self._lock = threading.Lock()

    def check_time(self, req: Request) -> float:
        """Raise ProofError for a time stamp outside the skew window; returns the clock's now."""
        now = self._clock()
        try:
            ts = float(req.ts)
        except ValueError as exc:
            raise ProofError(f"time stamp {req.ts!r} is not a number") from exc
        if not abs(now - ts) <= self.max_skew_s:
            raise ProofError(f"time stamp is {now - ts:+.0f} s from the daemon's clock (allowed ±{self.max_skew_s:g} s; "
                             "synchronise the clocks)")
        return now

    def check(self, req: Request) -> None:
        """Raise ProofError for a stale time stamp or a nonce seen before; else remember it."""
        now = self.check_time(req)
        with self._lock:
            for nonce, t in list(self._seen.items()):
                if now - t > 2 * self.max_skew_s:
                    del self._seen[nonce]
            if req.nonce in self._seen:
                raise ProofError("replayed request (its nonce was used before)")
            self._seen[req.nonce] = now


def verify_proof(req: Request, stored: bytes, message: bytes) -> bool:
    """True when ``req.proof`` unmasks to a token whose SHA-256 is ``stored`` (constant time)."""
    try:
        proof = bytes.fromhex(req.proof)
    except ValueError:
        return False
    if not 0 < len(proof) <= MAX_TOKEN_BYTES:
        return False
    token = _xor(proof, _mask(stored, message, len(proof)))
    return hmac.compare_digest(hashlib.sha256(token).digest(), stored)
