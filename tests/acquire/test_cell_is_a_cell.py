"""A cell is a cell: the run cannot tell a simulated cell from a real one.

- the same short plan, run against a simulated cell started separately (as ``acquire sim`` does:
  ``SimLaunch`` on loopback, the plan's own URLs pointed at it, the host's clock) and against
  ``--fake`` (the simulated cell started for the run and described to it), visits the same
  configurations in the same order with the same sequence of events, and writes both logs;
- outside ``acquire/commands/`` no module of ``acquire/`` imports ``drivers.sim`` or refers to
  the simulator's truth;
- no class in ``acquire/`` or ``calib/`` exceeds 400 lines.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from acquire.plan.schema import load_plan, resolve_configurations
from acquire.record.recorder import read_run
from acquire.run import RunController

from run_helpers import ROOT, RUN_TIMEOUT_S, simulated_run, small_plan, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest

#: Event kinds of the run loop itself (not retries or link figures, which a loaded host may vary).
LOOP_KINDS = ("run_started", "moved", "settled", "measured", "skipped", "failed", "run_finished")


def _three_configuration_plan(tmp_path: Path, **overrides) -> Path:
    """The example plan cut to three explicit configurations (from its own generated poses)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    lp = load_plan(small_plan(tmp_path, n=2, name="source.yaml"))
    rows = [np.round(np.degrees(c.q_rad), 4).tolist() for c in resolve_configurations(lp)[:3]]
    doc = yaml.safe_load((tmp_path / "source.yaml").read_text())
    doc["poses"] = {"joints": rows}
    doc["sequencing"].update({"samples": 5, "settle_window_s": 0.2})
    for section, values in overrides.items():
        doc.setdefault(section, {}).update(values)
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _loop(log: Path) -> tuple[list, list]:
    """(configurations measured in order, the run loop's (event kind, configuration) sequence)."""
    contents = read_run(log)
    assert contents.complete
    events = [(e["kind"], e.get("config_id")) for e in contents.events if e["kind"] in LOOP_KINDS]
    return [s["config_id"] for s in contents.samples], events


@pytest.mark.timeout(RUN_TIMEOUT_S)
def test_a_separately_started_simulated_cell_and_fake_run_the_same_loop(tmp_path):
    from drivers.sim.cell import SimCell
    from drivers.sim.clock import SimClock
    from drivers.sim.config import DEFAULT_CONFIG_PATH
    from drivers.sim.launch import SimLaunch
    from drivers.sim.running import free_udp_port

    # 1. as `acquire sim` + `acquire run plan.yaml`: the cell runs on its own; the plan's URLs point at it
    port = free_udp_port()
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, clock=SimClock(1.0))
    allow = cell.config.allowances
    with SimLaunch(cell, fri_port=port, max_runtime_s=300) as launch:
        plan = _three_configuration_plan(
            tmp_path / "separate",
            commander={"url": f"fri://127.0.0.1:{port}?timeout_ms={allow.silence_ms:g}&max_state_age_ms={allow.state_age_ms:g}"},
            output={"folder": str(tmp_path / "separate" / "runs")})
        doc = yaml.safe_load(plan.read_text())
        doc["sensors"][0]["url"] = launch.addresses["mocap"].url
        plan.write_text(yaml.safe_dump(doc, sort_keys=False))
        lp = load_plan(plan)
        separate = RunController(lp, fit=False)  # no cell given: the plan's own URLs, the host's clock
        separate.start()
        first = wait_for_run(separate)
    assert first.state == "finished", first.reason
    assert read_run(first.log_path).metadata.get("cell_source") == "plan"

    # 2. `--fake`: the simulated cell of the plan's fake section, started for the run and described to it
    plan = _three_configuration_plan(tmp_path / "fake", fake={"time_scale": 2.0},
                                     output={"folder": str(tmp_path / "fake" / "runs")})
    lp_fake = load_plan(plan)
    with simulated_run(lp_fake, fit=False) as (rc, _sim):
        rc.start()
        second = wait_for_run(rc)
    assert second.state == "finished", second.reason
    assert read_run(second.log_path).metadata.get("cell_source") == "simulated"

    # the same configurations, in the same order, with the same run loop; both logs written
    assert [c.config_id for c in resolve_configurations(lp)] == [c.config_id for c in resolve_configurations(lp_fake)]
    measured_a, events_a = _loop(first.log_path)
    measured_b, events_b = _loop(second.log_path)
    assert measured_a == measured_b and len(measured_a) == 3
    assert events_a == events_b
    assert first.log_path != second.log_path and first.log_path.is_file() and second.log_path.is_file()


