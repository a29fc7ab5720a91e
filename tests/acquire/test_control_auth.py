"""SCRAM-SHA-256 exchanges of the control channel, without Zenoh: single use, expiry, one
daemon instance, the operation and payload bound, what a config reader and an offline guesser
can and cannot do. The attacker's messages are built here with hashlib/hmac from RFC 5802's
definitions, not with our encoder.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets

import pytest
from pydantic import ValidationError

from acquire.daemon import control_auth as auth
from acquire.daemon.control import ControlClient
from acquire.daemon.config import AuthSection, Client
from acquire.daemon.tokens import WeakToken

CELL = "lab1"
TOKEN = "Zk3-pQ9xT2mV7bN4cR8sW1yL6hJ0fG"
CREDS = auth.derive_credentials(TOKEN, auth.MIN_ITERATIONS)


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _table(clock=None, creds=CREDS) -> auth.ExchangeTable:
    return auth.ExchangeTable(lambda name: creds if name == "operator" else None, decoy_iterations=creds.iterations,
                              **({"clock": clock} if clock else {}))


def _msg(attachment: bytes) -> str:
    return json.loads(attachment)["msg"]


def _exchange(table, op="pause", payload=b'{"x":1}', token=TOKEN, client="operator"):
    """(client exchange, responder, client-final) of one operation against ``table``."""
    ex = auth.ClientExchange(token, client, CELL, op, payload)
    server_first, name = table.first(_msg(ex.first_attachment()))
    assert name == client
    responder = ex.answer(server_first)
    return ex, responder, _msg(responder.final_attachment())


def _signed(verified: auth.Verified, body: dict) -> dict:
    body = {**body, "scram": verified.server_final}
    return {**body, "mac": auth.reply_mac(verified.reply_key, body)}


def test_an_exchange_proves_both_sides_once():
    table = _table()
    _, responder, final = _exchange(table)
    verified = table.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
    assert verified.client == "operator" and verified.server_final.startswith("v=")
    reply = _signed(verified, {"ok": True, "state": "paused"})
    # Another responder's reply to the same client-final, arriving first, changes nothing.
    assert not responder.verify({"ok": True, "scram": "v=" + base64.b64encode(b"x" * 32).decode(), "mac": "0" * 64})
    assert responder.verify(reply)
    assert not responder.verify({**reply, "state": "running"})  # the MAC covers the body
    # Single use: the same client-final again finds no exchange.
    with pytest.raises(auth.ProofError, match="used before, or expired"):
        table.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
    assert table.pending() == 0


def test_an_exchange_expires_within_seconds():
    clock = Clock()
    table = _table(clock)
    _, _, final = _exchange(table)
    clock.t += auth.EXCHANGE_TTL_S + 0.1
    with pytest.raises(auth.ProofError, match="expired"):
        table.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
    assert auth.EXCHANGE_TTL_S <= 10


def test_a_restarted_or_other_daemon_knows_no_exchange_it_did_not_issue():
    first_instance, restarted = _table(), _table()  # same configuration, new instance id
    assert first_instance.instance != restarted.instance
    _, _, final = _exchange(first_instance)
    with pytest.raises(auth.ProofError, match="not issued by this daemon instance"):
        restarted.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
    # The server nonce names the instance that issued it.
    nonce = next(p[2:] for p in final.split(",") if p.startswith("r="))
    assert f"@{first_instance.instance}." in nonce


@pytest.mark.parametrize("cell, op, payload", [(CELL, "start", b'{"x":1}'), (CELL, "pause", b'{"x":2}'),
                                               ("other-cell", "pause", b'{"x":1}'), (CELL, "pause", None)])
def test_the_operation_and_its_payload_are_bound_to_the_proof(cell, op, payload):
    table = _table()
    _, _, final = _exchange(table)
    with pytest.raises(auth.ProofError, match="another operation or payload"):
        table.final(final, cell=cell, op=op, payload=payload)


def test_a_wrong_token_and_an_unknown_name_fail_alike():
    table = _table()
    _, _, final = _exchange(table, token="Wrong-but-strong-token-8a7sd6f5")
    with pytest.raises(auth.ProofError, match="wrong token for client 'operator'"):
        table.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
    # An unknown name gets a server-first like a known one (stable salt, the configured
    # iterations), so the daemon does not tell which names exist; its proof fails.
    firsts = [table.first(_msg(auth.ClientExchange(TOKEN, "nobody", CELL, "pause", None).first_attachment()))[0]
              for _ in range(2)]
    fields = [dict(p.split("=", 1) for p in f.split(",")) for f in firsts]
    assert len({f["s"] for f in fields}) == 1 and fields[0]["s"] != base64.b64encode(CREDS.salt).decode()
    assert {f["i"] for f in fields} == {str(CREDS.iterations)}
    _, _, final = _exchange(table, client="nobody", payload=None)
    with pytest.raises(auth.ProofError, match="wrong token for client 'nobody'"):
        table.final(final, cell=CELL, op="pause", payload=None)


def _h(data: bytes) -> bytes:
    return hashlib.sha256(data).digest()


def _hmac(key: bytes, data: bytes) -> bytes:
    return hmac.new(key, data, hashlib.sha256).digest()


def _xor(a: bytes, b: bytes) -> bytes:
    return bytes(x ^ y for x, y in zip(a, b))


def _attacker_final(table, client_key: bytes) -> str:
    """A client-final built by hand (RFC 5802 §3) with ``client_key`` for a fresh exchange."""
    c_nonce = f"{secrets.token_urlsafe(18)}.{auth.request_digest(CELL, 'start', None)}"
    bare = f"n=operator,r={c_nonce}"
    server_first, _ = table.first("n,," + bare)
    nonce = dict(p.split("=", 1) for p in server_first.split(","))["r"]
    without_proof = f"c=biws,r={nonce}"
    message = f"{bare},{server_first},{without_proof}".encode()
    proof = _xor(client_key, _hmac(_h(client_key), message))
    return f"{without_proof},p={base64.b64encode(proof).decode()}"


def test_a_config_reader_cannot_log_in_but_can_impersonate_the_daemon_as_rfc5802_says():
    table = _table()
    # What a reader of the configuration has: salt, iterations, StoredKey, ServerKey. A proof
    # needs ClientKey (StoredKey = H(ClientKey)); every key it holds, used as ClientKey, fails.
    for guess in (CREDS.stored_key, CREDS.server_key, _hmac(CREDS.server_key, b"Client Key")):
        with pytest.raises(auth.ProofError, match="wrong token for client 'operator'"):
            table.final(_attacker_final(table, guess), cell=CELL, op="start", payload=None)
    # The true ClientKey (what only the token gives) passes: the hand-built messages are right.
    salted = hashlib.pbkdf2_hmac("sha256", TOKEN.encode(), CREDS.salt, CREDS.iterations)
    assert table.final(_attacker_final(table, _hmac(salted, b"Client Key")), cell=CELL, op="start",
                       payload=None).client == "operator"

    # RFC 5802 §9, as systemd/README.md says: with ServerKey a reader can sign replies a client accepts…
    _, responder, final = _exchange(table)
    fields = dict(p.split("=", 1) for p in final.split(","))
    # The AuthMessage, as anyone who saw the client-first, server-first and client-final has it.
    pending = next(iter(table._pending.values()))  # noqa: SLF001
    message = auth.auth_message(pending.scram.client_first_bare, pending.scram.server_first, final)
    forged = auth.Verified("operator", "v=" + base64.b64encode(_hmac(CREDS.server_key, message)).decode(),
                           auth.reply_key(CREDS.server_key, message))
    assert responder.verify(_signed(forged, {"ok": True, "forged": True}))
    # …and with StoredKey and one client-final it sees, it recovers ClientKey: hence the config
    # must be readable by root and the daemon only (daemon_config.check_config_mode).
    client_key = _xor(base64.b64decode(fields["p"]), _hmac(CREDS.stored_key, message))
    assert _h(client_key) == CREDS.stored_key


def test_offline_guessing_costs_one_salted_pbkdf2_of_the_configured_iterations_per_candidate(monkeypatch):
    """A captured exchange and a 1000-word list holding the token: each candidate must go through
    PBKDF2 with the configured salt and iteration count (≥ 4096; 600 000 by default) — plain
    hashing, no salt or fewer iterations never match."""
    table = _table()
    ex, _, final = _exchange(table, op="start", payload=b'{"plan":"p.yaml"}')
    pending = next(iter(table._pending.values()))  # noqa: SLF001 - what an eavesdropper saw on the bus
    bare, server_first = pending.scram.client_first_bare, pending.scram.server_first
    message = auth.auth_message(bare, server_first, final)
    fields = dict(p.split("=", 1) for p in server_first.split(","))
    salt, iterations = base64.b64decode(fields["s"]), int(fields["i"])
    proof = base64.b64decode(dict(p.split("=", 1) for p in final.split(","))["p"])
    words = [secrets.token_urlsafe(20) for _ in range(999)]
    words.insert(300, TOKEN)

    calls: list[tuple[bytes, int]] = []
    real = hashlib.pbkdf2_hmac

    def counted(name, password, salt_, rounds, *args):
        calls.append((salt_, rounds))
        return real(name, password, salt_, rounds, *args)

    monkeypatch.setattr(hashlib, "pbkdf2_hmac", counted)

    def matches(candidate: str, salt_: bytes, rounds: int) -> bool:
        client_key = _hmac(hashlib.pbkdf2_hmac("sha256", candidate.encode(), salt_, rounds), b"Client Key")
        return _xor(client_key, _hmac(_h(client_key), message)) == proof

    found = next(i for i, w in enumerate(words) if matches(w, salt, iterations))
    assert words[found] == TOKEN
    assert len(calls) == found + 1 and set(calls) == {(CREDS.salt, CREDS.iterations)}
    assert iterations == CREDS.iterations >= auth.MIN_ITERATIONS and len(salt) >= 12
    # The salt and the count are both needed: without either the true token does not match.
    assert not matches(TOKEN, b"", iterations) and not matches(TOKEN, salt, 1)
    assert auth.DEFAULT_ITERATIONS >= 600_000


def test_a_stand_in_cannot_make_the_client_spin_or_accept_its_reply():
    ex = auth.ClientExchange(TOKEN, "operator", CELL, "start", None)
    c_nonce = ex.nonce
    salt = base64.b64encode(b"s" * 16).decode()
    with pytest.raises(auth.ProofError, match="computes at most"):
        ex.answer(f"r={c_nonce}rogue,s={salt},i={auth.MAX_CLIENT_ITERATIONS + 1}")
    with pytest.raises(auth.ProofError, match="not a server-first for this exchange"):
        ex.answer(f"r=someone-else,s={salt},i=4096")
    responder = ex.answer(f"r={c_nonce}rogue,s={salt},i=4096")
    assert not responder.verify({"ok": True, "scram": "v=" + base64.b64encode(b"x" * 32).decode(), "mac": "00"})
    assert not responder.verify({"ok": True})


@pytest.mark.parametrize("weak, why", [
    ("dragon2024", "too short"), ("operator-secret-token", "too weak"),
    ("Password1!Password1!Pa", r"too weak: guessable in about 10\^6\.9 tries"),  # issue 32: cracked in 3.2 s
    ("correcthorsebatterystaple", "too weak"), ("remaster-operator-lab1-2026!!", "too weak"),
    ("aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa", "too weak"), ("Ab1Ab1Ab1Ab1Ab1Ab1Ab1Ab1Ab1", "too weak"),
    ("qwertyuiopasdfghjklzxcvbnm1234", "too weak"),
    ("with space but long enough 12345", "spaces"), ("", "no token")])
def test_weak_tokens_are_refused_wherever_a_token_is_accepted(weak, why):
    with pytest.raises(WeakToken, match=why):
        ControlClient(None, CELL, client="operator", token=weak)
    with pytest.raises(WeakToken):
        auth.derive_credentials(weak, auth.MIN_ITERATIONS)


def test_strong_tokens_are_accepted():
    from acquire.daemon.tokens import check_token, new_token

    for token in (new_token(), "0f1e2d3c4b5a69788796a5b4c3d2e1f0", TOKEN):
        assert check_token(token) == token


def test_the_configuration_holds_only_scram_keys_with_enough_iterations():
    good = {"name": "operator", "scram": CREDS.config(), "allow": ["observe"]}
    assert Client.model_validate(good).scram.credentials() == CREDS
    with pytest.raises(ValidationError, match="must be ≥ 4096"):
        Client.model_validate({**good, "scram": {**CREDS.config(), "iterations": 4095}})
    with pytest.raises(ValidationError, match="token_sha256 is no longer accepted.*acquire token new"):
        Client.model_validate({"name": "operator", "token_sha256": "0" * 64, "allow": ["observe"]})
    with pytest.raises(ValidationError, match="32 bytes"):
        Client.model_validate({**good, "scram": {**CREDS.config(), "stored_key": "AAAA"}})
    with pytest.raises(ValidationError, match="base64"):
        Client.model_validate({**good, "scram": {**CREDS.config(), "salt": "not base64!"}})
    assert AuthSection.model_validate({"clients": [good]}).clients[0].name == "operator"


def test_the_cached_key_client_final_is_the_one_scramp_computes():
    """Our client-final from cached keys is byte for byte what scramp's own client sends for the
    same nonces (RFC 5802 §3), and its ServerSignature is what scramp's server returns."""
    from scramp import ScramClient

    table = _table()
    ex = auth.ClientExchange(TOKEN, "operator", CELL, "pause", None)
    server_first, _ = table.first(_msg(ex.first_attachment()))
    ours = ex.answer(server_first)
    theirs = ScramClient(["SCRAM-SHA-256"], "operator", TOKEN, c_nonce=ex.nonce)
    theirs.get_client_first()
    theirs.set_server_first(server_first)
    assert _msg(ours.final_attachment()) == theirs.get_client_final()
    verified = table.final(_msg(ours.final_attachment()), cell=CELL, op="pause", payload=None)
    theirs.set_server_final(verified.server_final)  # scramp's client accepts the daemon's signature
    assert ours.verify(_signed(verified, {"ok": True}))


