"""Simulated tracker cells with the nuisances of a real cell, for the model-choice study (issue 22):
a KUKA LBR iiwa 14 (its model carries link masses, so the arm sags and the compliance candidates
compete) with a three-nest plate (``tests.calib.tracker_sim``), and per cell

* zero-offsets ~ N(0, 0.1°) on every axis;
* the tool 5–30 mm off its drawing in a random direction, not declared;
* link errors of a Franka Panda's size (its published corrections: 0.2–0.9 mm, 0.1–0.66°): every
  d and a off by ±U(0.2, 0.9) mm, every α by ±U(0.1, 0.66)°;
* joint sag under the arm's own weight, compliances 6e-6 rad/(N·m) on axes 1–4 and 1.2e-5 on
  5–7 (the simulated cell's, ``fixtures/sim/default.yaml``), each ×U(0.5, 1.5);
* in every other cell one configuration 0.3–1 mm off (a nest not seated, a bump);
* tracker noise 0.02 mm per sample, 20 samples averaged per row (``std_mm`` the spread of one).

The truth is returned so the study can score the fit's intervals and its predictions; nothing
in ``calib`` sees it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib.measure.dataset import Dataset
from calib.robot.gravity import gravity_torques
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.robot.transforms import apply, pose_to_matrix
from tests.calib.tracker_sim import CAL_NESTS, TRACKER2BASE_POSE, configurations, plate_model

ROBOT = "kuka_iiwa14_r820"
SAMPLES = 20
NOISE_MM = 0.02  # per sample, per axis
K_NOMINAL = np.array([6e-6] * 4 + [1.2e-5] * 3)  # rad/(N·m)


@dataclass
class NuisanceCell:
    model: RobotModel  # what the user gives the fit
    truth: np.ndarray  # (P,) the true arm's chain vector (offsets, links, true nests)
    compliance: np.ndarray  # (n,) rad/(N·m)
    base2sensor: np.ndarray  # (4, 4)
    cal: Dataset
    val: Dataset  # held-out configurations (the same nests), never fitted
    tool_mm: float
    outlier_mm: float
    outlier_config: str | None

    @property
    def noise_mm(self) -> float:
        """Per axis, of one averaged row."""
        return NOISE_MM / np.sqrt(SAMPLES)

    def true_positions(self, q: np.ndarray, markers: np.ndarray) -> np.ndarray:
        """(k, 3) mm in the sensor frame: the true arm, sagging, at commanded q (k, n)."""
        chain = Chain(self.model)
        q_true = q + chain.sign * self.compliance * gravity_torques(chain, q, self.truth)
        pos = chain.marker_positions(q_true, self.truth)
        idx = [chain.marker_names.index(m) for m in markers]
        return apply(self.base2sensor, pos[np.arange(len(q)), idx])


def _observe(cell: NuisanceCell, q: np.ndarray, rng: np.random.Generator, split: str) -> Dataset:
    from calib.measure.dataset import from_arrays

    k = q.shape[0]
    qq = np.repeat(q, len(CAL_NESTS), axis=0)
    markers = np.tile(np.array(CAL_NESTS), k)
    xyz = cell.true_positions(qq, markers) + rng.normal(0.0, cell.noise_mm, (len(qq), 3))
    ds = from_arrays(qq, xyz, marker=markers, config=np.array([f"{split}{i}" for i in np.repeat(np.arange(k), len(CAL_NESTS))]),
                     split=split)
    return replace(ds, std_mm=np.full(len(ds), NOISE_MM), count=np.full(len(ds), SAMPLES))


def nuisance_cell(seed: int, *, k_cal: int = 36, k_val: int = 40, outlier: bool | None = None,
                  offset_deg: float = 0.1) -> NuisanceCell:
    """Cell ``seed`` (see the module's docstring); ``outlier``: None — every other seed;
    ``offset_deg``: sd of the zero-offsets (the same draws scaled: a cell that lost its mastering)."""
    rng = np.random.default_rng(5000 + seed)
    model = plate_model(ROBOT)
    chain = Chain(model)
    truth = chain.nominal.copy()
    n = chain.n
    truth[:n] = np.radians(rng.normal(0.0, offset_deg, n))
    for kind in ("d", "a"):
        truth[chain.index(kind)] += rng.choice([-1.0, 1.0], n) * rng.uniform(0.2, 0.9, n)
    truth[chain.index("alpha")] += np.radians(rng.choice([-1.0, 1.0], n) * rng.uniform(0.1, 0.66, n))
    shift = rng.normal(size=3)
    tool_mm = rng.uniform(5.0, 30.0)
    shift *= tool_mm / np.linalg.norm(shift)
    ms = chain.marker_slice()
    truth[ms] = (truth[ms].reshape(-1, 3) + shift).ravel()
    compliance = K_NOMINAL * rng.uniform(0.5, 1.5, n)
    b2s = np.linalg.inv(pose_to_matrix(*TRACKER2BASE_POSE))
    cell = NuisanceCell(model, truth, compliance, b2s, None, None, tool_mm, 0.0, None)  # type: ignore[arg-type]
    cell.cal = _observe(cell, configurations(model, rng, k_cal), rng, "cal")
    cell.val = _observe(cell, configurations(model, rng, k_val, 0.6), rng, "val")
    if (seed % 2 == 1) if outlier is None else outlier:
        cell.outlier_mm = float(rng.uniform(0.3, 1.0))
        cell.outlier_config = str(cell.cal.config[rng.integers(len(cell.cal))])
        bad = cell.cal.config == cell.outlier_config
        direction = rng.normal(size=3)
        cell.cal.xyz_mm[bad] += cell.outlier_mm * direction / np.linalg.norm(direction)
    return cell
