"""The documentation: the site builds with warnings as errors, its reference is the program's,
the README stays a front page, and every command a tutorial shows is run."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
TUTORIALS = sorted((DOCS / "tutorials").glob("*.md"))
QUIET = {"NO_MKDOCS_2_WARNING": "1"}  # Material's end-of-life banner, not a build warning

# One xdist worker runs this file (./test --dist loadgroup): the site (5 CPU-s) is built once, not
# once per worker that happens to get one of its tests.
pytestmark = pytest.mark.xdist_group("docs-site")


def shell_blocks(page: Path) -> list[str]:
    """The command lines of the page's ```sh blocks, in order (comments and blank lines dropped)."""
    out = []
    for block in re.findall(r"```sh\n(.*?)```", page.read_text(), flags=re.S):
        for line in block.splitlines():
            line = line.split("  #")[0].strip()
            if line and not line.startswith("#"):
                out.append(line)
    return out


def yaml_blocks(page: Path) -> list[dict]:
    return [yaml.safe_load(b) for b in re.findall(r"```yaml\n(.*?)```", page.read_text(), flags=re.S)]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)], cwd=ROOT,
                          env={**os.environ, **QUIET}, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return out


def test_the_site_builds_with_warnings_as_errors_and_every_nav_page_exists(site):
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]

    def pages(node):
        if isinstance(node, str):
            yield node
        elif isinstance(node, dict):
            for v in node.values():
                yield from pages(v)
        else:
            for v in node:
                yield from pages(v)

    for page in pages(nav):
        stem = page.removesuffix(".md")
        built = site / (stem.removesuffix("index") if stem.endswith("index") else stem + "/") / "index.html"
        assert built.is_file(), page


def test_the_cli_reference_is_generated_from_the_program(site):
    from acquire.cli import COMMANDS, load_command

    html = (site / "reference" / "cli" / "index.html").read_text()
    for name in COMMANDS:
        command = load_command(name)
        assert f"acquire {name}" in html, name
        for param in command.params:
            for opt in getattr(param, "opts", []):
                if opt.startswith("--"):
                    assert opt in html, f"acquire {name} {opt} missing from the CLI reference"


@pytest.mark.parametrize("page, module, cls", [
    ("plan", "acquire.plan.schema", "Plan"),
    ("cell-file", "drivers.sim.config", "SimConfig"),
    ("daemon-config", "acquire.daemon.config", "DaemonConfig"),
    ("robot-model", "calib.robot.model", "RobotModel"),
])
def test_file_references_list_every_field_of_their_schema(site, page, module, cls):
    import importlib

    model = getattr(importlib.import_module(module), cls)
    html = (site / "reference" / page / "index.html").read_text()
    defs = model.model_json_schema()
    for name, sub in [(cls, defs), *defs.get("$defs", {}).items()]:
        for field in sub.get("properties", {}):
            assert f"<code>{field}</code>" in html, f"{cls}: {name}.{field} missing from reference/{page}"


def test_the_readme_is_a_front_page_whose_links_resolve():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    for target in re.findall(r"\]\((?!https?://)([^)#]+)\)", text):
        assert (ROOT / target).exists(), f"README links to {target}, which does not exist"


def _command_path(words: list[str]):
    """The typer command a command line names, and the words after it."""
    from acquire.cli import COMMANDS, load_command

    assert words[1] in COMMANDS, f"no command acquire {words[1]}"
    command, rest = load_command(words[1]), words[2:]
    while hasattr(command, "list_commands") and rest and not rest[0].startswith("-"):
        ctx = command.context_class(command, info_name=words[1])
        command, rest = command.get_command(ctx, rest[0]), rest[1:]
    return command, rest


@pytest.mark.parametrize("page", TUTORIALS, ids=lambda p: p.name)
def test_every_tutorial_command_names_a_command_and_options_the_program_has(page):
    lines = [line for line in shell_blocks(page) if line.startswith("acquire ")]
    assert lines, f"{page.name} shows no acquire command"
    for line in lines:
        command, rest = _command_path(shlex.split(line))
        known = {o for p in command.params for o in [*getattr(p, "opts", []), *getattr(p, "secondary_opts", [])]}
        for word in rest:
            if word.startswith("--") or re.fullmatch(r"-[a-z]", word):
                assert word.split("=")[0] in known, f"{page.name}: {line!r}: no option {word}"


