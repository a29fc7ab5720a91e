"""Plans and inline plan texts that could hurt (issue 21): alias bombs, duplicate keys.

The loader itself is tested in tests/calib/test_yamlfile.py; here: the plan loader, the
``acquire run`` command and the daemon's inline ``plan_text`` use it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from acquire.plan.schema import load_plan
from calib.io.yamlfile import ConfigError

from daemon_harness import OPERATOR_TOKEN, control, open_client  # noqa: E402
from run_helpers import ROOT, small_plan  # noqa: E402

BOMB = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"{n}: &{n} [{', '.join(['*' + p] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi"))


def _with_duplicate_speed(tmp_path: Path) -> tuple[Path, int, int]:
    """The small plan with a second ``speed: 1.0`` after ``speed: …`` in sequencing; its two lines."""
    path = small_plan(tmp_path)
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.strip().startswith("speed:"))
    indent = lines[first][: len(lines[first]) - len(lines[first].lstrip())]
    lines.insert(first + 2, f"{indent}speed: 1.0")
    path.write_text("\n".join(lines) + "\n")
    return path, first + 1, first + 3


def test_a_plan_with_a_duplicate_key_is_refused_naming_both_lines(tmp_path):
    path, first, second = _with_duplicate_speed(tmp_path)
    with pytest.raises(ConfigError) as exc:
        load_plan(path)
    assert str(exc.value).startswith(f"{path}:{second}:")
    assert f"sequencing.speed: duplicate key 'speed' (first given on line {first}, again on line {second})" in str(exc.value)


def test_acquire_run_refuses_the_alias_bomb_plan_with_exit_2(tmp_path):
    plan = tmp_path / "bomb.yaml"
    plan.write_text(BOMB)
    out = subprocess.run([sys.executable, "-m", "acquire", "run", str(plan), "--fake"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip() == f"error: {plan}:1:4: YAML anchors are not allowed (given &a); write the value " \
                                 "out in full where it is used"
    assert not (tmp_path / "runs").exists()


# (the `daemon` fixture: daemon_harness.py, offered by conftest.py)
def test_the_daemon_refuses_an_inline_alias_bomb_in_one_line_and_keeps_answering(daemon):
    from acquire.daemon.control import BadRequest

    proc, port, tmp_path = daemon
    proc.wait_ready()
    rss_before = proc.rss_kb()
    with open_client(port) as bus:
        op = control(bus, "operator", OPERATOR_TOKEN)
        with pytest.raises(BadRequest) as exc:
            op.call("start", {"plan_text": BOMB}, timeout=60)
        msg = str(exc.value)
        assert "\n" not in msg, msg
        assert msg.startswith("plan not valid: ") and ":1:4: YAML anchors are not allowed (given &a)" in msg
        # A duplicate key inline is refused the same way.
        text = (tmp_path / "plans" / "example.yaml").read_text().replace("  speed: 0.5", "  speed: 0.5\n  speed: 1.0", 1)
        with pytest.raises(BadRequest, match=r"sequencing.speed: duplicate key 'speed' \(first given on line \d+"):
            op.call("start", {"plan_text": text}, timeout=60)
        st = op.call("status")
        assert st["daemon"] == "ready" and st["run"] is None
    # Nothing was expanded: the daemon did not grow by the gigabytes the bomb describes.
    assert proc.rss_kb() < rss_before + 200_000
