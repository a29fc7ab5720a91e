"""Tokens people cannot get wrong: ``acquire token new`` (mode 0600, no silent overwrite, config
lines that work), the CLI's refusal of unprotected or weak token files, and the rate limit of
the log lines about what clients send."""

from __future__ import annotations

import json
import os
import re
import stat

import pytest
import yaml
from typer.testing import CliRunner

from acquire.daemon import control_auth as auth
from acquire.cli import app
from acquire.daemon.config import Client
from acquire.live.logthrottle import Throttle
from acquire.daemon.tokens import TokenFileError, read_token_file, write_token_file

STRONG = "Zk3-pQ9xT2mV7bN4cR8sW1yL6hJ0fG"


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_token_new_writes_a_private_file_and_config_lines_that_log_in(tmp_path):
    out = tmp_path / "cfg" / "token"
    res = CliRunner().invoke(app, ["token", "new", "--client", "viewer", "--out", str(out), "--iterations", "4096"])
    assert res.exit_code == 0, res.output
    assert _mode(out) == 0o600
    token = read_token_file(out)
    assert len(token) >= 43 and token not in res.output  # the token is never printed
    # The printed lines are a valid client entry of the daemon's configuration…
    entry = yaml.safe_load("\n".join(line for line in res.output.splitlines() if not line.startswith("#")))[0]
    client = Client.model_validate(entry)
    assert client.name == "viewer" and client.scram.iterations == 4096
    # …with which that token completes an exchange (and nothing else does).
    table = auth.ExchangeTable(lambda name: client.scram.credentials() if name == "viewer" else None)
    for candidate, ok in ((token, True), (STRONG, False)):
        ex = auth.ClientExchange(candidate, "viewer", "lab1", "status", None)
        first, _ = table.first(json.loads(ex.first_attachment())["msg"])
        final = ex.answer(first).client_final
        if ok:
            assert table.final(final, cell="lab1", op="status", payload=None).client == "viewer"
        else:
            with pytest.raises(auth.ProofError, match="wrong token"):
                table.final(final, cell="lab1", op="status", payload=None)


def test_token_new_refuses_to_overwrite_and_low_iterations(tmp_path):
    out = tmp_path / "token"
    out.write_text("old\n")
    out.chmod(0o644)
    res = CliRunner().invoke(app, ["token", "new", "--out", str(out), "--iterations", "4096"])
    assert res.exit_code == 2 and "exists; give --force" in res.output
    assert out.read_text() == "old\n"
    res = CliRunner().invoke(app, ["token", "new", "--out", str(out), "--iterations", "1000", "--force"])
    assert res.exit_code == 2 and "at least 4096" in res.output
    res = CliRunner().invoke(app, ["token", "new", "--out", str(out), "--iterations", "4096", "--force"])
    assert res.exit_code == 0, res.output
    assert _mode(out) == 0o600 and out.read_text() != "old\n"  # replaced, and no longer world-readable


def test_an_unprotected_or_weak_token_file_is_refused_like_ssh_refuses_a_key(tmp_path):
    path = tmp_path / "token"
    path.write_text(STRONG + "\n")  # what `echo "$token" > file` makes under umask 022
    path.chmod(0o644)
    with pytest.raises(TokenFileError, match=r"UNPROTECTED TOKEN FILE: .* mode 0644.*chmod 600"):
        read_token_file(path)
    res = CliRunner().invoke(app, ["status", "--cell", "lab1", "--client", "operator", "--token-file", str(path)])
    assert res.exit_code == 2 and "UNPROTECTED TOKEN FILE" in res.output, res.output
    path.chmod(0o640)
    with pytest.raises(TokenFileError, match="0640"):
        read_token_file(path)
    path.chmod(0o600)
    assert read_token_file(path) == STRONG
    path.write_text("dragon2024\n")
    res = CliRunner().invoke(app, ["pause", "--cell", "lab1", "--client", "operator", "--token-file", str(path)])
    assert res.exit_code == 2 and re.search(r"token too short: 10 characters.*acquire token new", res.output)
    res = CliRunner().invoke(app, ["pause", "--cell", "lab1", "--client", "operator"],
                             env={"REMASTER_TOKEN": "operator-secret-token"})
    assert res.exit_code == 2 and "REMASTER_TOKEN: token too weak" in res.output


def test_write_token_file_never_creates_a_readable_file(tmp_path):
    old = os.umask(0)  # even with a permissive umask
    try:
        path = write_token_file(tmp_path / "a" / "token", STRONG)
    finally:
        os.umask(old)
    assert _mode(path) == 0o600 and _mode(path.parent) == 0o700
    with pytest.raises(FileExistsError):
        write_token_file(path, STRONG)


def test_throttle_bounds_lines_per_source_and_overall_and_counts_the_rest():
    t = [0.0]
    throttle = Throttle(burst=20, per_s=0.2, total_burst=60, total_per_s=1.0, clock=lambda: t[0])
    admitted = [throttle.admit("zid-a") for _ in range(1000)]
    assert sum(a is not None for a in admitted) == 20
    t[0] += 5.0  # one more line allowed per source after 5 s: it carries the count
    assert throttle.admit("zid-a") == 980
    # A client that changes its source id every time is bounded by the overall bucket.
    t[0] += 100.0
    spread = [throttle.admit(f"zid-{i}") for i in range(1000)]
    assert sum(a is not None for a in spread) == 60
    assert throttle.suppressed_total == 980 + 940


def test_throttle_drain_returns_what_is_still_owed_once():
    throttle = Throttle(burst=2, per_s=0.0, total_burst=100, total_per_s=0.0, clock=lambda: 0.0)
    for _ in range(7):
        throttle.admit("zid-a")
    throttle.admit("zid-b")
    assert throttle.drain() == {"zid-a": 5}  # zid-b had nothing dropped
    assert throttle.drain() == {}


def test_a_token_made_of_the_cell_and_client_names_is_refused_where_they_are_known():
    from acquire.daemon.control import ControlClient
    from acquire.daemon.tokens import WeakToken, check_token, guesses_log10, new_token

    token = "hallb-cell7-welder-2026-hallb-cell7"
    assert check_token(token) == token  # strangers' words: zxcvbn rates it above 10^20…
    with pytest.raises(WeakToken, match="too weak"):  # …but the client's name and the cell id are no secret
        ControlClient(None, "hallb-cell7", client="welder", token=token)
    res = CliRunner().invoke(app, ["status", "--cell", "hallb-cell7", "--client", "welder"], env={"REMASTER_TOKEN": token})
    assert res.exit_code == 2 and "REMASTER_TOKEN: token too weak" in res.output, res.output
    generated = new_token()
    assert guesses_log10(generated, ("welder", "hallb-cell7")) >= 40  # 43 random characters
    assert ControlClient(None, "hallb-cell7", client="welder", token=generated)
