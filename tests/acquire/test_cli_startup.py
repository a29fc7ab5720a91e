"""Start-up of the ``acquire`` command line: what ``--help`` and the thin clients import, the
command table against the command modules, and how switches are shown.

No timing here (tests/bench/bench_startup.py measures it against ``import numpy``): the tests
look at ``sys.modules`` of a fresh interpreter after the command ran.
"""

from __future__ import annotations

import ast
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquire import cli

ROOT = Path(__file__).resolve().parents[2]

#: What a fresh interpreter runs: the CLI with argv, then a JSON line with the outcome on fd 3's
#: stand-in (a file named in the environment), so the command's own output stays untouched.
PROBE = """
import json, os, sys
from acquire.cli import app
try:
    app(sys.argv[1:], prog_name="acquire")
    code = 0
except SystemExit as exc:
    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
with open(os.environ["PROBE_OUT"], "w") as f:
    json.dump({"code": code, "modules": sorted(sys.modules)}, f)
"""

#: Never needed to print help or ask the daemon for its status. (pydantic is not listed: typer
#: itself uses it to convert option values.)
HEAVY_FOR_ANY = ["scipy", "scipy.stats", "matplotlib", "matplotlib.pyplot", "calib.fit.offsets", "calib.fit.identification",
                 "calib.fit.posterior", "acquire.daemon.config", "yaml", "mcap"]


def _probe(tmp_path: Path, *args: str) -> tuple[dict, subprocess.CompletedProcess]:
    out = tmp_path / "probe.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT), PROBE_OUT=str(out), COLUMNS="120")
    proc = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=120, stdin=subprocess.DEVNULL)
    assert out.is_file(), f"the probe did not finish: {proc.stderr}"
    return json.loads(out.read_text()), proc


def test_root_help_lists_every_command_without_importing_any_of_them(tmp_path):
    res, proc = _probe(tmp_path, "--help")
    assert res["code"] == 0, proc.stderr
    for name in cli.COMMANDS:
        assert f" {name} " in proc.stdout, f"{name} missing from --help:\n{proc.stdout}"
    loaded = set(res["modules"])
    heavy = sorted(loaded & set(HEAVY_FOR_ANY + ["numpy", "zenoh"]))
    assert not heavy, f"acquire --help imported {heavy}"
    commands = sorted(m for m in loaded if m.startswith("acquire.commands."))
    assert not commands, f"acquire --help imported command modules {commands}"


def test_status_client_imports_no_fitter_no_plotting_no_config_parser(tmp_path):
    with socket.socket() as s:  # a port nobody listens on: the client fails, after its imports
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    res, proc = _probe(tmp_path, "status", "--cell", "lab1", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "1")
    assert res["code"] in (1, 4), proc.stderr  # the daemon is absent: the client got as far as the bus
    assert "zenoh" in res["modules"]
    heavy = sorted(set(res["modules"]) & set(HEAVY_FOR_ANY + ["numpy"]))
    assert not heavy, f"acquire status imported {heavy}"
    assert [m for m in res["modules"] if m.startswith("acquire.commands.")] == ["acquire.commands.daemon"]


#: Never needed for a sub-command's own --help.
HEAVY_FOR_HELP = ["scipy", "scipy.stats", "matplotlib", "matplotlib.pyplot", "calib.fit.offsets", "calib.fit.identification",
                  "calib.fit.posterior", "calib.plan.poses", "zenoh", "mcap"]


@pytest.mark.parametrize("name, shows", [("watch", "--raw"), ("run", "--listen"), ("poses", "--sensor-origin"),
                                         ("select", "--candidates"), ("status", "--cell"), ("fit", "--report")])
def test_a_sub_command_help_loads_only_its_own_module_and_nothing_heavy(tmp_path, name, shows):
    res, proc = _probe(tmp_path, name, "--help")
    assert res["code"] == 0, proc.stderr
    assert shows in proc.stdout
    assert sorted(m for m in res["modules"] if m.startswith("acquire.commands.")) == [cli.COMMANDS[name].module]
    heavy = sorted(set(res["modules"]) & set(HEAVY_FOR_HELP))
    assert not heavy, f"acquire {name} --help imported {heavy}"


