"""``acquire fleet``: the table (and --json) with drift flags, per-robot HTML pages, ``enter``."""

import json
import os
import subprocess
import sys
from pathlib import Path

from acquire.station.fleet import fleet_rows, robot_page
from acquire.station.history import add_entry

ROOT = Path(__file__).resolve().parents[3]
JOINTS = ["A1", "A2"]


def _entry(run_id, day, offsets, kind="calibration", drifted=False):
    return {"run_id": run_id, "finished": f"2026-0{day}-01T00:00:00+00:00", "site": "plant-a", "cell": "c1",
            "kind": kind, "entered": kind == "calibration", "joints": JOINTS, "offsets_deg": offsets,
            "std_deg": [0.01, 0.01], "ci95_deg": [None, None], "accuracy_mm": {"before": 0.9, "after": 0.2},
            "drift": {"drifted": drifted, "reasons": ["offsets moved: χ² = 80.0 > 9.2"] if drifted else []}}


def _archive(tmp_path):
    add_entry(tmp_path, "R-1", _entry("cal1", 1, [0.0, 0.0]))
    add_entry(tmp_path, "R-1", _entry("chk1", 2, [0.2, 0.0], "check", drifted=True))
    add_entry(tmp_path, "R-2", _entry("cal2", 1, [0.0, 0.0]))
    (tmp_path / ".station").mkdir()
    (tmp_path / ".station" / "cells.json").write_text(json.dumps({"cells": [
        {"site": "plant-a", "cell": "c1", "alive": True, "last_error": None}]}))


def _acquire(*args):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "acquire", *args], capture_output=True, text=True, env=env,
                          timeout=120)


def test_the_table_flags_the_drifted_robot_and_exits_3(tmp_path):
    _archive(tmp_path)
    rows = {r["robot_serial"]: r for r in fleet_rows(tmp_path)}
    assert rows["R-1"]["drifted"] and not rows["R-2"]["drifted"]
    assert rows["R-1"]["last_calibration"]["run_id"] == "cal1" and rows["R-1"]["cell_state"] == "up"
    out = _acquire("fleet", "--archive", str(tmp_path), "--json", "--html", str(tmp_path / "html"))
    assert out.returncode == 3, out.stderr
    assert [r["robot_serial"] for r in json.loads(out.stdout)] == ["R-1", "R-2"]
    page = (tmp_path / "html" / "R-1.html").read_text()
    assert page.count('class="marker"') == 4 and "chk1" in page  # 2 runs × 2 joints plotted


def test_enter_makes_a_run_the_reference_and_unknown_runs_are_refused(tmp_path):
    _archive(tmp_path)
    assert _acquire("fleet", "enter", "R-1", "chk1", "--archive", str(tmp_path)).returncode == 0
    assert fleet_rows(tmp_path)[0]["last_calibration"]["run_id"] == "chk1"
    bad = _acquire("fleet", "enter", "R-1", "nope", "--archive", str(tmp_path))
    assert bad.returncode == 2 and "has no run 'nope'" in bad.stderr
    assert "Robot R-2" in robot_page(tmp_path, "R-2")
