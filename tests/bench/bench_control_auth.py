"""Cost of one authenticated control operation on the client (the station pulling chunks).

    python tests/bench/bench_control_auth.py [--iterations 600000] [--exchanges 5]

Before: every exchange computed PBKDF2 in scramp's client (what the control client did until
the key cache). After: ``acquire.daemon.control_auth.ClientExchange`` — one PBKDF2 per process and
(salt, iterations), then HMACs only (RFC 5802 §5.1). Both run against the daemon's
``ExchangeTable`` without Zenoh; every proof is verified by the table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from scramp import ScramClient  # noqa: E402

from acquire.daemon import control_auth as auth  # noqa: E402

TOKEN = "Zk3-pQ9xT2mV7bN4cR8sW1yL6hJ0fG"


def _msg(att: bytes) -> str:
    return json.loads(att)["msg"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--iterations", type=int, default=auth.DEFAULT_ITERATIONS)
    ap.add_argument("--exchanges", type=int, default=5)
    args = ap.parse_args()
    creds = auth.derive_credentials(TOKEN, args.iterations)
    table = auth.ExchangeTable(lambda n: creds, decoy_iterations=args.iterations)

    before = []
    for _ in range(args.exchanges):
        t = time.perf_counter()
        ex = auth.ClientExchange(TOKEN, "station", "c1", "archive-chunk", b"{}")
        first, _ = table.first(_msg(ex.first_attachment()))
        c = ScramClient([auth.MECHANISM], "station", TOKEN, c_nonce=ex.nonce)
        c.get_client_first()
        c.set_server_first(first)
        v = table.final(c.get_client_final(), cell="c1", op="archive-chunk", payload=b"{}")
        c.set_server_final(v.server_final)
        before.append(time.perf_counter() - t)

    after = []
    for _ in range(args.exchanges):
        t = time.perf_counter()
        ex = auth.ClientExchange(TOKEN, "station", "c1", "archive-chunk", b"{}")
        first, _ = table.first(_msg(ex.first_attachment()))
        r = ex.answer(first)
        v = table.final(_msg(r.final_attachment()), cell="c1", op="archive-chunk", payload=b"{}")
        body = {"ok": True, "scram": v.server_final}
        assert r.verify({**body, "mac": auth.reply_mac(v.reply_key, body)})
        after.append(time.perf_counter() - t)

    ms = lambda xs: ", ".join(f"{x * 1e3:.2f}" for x in xs)  # noqa: E731
    print(f"{args.iterations} PBKDF2 iterations, {args.exchanges} exchanges each (ms per exchange, client+daemon)")
    print(f"before (PBKDF2 every exchange): {ms(before)}")
    print(f"after  (keys cached per salt):  {ms(after)}")
    print(f"steady-state ratio before/after: {sorted(before)[len(before) // 2] / sorted(after[1:])[len(after[1:]) // 2]:.0f}x")


if __name__ == "__main__":
    main()
