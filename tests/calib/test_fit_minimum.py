"""`min_configurations` (what a plan is checked against) agrees with what `fit_offsets` accepts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.measure.dataset import DatasetError, read_csv
from calib.fit.offsets import FitOptions, fit_offsets, min_configurations
from calib.robot.model import load_robot_model

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
DATA = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", IIWA)


def first_configurations(k: int):
    """k configurations of k different pose groups (the branches of one pose share the flange
    position: three of them would be collinear points)."""
    first_of_pose = {}
    for c, pose in zip(DATA.config.tolist(), DATA.pose.tolist()):
        first_of_pose.setdefault(pose, c)
    keep = list(first_of_pose.values())[:k]
    assert len(keep) == k
    return DATA.subset(np.isin(DATA.config, keep))


@pytest.mark.parametrize("joints, fixed", [(None, False), ((2, 3), False), ((2,), True)])
def test_the_fit_refuses_one_configuration_fewer_and_accepts_the_minimum(joints, fixed):
    assert len(DATA) == len(set(DATA.config.tolist()))  # one marker, one sensor: a row per configuration
    need = min_configurations(len(joints) if joints else IIWA.n_joints, [1], fix_registration=fixed)
    options = FitOptions(joints=joints, fix_registration=fixed, link_tolerance=None, n_chains=2, n_draws=50)
    with pytest.raises(DatasetError, match="measure at least|a registration needs at least"):
        fit_offsets(IIWA, first_configurations(need - 1), options)
    result = fit_offsets(IIWA, first_configurations(need), options)  # past the count checks: a result
    assert result.applied_offsets_rad.shape == (IIWA.n_joints,)


def test_more_markers_per_configuration_need_fewer_configurations():
    assert min_configurations(7, [1]) == 10
    assert min_configurations(7, [2]) == 5
    assert min_configurations(7, [1, 1]) == 7  # a second sensor: its registration and σ, and its rows
    with pytest.raises(ValueError, match="at least one marker"):
        min_configurations(7, [])
