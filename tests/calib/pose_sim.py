"""A simulated 6-DoF cell for the pose tests and studies: a tracker measuring a T-Mac-like target
(position of its origin and orientation of its frame) on a robot whose true kinematics differ
from its model. Only the dataset leaves this module; the truth is returned separately."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.measure.dataset import Dataset, from_arrays
from calib.robot.kinematics import Chain
from calib.robot.transforms import exp_so3, pose_to_matrix

#: Tracker placement relative to the robot base (mm, ZYX degrees), about 1.5 m away as in the paper.
BASE2SENSOR = pose_to_matrix(np.array([1500.0, 250.0, -350.0]), np.radians([165.0, 2.0, -1.5]))


@dataclass(frozen=True)
class PoseCell:
    """truth: the chain parameter vector of the real arm; frame: R_flange←target (3, 3);
    base2sensor: (4, 4); noise_mm / noise_deg: per-axis measurement noise."""

    truth: np.ndarray
    frame: np.ndarray
    base2sensor: np.ndarray
    noise_mm: float
    noise_deg: float


def measure_poses(chain: Chain, q: np.ndarray, cell: PoseCell, rng: np.random.Generator, *, marker: str | None = None,
                  sensor: str = "tracker") -> Dataset:
    """One pose row per configuration q (k, n) rad: the target's origin (``marker``, default the
    model's first) and its frame, seen by the tracker, with Gaussian noise (position per axis,
    attitude as a rotation vector per axis) and the noise levels as the rows' stated spreads."""
    marker = marker or chain.marker_names[0]
    m = chain.marker_names.index(marker)
    k = q.shape[0]
    p = chain.marker_positions(q, cell.truth)[:, m]
    r_f, _ = chain.flange_pose(q, cell.truth)
    b2s = cell.base2sensor
    xyz = p @ b2s[:3, :3].T + b2s[:3, 3] + rng.normal(0.0, cell.noise_mm, (k, 3))
    rot = exp_so3(rng.normal(0.0, np.radians(cell.noise_deg), (k, 3))) @ b2s[:3, :3] @ r_f @ cell.frame
    return from_arrays(q, xyz, marker=marker, sensor=sensor, std_mm=np.full(k, cell.noise_mm),
                       rot=rot, att_std_rad=np.full(k, np.radians(cell.noise_deg)))


def perturb(chain: Chain, names: list[str], rng: np.random.Generator, length_mm: float, angle_deg: float) -> np.ndarray:
    """Nominal parameters with the named link parameters and offsets off by N(0, length_mm) / N(0, angle_deg)."""
    truth = chain.nominal.copy()
    for n in names:
        if n not in chain.param_names:
            continue
        i = chain.param_names.index(n)
        kind = n.rsplit(".", 1)[1]
        if kind in ("offset", "alpha", "beta"):
            truth[i] += np.radians(rng.normal(0.0, angle_deg))
        elif kind in ("d", "a"):
            truth[i] += rng.normal(0.0, length_mm)
    return truth


#: The pose-selection paper's identified errors of its TX60 (Table 5): per joint θ (rad), d (mm),
#: a (mm), α (rad), β (rad); None where the paper leaves the parameter out.
TX60_TABLE5 = [
    (-3.2792e-4, -0.2226, -0.2389, 5.3341e-5, None),
    (7.8894e-4, None, 0.3223, -5.4318e-5, 3.8910e-5),
    (2.3603e-4, 0.0826, 0.0484, 3.7122e-4, None),
    (0.0014, 0.2044, -0.0812, 1.1155e-4, None),
    (5.1444e-4, 7.4762e-5, 0.0205, 3.9926e-5, None),
    (4.0758e-4, -0.0624, -0.1351, 0.0033, None),
]


def tx60_paper_truth(chain: Chain) -> np.ndarray:
    """The TX60 model's parameters with the paper's Table 5 errors added (θ as zero-offsets)."""
    truth = chain.nominal.copy()
    for i, row in enumerate(TX60_TABLE5):
        for kind, v in zip(("offset", "d", "a", "alpha", "beta"), row):
            if v is not None:
                truth[chain.param_names.index(f"{chain.model.axis_names[i]}.{kind}")] += v
    return truth
