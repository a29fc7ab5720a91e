"""A plan that selects a skeleton bone (``sk:tool:plate``) runs under ``--fake``: the simulated
cell's Motive defines the tool as a skeleton (cell file ``natnet: {asset: skeleton}``) carrying
three infrared markers of the tool plate, and the bone is measured where the plate's centre is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from acquire.plan.schema import load_plan
from acquire.record.recorder import read_run
from drivers.sim.cell import SimCell

from run_helpers import ROOT, RUN_TIMEOUT_S, fake_controller, small_plan, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest

pytestmark = pytest.mark.timeout(RUN_TIMEOUT_S)

#: Three infrared markers on a plate around the paper plate's SIR position, and the plate's
#: centre (where Motive puts the bone: the centroid of its markers) as a tool point to fit.
PLATE = [
    {"name": "p1", "xyz": [-70.0, 0.0, 20.0], "kind": "infrared"},
    {"name": "p2", "xyz": [-115.0, 26.0, 20.0], "kind": "infrared"},
    {"name": "p3", "xyz": [-115.0, -26.0, 20.0], "kind": "infrared"},
    {"name": "plate", "xyz": [-100.0, 0.0, 20.0], "kind": "other"},
]

#: A short plan: three configurations near the cell's start pose (the plate faces the bar).
CONFIGS = [[5, 20, 0, -90, 0, -30, 0], [0, 25, 0, -85, 0, -30, 10], [-5, 20, 5, -90, 0, -35, 0]]


def skeleton_cell(tmp_path: Path, version: str, asset: str) -> tuple[Path, Path]:
    robot = yaml.safe_load((ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").read_text())
    robot["tool"]["markers"] = [m for m in robot["tool"]["markers"] if m["name"] == "smr"] + PLATE
    robot_path = tmp_path / "iiwa14_plate.yaml"
    robot_path.write_text(yaml.safe_dump(robot, sort_keys=False))
    cell = yaml.safe_load((ROOT / "fixtures" / "sim" / "default.yaml").read_text())
    cell["robot"] = str(robot_path)
    mocap = cell["sensors"][0]
    assert mocap["kind"] == "mocap"
    mocap["markers"] = ["p1", "p2", "p3"]
    mocap["natnet"] = {"version": version, "asset": asset, "asset_name": "tool"}
    cell_path = tmp_path / "cell.yaml"
    cell_path.write_text(yaml.safe_dump(cell, sort_keys=False))
    return robot_path, cell_path


@pytest.mark.parametrize("version, asset", [
    ("4.0", "skeleton"),
    pytest.param("4.1", "trained_markerset", marks=pytest.mark.slow),  # a second whole run; 4.1's frames are test_natnet_*'s
])
def test_a_skeleton_bone_plan_runs_under_fake(tmp_path, version, asset):
    robot, cell = skeleton_cell(tmp_path, version, asset)
    plan = small_plan(tmp_path, sequencing={"samples": 3}, fake={"sim_config": str(cell), "time_scale": 3.0})
    doc = yaml.safe_load(plan.read_text())
    doc["poses"] = {"joints": CONFIGS}
    doc["robot"] = str(robot)
    doc["sensors"][0]["markers"] = {"plate": "sk:tool:plate"}
    plan.write_text(yaml.safe_dump(doc, sort_keys=False))
    lp = load_plan(plan)
    rc = fake_controller(lp, fit=False)
    rc.start()
    summary = wait_for_run(rc)
    assert summary.state == "finished", summary.reason
    samples = read_run(summary.log_path).samples
    assert len(samples) == len(CONFIGS), f"only {len(samples)} configurations measured"
    truth = SimCell.from_yaml(cell)  # the same seed: the same hidden robot
    for rec in samples:
        (marker,) = rec["markers"]
        assert (marker["sensor"], marker["marker"], marker["count"]) == ("mocap", "plate", 3)
        q = np.radians(rec["q_measured_deg"])
        plate_mm = truth.true_marker_positions(q, frame="mocap")[truth.marker_names.index("plate")]
        np.testing.assert_allclose(marker["mean_mm"], plate_mm, atol=0.3)  # noise 0.03 mm per marker
