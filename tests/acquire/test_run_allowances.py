"""Whole runs with the cell's timing allowances at 1500 ms (issue 32), against the simulated cell's
fake Sunrise speaking FRI 1.15, 2.5 and 2.7.

Seen: with the allowances raised to 1500 ms (as advised for busy hosts), 5 of 5 runs failed at
the start with "move refused: a move is already in progress; stop() it first". The driver-level
cause found (a move that timed out on a controller whose messages came late was reported
"stopped" while its stop still ran) is tested cheaply in
``tests/drivers/kuka_fri/test_fri_faults.py``
(``test_a_move_timed_out_on_a_late_controller_is_over_when_reported_and_the_next_one_starts``).
These whole runs keep the outcome true: every configuration measured, nothing refused or failed,
no move ever found another still running. They did not fail on this repository's host before
the fix either (the refusal was not reproduced in whole runs; see docs/how-to/faults.md).

Each run is ~15–30 s of wall time (slow selection).
"""

from __future__ import annotations

import pytest
import yaml

from acquire.plan.schema import load_plan
from acquire.record.recorder import read_run

from run_helpers import ROOT, RUN_TIMEOUT_S, fake_controller, small_plan, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest
from test_run_faults import assert_complete  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.timeout(RUN_TIMEOUT_S)]

ALLOWANCES = {"silence_ms": 1500, "state_age_ms": 1500}
TIME_SCALE = 3.0


def plan_at_1500_ms(tmp_path, fri_version: str):
    """The example plan, shrunk (8 configurations), on a copy of the default cell whose allowances
    are 1500 ms and whose fake Sunrise speaks ``fri_version``."""
    cell = yaml.safe_load((ROOT / "fixtures" / "sim" / "default.yaml").read_text())
    cell["robot"] = str((ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").resolve())
    cell["allowances"] = ALLOWANCES
    cell["controller"] = {**(cell.get("controller") or {}), "fri_version": fri_version}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell, sort_keys=False))
    return load_plan(small_plan(tmp_path, n=4, fake={"sim_config": str(tmp_path / "cell.yaml"),
                                                     "time_scale": TIME_SCALE}))


@pytest.mark.parametrize("fri_version", ["1.15", "2.5", "2.7"])
def test_a_whole_run_with_the_cells_allowances_at_1500_ms_completes(tmp_path, fri_version):
    lp = plan_at_1500_ms(tmp_path, fri_version)
    rc = fake_controller(lp, fit=False)
    # the run is handed the cell's allowances (wall ms × time scale: the commander's clock is the cell's)
    assert rc.cell.commander_url.endswith("?timeout_ms=4500&max_state_age_ms=4500"), rc.cell.commander_url
    rc.start()
    summary = wait_for_run(rc)
    contents = read_run(summary.log_path)
    assert_complete(lp, summary, contents)
    assert summary.failed == 0 and summary.skipped == 0
    reasons = " ".join(f"{e.get('reason', '')} {' '.join(e.get('not_ready') or [])}" for e in contents.events)
    assert "already in progress" not in reasons and "still ending" not in reasons
    assert f"FRI {fri_version}" in " ".join(rc.cell.notes)  # the fake Sunrise spoke the version asked for