def test_one_pbkdf2_per_salt_then_hmacs_only_and_still_no_replay(monkeypatch):
    """RFC 5802 §5.1: the client keeps ClientKey/ServerKey per (salt, iterations). After the
    first exchange no PBKDF2 runs; each exchange still has fresh nonces, a used or replayed
    client-final is refused, and a wrong token still fails (its keys are its own)."""
    calls: list[int] = []
    real = hashlib.pbkdf2_hmac

    def counted(name, password, salt_, rounds, *args):
        calls.append(rounds)
        return real(name, password, salt_, rounds, *args)

    monkeypatch.setattr(hashlib, "pbkdf2_hmac", counted)
    creds = auth.derive_credentials(TOKEN, auth.MIN_ITERATIONS)  # a fresh salt: nothing cached yet
    table = _table(creds=creds)
    calls.clear()
    finals = []
    for _ in range(5):
        _, responder, final = _exchange(table)
        verified = table.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
        assert responder.verify(_signed(verified, {"ok": True}))
        finals.append(final)
    assert calls == [creds.iterations]          # one PBKDF2 for five exchanges
    assert len(set(finals)) == 5                # fresh nonces and proofs every time
    with pytest.raises(auth.ProofError, match="used before, or expired"):
        table.final(finals[-1], cell=CELL, op="pause", payload=b'{"x":1}')
    _, _, final = _exchange(table, token="Wrong-but-strong-token-8a7sd6f5")
    with pytest.raises(auth.ProofError, match="wrong token for client 'operator'"):
        table.final(final, cell=CELL, op="pause", payload=b'{"x":1}')
    assert len(calls) == 2                      # the wrong token paid its own PBKDF2
