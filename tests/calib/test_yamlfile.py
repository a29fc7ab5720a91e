"""The one safe YAML loader (calib/io/yamlfile.py): aliases, duplicate keys, size and depth refused
with file:line:column, for files and inline text, and through every loader that uses it."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest

from calib.io.yamlfile import MAX_BYTES, MAX_DEPTH, ConfigError, load_yaml_with_marks, parse_yaml_text

ROOT = Path(__file__).resolve().parents[2]

# The attack: nine levels of nine aliases each, ~10^9 strings once expanded (~300 bytes).
BILLION_LAUGHS = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"{n}: &{n} [{', '.join(['*' + p] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi"))


def test_alias_bomb_is_refused_at_its_first_anchor_with_bounded_memory():
    assert len(BILLION_LAUGHS) < 400
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError) as exc:
            parse_yaml_text(BILLION_LAUGHS, "bomb.yaml")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert str(exc.value).startswith("bomb.yaml:1:4: YAML anchors are not allowed (given &a)")
    assert "\n" not in str(exc.value)
    assert peak < 5_000_000, peak  # refused while composing: nothing was expanded


def test_an_alias_without_anchor_is_refused_naming_its_place():
    with pytest.raises(ConfigError, match=r"^t.yaml:2:8: YAML aliases are not allowed \(given \*x\)"):
        parse_yaml_text("a: 1\nspeed: *x\n", "t.yaml")


def test_duplicate_keys_are_refused_naming_both_lines():
    with pytest.raises(ConfigError) as exc:
        parse_yaml_text("sequencing:\n  speed: 0.5\n  samples: 5\n  speed: 1.0\n", "p.yaml")
    msg = str(exc.value)
    assert msg.startswith("p.yaml:4:3: sequencing.speed: duplicate key 'speed'")
    assert "first given on line 2, again on line 4" in msg
    # Top level too, and in flow mappings.
    with pytest.raises(ConfigError, match=r"p.yaml:1:9: a: duplicate key 'a' \(first given on line 1, again on line 1\)"):
        parse_yaml_text("{a: 1,  a: 2}", "p.yaml")


def test_nesting_deeper_than_the_limit_is_refused_and_the_limit_itself_is_accepted():
    ok = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    data, _ = parse_yaml_text(ok)
    for _ in range(MAX_DEPTH - 1):
        data = data[0]
    assert data == []
    deep = "[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1)
    with pytest.raises(ConfigError, match=rf"^d.yaml:1:{MAX_DEPTH + 1}: nested too deep"):
        parse_yaml_text(deep, "d.yaml")
    # Far deeper than Python's recursion limit: still a ConfigError, not a RecursionError.
    with pytest.raises(ConfigError, match="nested too deep"):
        parse_yaml_text("a: " + "[" * 5000 + "]" * 5000)
    with pytest.raises(ConfigError, match=r"^<text>:65:65: nested too deep"):
        parse_yaml_text("".join(" " * i + f"k{i}:\n" for i in range(100)) + " " * 100 + "x\n")


def test_over_large_text_and_file_are_refused_before_parsing(tmp_path):
    big = "a: " + "x" * MAX_BYTES + "\n"
    with pytest.raises(ConfigError, match=rf"^inline: too large \({len(big)} bytes; allowed: at most {MAX_BYTES} bytes\)"):
        parse_yaml_text(big, "inline")
    path = tmp_path / "big.yaml"
    path.write_text(big)
    with pytest.raises(ConfigError, match=rf"^{path}: too large"):
        load_yaml_with_marks(path)


def test_unsafe_tags_non_scalar_keys_and_bad_bytes_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"t.yaml:1:4: a: YAML tags are not allowed on mappings and lists \(given .tag:yaml.org,2002:python/object/apply:os.system.\)"):
        parse_yaml_text("a: !!python/object/apply:os.system [echo hi]\n", "t.yaml")
    with pytest.raises(ConfigError, match="t.yaml:1:4: not valid YAML: could not determine a constructor"):
        parse_yaml_text("a: !!python/name:os.system x\n", "t.yaml")
    with pytest.raises(ConfigError, match=r"t.yaml:1:3: \(top level\): a key must be a plain value"):
        parse_yaml_text("? [1, 2]\n: 3\n", "t.yaml")
    path = tmp_path / "latin1.yaml"
    path.write_bytes(b"a: 1\nname: caf\xe9\n")
    with pytest.raises(ConfigError, match=rf"{path}:2: not UTF-8 text"):
        load_yaml_with_marks(path)


def test_plain_files_still_load_with_their_marks():
    data, marks = parse_yaml_text("a:\n  - 1\n  - {b: c}\n")
    assert data == {"a": [1, {"b": "c"}]}
    assert marks[("a", 1)] == (3, 5) and marks[("a", 1, "b")] == (3, 9)  # where each value starts
    for path in sorted((ROOT / "fixtures").rglob("*.yaml")):
        load_yaml_with_marks(path)  # every shipped file passes the stricter loader


def test_every_loader_uses_it(tmp_path):
    """Robot models, simulated cells and daemon configs refuse duplicate keys with both lines."""
    from acquire.daemon.config import load_daemon_config
    from calib.robot.model import load_robot_model
    from drivers.sim.config import load_sim_config

    daemon = tmp_path / "daemon.yaml"
    daemon.write_text("cell: lab1\nfake: true\nauth:\n  anonymous: [observe]\n  anonymous: [observe, control]\n")
    with pytest.raises(ConfigError, match=rf"^{daemon}:5:3: auth.anonymous: duplicate key 'anonymous' "
                                          r"\(first given on line 4, again on line 5\)"):
        load_daemon_config(daemon)

    model = tmp_path / "robot.yaml"
    text = (ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").read_text()
    model.write_text(text + "\nname: other\n")
    with pytest.raises(ConfigError, match=rf"^{model}:\d+:1: name: duplicate key 'name'"):
        load_robot_model(model)

    cell = tmp_path / "cell.yaml"
    cell.write_text((ROOT / "fixtures" / "sim" / "default.yaml").read_text() + "\nrobot: &r x\n")
    with pytest.raises(ConfigError, match=rf"^{cell}:\d+:8: YAML anchors are not allowed"):
        load_sim_config(cell)
