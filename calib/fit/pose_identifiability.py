"""What measured orientations make identifiable that positions alone do not.

Builds the identification's Jacobian (``calib.fit.identification``) twice for the same rows —
positions only, and positions with their attitude rows (rotation vectors, weighted by the stated
spreads) — and compares them with ``calib.plan.identifiability.orientation_gain``. Every column
of the identification is kept (registration, markers, targets' frames, offsets, links), so a
parameter is reported as determined only if no combination of the others can stand in for it.
Classic answer it reproduces: one marker on the last joint's axis never moves with that joint's
offset, while the target's orientation turns with it — when the target's frame on the flange is
known (the model's ``rpy_deg`` with rotation prior 0), that offset is determined by orientation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calib.fit.identification import IdentOptions, _excluded_by_choice, _Problem
from calib.fit.offsets import initial_registrations
from calib.measure.dataset import Dataset
from calib.plan.identifiability import OrientationGain, orientation_gain
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel


def pose_identifiability(model: RobotModel, data: Dataset, options: IdentOptions = IdentOptions()) -> OrientationGain:
    """``OrientationGain`` of ``data``'s pose rows over its positions, for the columns the
    identification would consider (those excluded by the options or the convention left out)."""
    if not data.has_orientation:
        raise ValueError(f"{data.source or 'the dataset'} has no measured orientation (columns qw, qx, qy, qz)")
    chain = Chain(model)
    b2s0 = initial_registrations(chain, data, options.initial_registration, 0)
    poses = _Problem(chain, data, b2s0, None, options.orientation_weight)
    excluded = _excluded_by_choice(model, chain, poses.names, options)
    x0 = np.zeros(len(poses.names))
    x0[: poses.P] = chain.nominal
    _, j = poses.residuals_and_jacobian(x0)
    keep = [i for i, n in enumerate(poses.names) if n not in excluded]
    names = [poses.names[i] for i in keep]
    lever = float(np.sqrt(np.mean(np.sum(chain.marker_positions(data.q_rad) ** 2, axis=-1))))
    scale = poses.scale(lever)[keep]
    n_pos = 3 * len(data)
    j = j[:, keep]
    gain = orientation_gain(j[:n_pos], j, names, scale, rel_tol=options.rank_tol)
    # The targets' frames are seen by attitude rows only: trivially "new"; not what the report is about.
    return replace(gain, newly_determined=[n for n in gain.newly_determined if ".frame_" not in n])
