"""``acquire fleet``: the table (and --json) with each robot's state, the index and per-robot pages
(parsed back), ``enter`` and its refusals."""

import json
import os
import subprocess
import sys
from datetime import datetime, timezone
from html.parser import HTMLParser
from pathlib import Path

import pytest

from acquire.station.fleet import fleet_rows, index_page, robot_page
from acquire.station.history import add_entry, mark_entered

ROOT = Path(__file__).resolve().parents[3]
JOINTS = ["A1", "A2", "A7"]
NOW = datetime(2026, 3, 1, tzinfo=timezone.utc)


def _entry(run_id, day, offsets, kind="calibration", std=(0.01, 0.01, None)):
    return {"run_id": run_id, "finished": f"2026-02-{day:02d}T00:00:00+00:00", "site": "plant-a", "cell": "c1",
            "kind": kind, "n_configurations": 40 if kind == "calibration" else 8, "entered": kind == "calibration",
            "joints": JOINTS, "offsets_deg": list(offsets), "std_deg": list(std), "ci95_deg": [None] * 3,
            "accuracy_mm": {"before": 0.9 if kind == "calibration" else 0.3, "after": 0.25}, "drift": None}


def _archive(tmp_path):
    # calibrated (found −0.186 on A1, entered), then a check finds A1 moved by 0.2°: drifted.
    add_entry(tmp_path, "R-1", _entry("cal1", 1, [-0.186, 0.0, None]))
    add_entry(tmp_path, "R-1", _entry("chk1", 20, [0.2, 0.0, None], "check"))
    # calibrated, a stable check.
    add_entry(tmp_path, "R-2", _entry("cal2", 1, [0.05, 0.0, None]))
    add_entry(tmp_path, "R-2", _entry("chk2", 20, [0.003, -0.002, None], "check"))
    (tmp_path / ".station").mkdir()
    (tmp_path / ".station" / "cells.json").write_text(json.dumps({"cells": [
        {"site": "plant-a", "cell": "c1", "alive": True, "last_error": None}]}))


class Tables(HTMLParser):
    """Rows of every table (by id) as lists of cell texts, and text by element id."""

    def __init__(self, page: str) -> None:
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self.by_id: dict[str, str] = {}
        self.markers = 0
        self._table = self._row = self._cell = self._id = None
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self._table = self.tables.setdefault(a.get("id", ""), [])
        elif tag == "tr" and self._table is not None:
            self._row = []
            self._table.append(self._row)
        elif tag in ("td", "th") and self._row is not None:
            self._cell = ""
        elif tag == "circle" and a.get("class") == "marker":
            self.markers += 1
        if "id" in a and tag != "table":
            self._id = a["id"]
            self.by_id[self._id] = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append(self._cell.strip())
            self._cell = None
        elif tag == "table":
            self._table = None
        elif tag in ("p", "ul"):
            self._id = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data
        if self._id is not None:
            self.by_id[self._id] += data


def _acquire(*args):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "acquire", *args], capture_output=True, text=True, env=env,
                          timeout=120)


def test_the_table_gives_each_robot_its_state_and_exits_3_when_one_needs_action(tmp_path):
    _archive(tmp_path)
    rows = {r["robot_serial"]: r for r in fleet_rows(tmp_path, now=NOW)}
    assert rows["R-1"]["state"] == "drifted" and rows["R-1"]["axes"] == ["A1"]
    assert rows["R-2"]["state"] == "calibrated" and rows["R-1"]["cell_state"] == "up"
    out = _acquire("fleet", "--archive", str(tmp_path), "--json", "--html", str(tmp_path / "html"))
    assert out.returncode == 3, out.stderr
    assert [r["robot_serial"] for r in json.loads(out.stdout)] == ["R-1", "R-2"]
    assert (tmp_path / "html" / "index.html").exists() and (tmp_path / "html" / "R-1.html").exists()


def test_the_index_lists_every_robot_with_its_state_worst_first(tmp_path):
    _archive(tmp_path)
    add_entry(tmp_path, "R-3", _entry("x1", 2, [None, None, None], "check", std=(None, None, None)))
    (tmp_path / ".index").mkdir()   # what the scrub leaves for a damaged copy (acquire.station.archive)
    (tmp_path / ".index" / "plant-a~c1~cal2.json").write_text(
        json.dumps({"folder": "R-2/2026-02-01/cal2", "damaged": ["cal2.mcap"]}))
    page = Tables(index_page(tmp_path, now=NOW))
    rows = page.tables["robots"][1:]
    assert [(r[0], r[2]) for r in rows] == [("R-1", "drifted"), ("R-3", "never calibrated"), ("R-2", "calibrated")]
    assert "A1 +0.2000°" in rows[0][3]
    assert page.by_id["summary"] == "1 drifted, 1 never calibrated, 1 calibrated"
    assert rows[2][7] == "cal2: cal2.mcap (awaiting a copy from the cell)" and rows[0][7] == "ok"


def test_a_robot_page_plots_offsets_as_delta_from_the_reference_and_says_what_is_undetermined(tmp_path):
    _archive(tmp_path)
    page = Tables(robot_page(tmp_path, "R-1", now=NOW))
    assert page.by_id["state"] == "drifted"
    runs = page.tables["runs"]
    head = runs[0]
    cal, chk = (dict(zip(head, r)) for r in runs[1:])
    # The reference sits at Δ 0 (its −0.186 is what was entered), the check at +0.2 beyond its threshold.
    assert cal["Δ A1 (deg)"] == "+0.0000 ± 0.0200" and cal["verdict"] == "reference"
    assert chk["Δ A1 (deg)"] == "+0.2000 ± 0.0200 / thr 0.0424 BEYOND"
    assert chk["Δ A2 (deg)"] == "+0.0000 ± 0.0200 / thr 0.0424"
    assert chk["Δ A7 (deg)"] == "undetermined" and "offsets moved" in chk["verdict"]
    assert "A7: no Δ to plot — undetermined in every run (cal1, chk1)" in page.by_id["notes"]
    assert page.markers == 4   # 2 runs × the 2 determined axes
    stable = Tables(robot_page(tmp_path, "R-2", now=NOW))
    chk2 = dict(zip(stable.tables["runs"][0], stable.tables["runs"][2]))
    assert chk2["Δ A1 (deg)"] == "+0.0030 ± 0.0200 / thr 0.0424" and chk2["verdict"] == "offsets ok"


def test_enter_makes_a_run_the_reference_and_refuses_unknown_runs_and_checks(tmp_path):
    _archive(tmp_path)
    add_entry(tmp_path, "R-1", _entry("cal3", 25, [0.2, 0.0, None]))
    add_entry(tmp_path, "R-1", _entry("cal3", 25, [0.2, 0.0, None]) | {"entered": False})
    assert _acquire("fleet", "enter", "R-1", "cal3", "--archive", str(tmp_path)).returncode == 0
    assert fleet_rows(tmp_path, now=NOW)[0]["reference"]["run_id"] == "cal3"
    with pytest.raises(ValueError, match="has no run 'nope'"):
        mark_entered(tmp_path, "R-1", "nope")
    check = _acquire("fleet", "enter", "R-1", "chk1", "--archive", str(tmp_path))
    assert check.returncode == 2 and "measured 8 configurations; a reference needs at least 13" in check.stderr