# ----------------------------------------------------------------------------------- the source
def _modules(folder: str):
    return sorted((ROOT / folder).rglob("*.py"))


def _sim_imports_and_truth(path: Path) -> list[str]:
    """Where ``path`` imports ``drivers.sim`` or names the simulator's truth."""
    text = path.read_text(encoding="utf-8")
    out = []
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if isinstance(node, ast.Import):
            out += [f"import {a.name}" for a in node.names if a.name.startswith("drivers.sim")]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("drivers.sim"):
            out.append(f"from {node.module} import …")
        elif isinstance(node, ast.ImportFrom) and node.module == "drivers" and any(a.name == "sim" for a in node.names):
            out.append("from drivers import sim")
    out += [f"line {text[:m.start()].count(chr(10)) + 1}: {m.group(0)!r}"
            for m in re.finditer(r"\w*truth\w*", text, flags=re.IGNORECASE)]
    return out


def test_outside_the_commands_acquire_neither_imports_the_simulator_nor_names_its_truth():
    offenders = {str(p.relative_to(ROOT)): hits for p in _modules("acquire")
                 if "commands" not in p.relative_to(ROOT).parts and (hits := _sim_imports_and_truth(p))}
    assert not offenders, f"the run must not know its cell is simulated: {offenders}"


def test_the_source_check_sees_a_simulator_import_and_the_truth(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from drivers.sim.cell import SimCell\nimport drivers.sim.launch\nx = cell.truth.offsets_deg\n")
    hits = _sim_imports_and_truth(bad)
    assert len(hits) == 3 and any("truth" in h for h in hits)


def _long_classes(folder: str, limit: int) -> dict[str, int]:
    out = {}
    for p in _modules(folder):
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"), filename=str(p))):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > limit:
                out[f"{p.relative_to(ROOT)}:{node.lineno} {node.name}"] = node.end_lineno - node.lineno + 1
    return out


@pytest.mark.parametrize("folder", ["acquire", "calib"])
def test_no_class_exceeds_400_lines(folder):
    assert not _long_classes(folder, 400), f"split these classes by what they hold: {_long_classes(folder, 400)}"


def test_the_class_length_check_counts_lines(tmp_path, monkeypatch):
    monkeypatch.setattr(f"{__name__}.ROOT", tmp_path)
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "big.py").write_text("class Big:\n" + "    x = 1\n" * 401)
    assert _long_classes("pkg", 400) == {"pkg/big.py:1 Big": 402}


def test_the_simulated_cell_carries_its_cell_files_allowances_in_the_commander_url(tmp_path):
    """The timing a simulated controller needs is a property of its cell file (wall ms), carried
    in the commander URL in the commander's clock (simulated ms = wall ms × time scale)."""
    from drivers.kuka_fri.commander import FriCommander
    from drivers.protocols import JointLimits
    from drivers.sim.running import SimulatedCell

    doc = yaml.safe_load((ROOT / "fixtures" / "sim" / "default.yaml").read_text())
    doc["robot"] = str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    doc["allowances"] = {"silence_ms": 250, "state_age_ms": 400}
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with SimulatedCell(path, time_scale=2.0, sensors=[("mocap", "natnet")]) as sim:
        cell = sim.describe("fri", [("mocap", "natnet", "natnet://192.0.2.1:1510")])
        assert cell.commander_url == f"fri://127.0.0.1:{sim.port}?timeout_ms=500&max_state_age_ms=800"
        assert cell.sensor_urls["mocap"] == sim.launch.addresses["mocap"].url != "natnet://192.0.2.1:1510"
        assert cell.time_scale == 2.0 and cell.clock == sim.clock.now
        cmd = FriCommander.from_url(cell.commander_url, limits=JointLimits.from_model(sim.model))
        assert (cmd.receive_timeout_s, cmd.max_state_age_s) == (0.5, 0.8)
        with pytest.raises(ValueError, match="speaks fri"):
            sim.describe("rsi", [])
        with pytest.raises(ValueError, match="no such device"):
            sim.describe("fri", [("x", "emscon", "emscon://192.0.2.1:700")])
