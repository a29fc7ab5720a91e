"""The fit's linearised model over a plan's candidate configurations, for the sequential design
(``calib.plan.adaptive``): the same free parameters, priors and fixed combinations as the fit
(``calib.fit.offsets.fit_mode``), its Jacobian at the nominal robot per candidate, and the
workspace matrix (the plan's configurations as the sensor sees them).

The fit's parameter set is found by setting up ``fit_mode`` on the nominal marker positions of
every candidate (with a small seeded noise, so the fit's σ is finite): what it fixes (the first
axis against the registration, the last axis against the tool) is what the full plan cannot
determine, and is left out of the stop rule.
"""

from __future__ import annotations

import math

import numpy as np

from calib.fit.offsets import FitOptions, _prior_precision, fit_mode
from calib.measure.dataset import from_arrays
from calib.plan.adaptive import DesignModel
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel

#: Weak prior sds of the parameters the fit leaves flat, so the covariance exists before the
#: first configuration: offsets (deg), registration translation (mm) and rotation (deg),
#: compliances (µrad/(N·m)). Each is far wider than anything a measured plan leaves.
FLAT_PRIOR = {"offset": 5.0, "translation": 1000.0, "rotation": 30.0, "compliance": 1000.0}


def design_model(model: RobotModel, q_rad: np.ndarray, sensors: dict[str, list[str]],
                 options: FitOptions = FitOptions(), *, seed: int = 0, plan_size: int | None = None,
                 joint_space_q: np.ndarray | None = None) -> DesignModel:
    """The linearised fit over candidates ``q_rad`` (N, n) rad, each measured by every sensor's
    markers (``sensors``: name → marker names on the tool). Rows of a candidate: 3 per (sensor,
    marker), in the sensor's frame (the registration at identity: the information does not
    depend on where the sensor stands, only on the robot's configurations).

    plan_size: the first this many candidates are the plan's configurations, the rest a pool of
    generated ones (the plan's ``adaptive.candidates``): the workspace (what the stop rule's
    errors average over) and the full plan stay the plan's [None: every candidate].
    joint_space_q: (M, n) rad, configurations of the robot's working joint space: their matrix
    (as the workspace's) is the model's ``joint_space`` [None: none]."""
    rows, post = _linearised(model, q_rad, sensors, options, seed)
    q = np.asarray(q_rad, dtype=float)
    n_cfg = q.shape[0]
    n_plan = n_cfg if plan_size is None else int(plan_size)
    if not 1 <= n_plan <= n_cfg:
        raise ValueError(f"plan_size must be 1…{n_cfg} (the candidates), given {plan_size}")
    n_pairs = rows.shape[1] // 3
    prior = _prior_precision(post)
    offsets = []
    for k, name in enumerate(post.free_names):
        kind = name.rsplit(".", 1)[1]
        if k < post.n and post.free[k] < post.n:
            offsets.append(k)
        if name.split(".")[0] in post.sensors:
            sd = FLAT_PRIOR["translation"] if kind in ("x", "y", "z") else math.radians(FLAT_PRIOR["rotation"])
            prior[k, k] += 1.0 / sd**2
        elif kind == "offset":
            prior[k, k] += 1.0 / math.radians(FLAT_PRIOR["offset"]) ** 2
        elif kind == "compliance":
            prior[k, k] += 1.0 / FLAT_PRIOR["compliance"] ** 2
    # Workspace: the calibrated model's marker positions over the plan's configurations as the
    # sensor sees them — with the registration, so that what only moves the model's base frame
    # (a link length along the first axis against the registration's shift) is not counted.
    workspace = np.einsum("nri,nrj->ij", rows[:n_plan], rows[:n_plan]) / (n_plan * n_pairs)
    joint_space = None
    if joint_space_q is not None:
        js_rows, js_post = _linearised(model, joint_space_q, sensors, options, seed)
        if tuple(js_post.free_names) != tuple(post.free_names):
            raise ValueError("the working joint space's linearised fit has other free parameters than the plan's "
                             f"({len(js_post.free_names)} against {len(post.free_names)})")
        joint_space = np.einsum("nri,nrj->ij", js_rows, js_rows) / (js_rows.shape[0] * n_pairs)
    off = np.array(offsets, dtype=int)
    return DesignModel(rows=rows, prior=prior, offsets=off,
                       offset_names=tuple(post.free_names[k] for k in off), workspace=workspace,
                       names=tuple(post.free_names), plan_size=None if plan_size is None else n_plan,
                       workspace_from_candidates=True, joint_space=joint_space)


def _linearised(model: RobotModel, q_rad: np.ndarray, sensors: dict[str, list[str]], options: FitOptions,
                seed: int):
    """(rows (N, r, L) mm per unit, the fit's posterior) at the nominal robot over ``q_rad``."""
    chain = Chain(model)
    q = np.asarray(q_rad, dtype=float)
    n_cfg = q.shape[0]
    pairs = [(s, m) for s, ms in sorted(sensors.items()) for m in ms]
    if not pairs:
        raise ValueError("the design needs at least one measured marker")
    pos = chain.marker_positions(q)  # (N, M, 3)
    idx = [chain.marker_names.index(m) for _, m in pairs]
    rng = np.random.default_rng(seed)
    xyz = pos[:, idx, :].reshape(-1, 3) + rng.normal(0.0, 0.01, size=(n_cfg * len(pairs), 3))
    data = from_arrays(np.repeat(q, len(pairs), axis=0), xyz,
                       marker=np.tile(np.array([m for _, m in pairs]), n_cfg),
                       sensor=np.tile(np.array([s for s, _ in pairs]), n_cfg),
                       config=np.repeat(np.arange(n_cfg), len(pairs)).astype(str))
    post = fit_mode(model, data, options, tol=1e-6).post
    return post.jacobian(np.zeros(post.dim)).reshape(n_cfg, 3 * len(pairs), post.dim), post
