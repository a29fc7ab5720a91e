"""A simulated laser-tracker cell shaped like a real calibration: a nest plate on the flange
with three reflector nests for the calibration and a fourth for validation, 30–40 calibration
configurations, a true arm with link errors, a plate mounted only roughly where the model says
(the nests' layout on the plate is machined and right; the plate's pose on the flange is off by
up to 10 mm at the nests), and tracker noise of a few hundredths of a mm."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.measure.dataset import Dataset, from_arrays
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel, load_robot_model, robot_model_from_dict
from calib.robot.transforms import apply, pose_to_matrix
from tests.calib.test_identification import ROBOTS

#: Nests on the plate, flange frame of the model (mm): three for the calibration, one for validation.
PLATE_MM = {"n1": (70.0, 0.0, 25.0), "n2": (-35.0, 60.0, 25.0), "n3": (-35.0, -60.0, 25.0), "n4": (0.0, 0.0, 60.0)}
CAL_NESTS = ("n1", "n2", "n3")
TRACKER2BASE_POSE = (np.array([2200.0, -600.0, -150.0]), np.radians([160.0, 4.0, -3.0]))


@dataclass
class TrackerCell:
    model: RobotModel  # what the user gives the fit: nominal arm, the plate where the drawing puts it
    truth: np.ndarray  # the true arm's full Chain vector, the true nests (mm) in its flange frame
    base2sensor: np.ndarray  # (4, 4) the tracker's true pose
    cal: Dataset
    val: Dataset


def plate_model(robot: str = "staubli_tx60") -> RobotModel:
    d = load_robot_model(ROBOTS / f"{robot}.yaml").model_dump()
    d["tool"] = {"name": "nest plate", "markers": [{"name": k, "xyz": v, "kind": "retroreflector"} for k, v in PLATE_MM.items()]}
    return robot_model_from_dict(d)


def rigid_plate_error(rng: np.random.Generator, max_mm: float = 10.0) -> np.ndarray:
    """A plate mounting error (4, 4): a rotation of a few degrees and a shift, scaled so that the
    nest it moves most moves about ``max_mm`` · U(0.6, 1) (the scaling is linear in the angles)."""
    shift, angles = rng.normal(0.0, 4.0, 3), np.radians(rng.normal(0.0, 3.0, 3))
    nests = np.array(list(PLATE_MM.values()))
    worst = np.linalg.norm(apply(pose_to_matrix(shift, angles), nests) - nests, axis=1).max()
    s = max_mm * rng.uniform(0.6, 1.0) / worst
    return pose_to_matrix(shift * s, angles * s)


def link_errors(chain: Chain, rng: np.random.Generator, length_mm: float, angle_deg: float) -> np.ndarray:
    """Offsets, d, a, α (and β for mdh) perturbed by N(0, sd); the registration-like first link too."""
    p = chain.nominal.copy()
    n = chain.n
    p[:n] += np.radians(rng.normal(0.0, angle_deg, n))
    for kind, sd in (("d", length_mm), ("a", length_mm), ("alpha", np.radians(angle_deg)), ("beta", np.radians(angle_deg))):
        p[chain.index(kind)] += rng.normal(0.0, sd, n)
    if chain.model.convention == "dh":
        p[chain.index("beta")] = 0.0
    return p


def configurations(model: RobotModel, rng: np.random.Generator, k: int, fraction: float = 0.75) -> np.ndarray:
    return rng.uniform(model.lower_limits_rad * fraction, model.upper_limits_rad * fraction, (k, model.n_joints))


def observe(chain: Chain, q: np.ndarray, params: np.ndarray, nests: tuple[str, ...], base2sensor: np.ndarray,
            rng: np.random.Generator, noise_mm: float, split: str) -> Dataset:
    """Every nest of ``nests`` in every configuration as the tracker reports it (mm)."""
    idx = [chain.marker_names.index(n) for n in nests]
    p = chain.marker_positions(q, params)[:, idx]  # (k, len(nests), 3)
    xyz = apply(base2sensor, p.reshape(-1, 3)) + rng.normal(0.0, noise_mm, (p.shape[0] * len(nests), 3))
    return from_arrays(np.repeat(q, len(nests), axis=0), xyz, marker=np.tile(np.array(nests), q.shape[0]),
                       config=np.repeat(np.arange(q.shape[0]), len(nests)).astype(str), split=split)


def tracker_cell(seed: int, *, robot: str = "staubli_tx60", k_cal: int = 36, k_val: int = 40, link_mm: float = 0.3,
                 angle_deg: float = 0.05, plate_mm: float = 10.0, noise_mm: float = 0.03) -> TrackerCell:
    rng = np.random.default_rng(seed)
    model = plate_model(robot)
    chain = Chain(model)
    truth = link_errors(chain, rng, link_mm, angle_deg)
    ms = chain.marker_slice()
    nominal_nests = truth[ms].reshape(-1, 3)
    truth[ms] = apply(rigid_plate_error(rng, plate_mm), nominal_nests).ravel()
    b2s = np.linalg.inv(pose_to_matrix(*TRACKER2BASE_POSE))
    cal = observe(chain, configurations(model, rng, k_cal), truth, CAL_NESTS, b2s, rng, noise_mm, "cal")
    val = observe(chain, configurations(model, rng, k_val, 0.6), truth, ("n4",), b2s, rng, noise_mm, "val")
    return TrackerCell(model, truth, b2s, cal, val)