def test_a_fast_zero_offset_fit_with_its_report_runs_without_matplotlib(tmp_path):
    """``acquire fit --method fast`` on sensor data — read, fit, metrics, report — needs no
    plotting library (the report's figures are SVG written by ``calib.report.svg``), nor the socket
    fit (a one-line header test tells the two CSV formats apart), nor scipy's statistics. It does
    need ``scipy.optimize``: what it tells the operator to enter is judged against the robot as
    found, whose registration and tool are fitted by least squares (``calib.fit.entered``)."""
    data = ROOT / "fixtures" / "datasets"
    res, proc = _probe(tmp_path, "fit", str(data / "iiwa14_sim_cal.csv"), "--robot",
                       str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"), "--validate",
                       str(data / "iiwa14_sim_val.csv"), "--method", "fast", "--report", str(tmp_path / "r.html"))
    assert res["code"] == 0, proc.stderr
    assert (tmp_path / "r.html").stat().st_size > 0 and "calib.fit.offsets" in res["modules"]
    heavy = [m for m in res["modules"] if m.split(".")[0] in ("matplotlib", "PIL") or m.startswith("scipy.stats")
             or m in ("calib.fit.socket", "acquire.run.socket_fit")]
    assert not heavy, heavy


def _registered(module: str) -> set[str]:
    """Command names ``module.register`` adds, read from the source (``app.command("x")``, the
    ``for fn in (a, b): app.command(fn.__name__)`` idiom and ``app.add_typer(..., name="x")``)."""
    tree = ast.parse((ROOT / (module.replace(".", "/") + ".py")).read_text())
    reg = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "register")
    names: set[str] = set()
    for node in ast.walk(reg):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "command" and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Constant):
                names.add(arg.value)
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_typer":
            names |= {k.value.value for k in node.keywords
                      if k.arg == "name" and isinstance(k.value, ast.Constant)}  # a command group
        if isinstance(node, ast.For) and isinstance(node.iter, ast.Tuple):
            names |= {e.id for e in node.iter.elts if isinstance(e, ast.Name)}
    return names


def test_command_table_matches_what_each_module_registers():
    modules = {p.stem for p in (ROOT / "acquire" / "commands").glob("*.py")
               if "def register(" in p.read_text()}
    assert {m.rsplit(".", 1)[1] for m in cli.COMMAND_MODULES} == modules, (
        "every acquire/commands module with register() must be listed in acquire.cli.COMMANDS")
    for module in cli.COMMAND_MODULES:
        in_table = {n for n, spec in cli.COMMANDS.items() if spec.module == module}
        assert _registered(module) == in_table, module


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_table_help_is_the_commands_own_first_docstring_line(name):
    command = cli.load_command(name)
    assert command.name == name
    first = (command.help or "").strip().splitlines()[0]
    assert first == cli.COMMANDS[name].help


@pytest.mark.parametrize("args", [["--help"]] + [[name, "--help"] for name in cli.COMMANDS])
def test_switches_show_no_value_type_and_valued_options_keep_theirs(args):
    res = CliRunner().invoke(cli.app, args, env={"COLUMNS": "160"}, prog_name="acquire")
    assert res.exit_code == 0, res.output
    assert "--help" in res.output
    assert "<bool>" not in res.output, res.output
    if args[0] == "run":
        fake_row = next(line for line in res.output.splitlines() if "--fake " in line)
        assert "<" not in fake_row.split("--fake", 1)[1].split("Run against")[0]
        assert "<path>" in next(line for line in res.output.splitlines() if "--resume" in line)


def test_unknown_command_is_refused_with_a_suggestion():
    res = CliRunner().invoke(cli.app, ["wach"], prog_name="acquire")
    assert res.exit_code == 2
    assert "No such command 'wach'" in res.output and "'watch'" in res.output