def test_every_top_level_key_of_a_result_is_in_the_result_reference(tmp_path):
    from typer.testing import CliRunner

    from acquire.cli import app

    documented = set(re.findall(r"^\| `(\w+)`(?:, `(\w+)`)? \|", (DOCS / "reference" / "result-json.md").read_text(), flags=re.M))
    documented = {k for pair in documented for k in pair if k}
    out = tmp_path / "result.json"
    result = CliRunner().invoke(app, ["fit", str(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"), "--robot",
                                      str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"), "--method", "fast",
                                      "--draws", "200", "--random-configs", "100", "-o", str(out)])
    assert result.exit_code in (0, 1), result.output
    import json

    keys = set(json.loads(out.read_text()))
    assert keys <= documented, f"result.json keys not in docs/reference/result-json.md: {sorted(keys - documented)}"


# ------------------------------------------------------------------ the tutorials, run
def _shell(tmp_path: Path) -> dict:
    """An environment whose ``acquire`` is this checkout's (a wrapper in tmp_path/bin)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    wrapper = bin_dir / "acquire"
    wrapper.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m acquire "$@"\n')
    wrapper.chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "PYTHONPATH": str(ROOT)}


def _run(line: str, cwd: Path, env: dict, timeout: float = 600) -> str:
    if line.startswith("python3 -m pip install"):
        return ""  # the checkout is installed already (./test installed it)
    proc = subprocess.run(["bash", "-c", line], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{line!r} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_simulated_cell_tutorial_runs_as_written(tmp_path):
    env = _shell(tmp_path)
    outputs = [_run(line, tmp_path, env) for line in shell_blocks(DOCS / "tutorials" / "simulated-cell.md")]
    assert "example" in outputs[1]  # acquire examples lists the plan the next step runs
    assert list(tmp_path.glob("runs/*/*.mcap")) and (tmp_path / "result.json").is_file()
    assert (tmp_path / "report.html").is_file() and (tmp_path / "iiwa14_calibrated.urdf").is_file()


def _deep_update(doc: dict, edits: dict) -> None:
    for key, value in edits.items():
        if isinstance(value, dict) and isinstance(doc.get(key), dict):
            _deep_update(doc[key], value)
        else:
            doc[key] = value


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_first_real_cell_tutorial_runs_as_written_against_the_simulated_cell(tmp_path):
    """The tutorial's commands in order; its plan edits applied as a user would; `acquire sim`
    stands in for the robot and the bar (its FRI port from the kernel, not 30200, so that tests
    can run side by side; the plan's addresses are the ones it prints)."""
    from drivers.sim.running import free_udp_port

    page = DOCS / "tutorials" / "first-real-cell.md"
    env = _shell(tmp_path)
    port = str(free_udp_port())
    (edits,) = yaml_blocks(page)
    sim = None
    try:
        for line in shell_blocks(page):
            line = line.replace("30200", port)
            if line.startswith("acquire sim"):
                sim = subprocess.Popen(["bash", "-c", "exec " + line], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT, text=True, stdin=subprocess.PIPE)
                natnet = None
                deadline = time.monotonic() + 120
                while natnet is None and time.monotonic() < deadline:
                    out = sim.stdout.readline()
                    assert out, "acquire sim ended before it printed its addresses"
                    m = re.match(r"mocap\s+(natnet://\S+)", out)
                    natnet = m.group(1) if m else None
                plan = tmp_path / "example.yaml"
                doc = yaml.safe_load(plan.read_text())
                doc["sensors"][0]["url"] = natnet
                # a loaded test machine: the cell's timing allowances, as the simulated cell's own runs carry them
                doc["commander"]["url"] += "?timeout_ms=1500&max_state_age_ms=1500"
                plan.write_text(yaml.safe_dump(doc, sort_keys=False))
                continue
            _run(line, tmp_path, env)
            if line.startswith("acquire examples --copy"):
                plan = tmp_path / "example.yaml"
                doc = yaml.safe_load(plan.read_text())
                _deep_update(doc, yaml.safe_load(yaml.safe_dump(edits).replace("30200", port)))
                plan.write_text(yaml.safe_dump(doc, sort_keys=False))
    finally:
        if sim is not None:
            sim.terminate()
            sim.wait(30)
            sim.stdout.close()
            sim.stdin.close()
    results = list(tmp_path.glob("runs/*/result.json"))
    assert results, "the run wrote no result"
