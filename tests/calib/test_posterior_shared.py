"""Posteriors of one fit that differ only in their masks share the data's set-up
(``OffsetPosterior(shared=…)``): the same numbers as a posterior that computes its own, and the
second posterior computes none of it again."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.fit.offsets import initial_registrations
from calib.fit.posterior import OffsetPosterior, ParamMask
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from tests.calib.pose_sim import BASE2SENSOR, PoseCell, measure_poses, perturb

ROBOT = Path(__file__).resolve().parents[2] / "fixtures/robots/kuka_iiwa14_r820.yaml"


def test_posteriors_sharing_their_set_up_give_the_numbers_of_one_alone():
    model = load_robot_model(ROBOT)  # with link masses: the compliance terms
    chain = Chain(model)
    rng = np.random.default_rng(7)
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    q = lo + (hi - lo) * rng.uniform(0.15, 0.85, (14, chain.n))
    truth = perturb(chain, [f"{a}.offset" for a in model.axis_names], rng, 0.0, 0.1)
    data = measure_poses(chain, q, PoseCell(truth, np.eye(3), BASE2SENSOR, 0.03, 0.01), rng)  # attitude rows too
    b2s0 = initial_registrations(chain, data, "least-squares", 0)
    reg = np.ones((1, 6), bool)
    every = ParamMask(np.ones(chain.n, bool), reg, compliance=np.ones(chain.n, bool))
    fewer = ParamMask(np.r_[np.ones(chain.n - 1, bool), False], reg, compliance=np.r_[np.ones(2, bool), np.zeros(chain.n - 2, bool)])
    shared: dict = {}
    first = OffsetPosterior(chain, data, b2s0, every, compliance=True, shared=shared)
    second = OffsetPosterior(chain, data, b2s0, fewer, compliance=True, shared=shared)
    assert second._offset_fk is first._offset_fk and second._sag is first._sag  # computed once
    assert second.attitude.sag_w is first.attitude.sag_w
    for mask, post in ((every, first), (fewer, second)):
        alone = OffsetPosterior(chain, data, b2s0, mask, compliance=True)
        for theta in (np.zeros(post.dim), rng.normal(0.0, 1e-3, post.dim)):
            np.testing.assert_array_equal(post.residuals(theta), alone.residuals(theta))
            np.testing.assert_array_equal(post.jacobian(theta), alone.jacobian(theta))
        np.testing.assert_array_equal(post.torques, alone.torques)
