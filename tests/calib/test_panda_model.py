"""The shipped Franka Panda model works for what it ships for: a socket calibration. (Its forward
kinematics against the URDF: tests/calib/test_fk_reference.py.)"""

from pathlib import Path

import numpy as np

from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.fit.socket import fit_socket
from socket_sim import equivalent_ball, simulate, true_params  # tests/calib is on sys.path under pytest

PANDA = Path(__file__).resolve().parents[2] / "fixtures" / "robots" / "franka_panda.yaml"


def test_panda_model_is_the_published_geometry_with_the_socket_ball():
    model = load_robot_model(PANDA)
    assert model.n_joints == 7 and model.tool.markers[0].name == "ball"
    assert [j.a for j in model.joints] == [0, 0, 82.5, -82.5, 0, 88, 0]
    assert [j.d for j in model.joints] == [333, 0, 316, 0, 384, 0, 0] and model.flange.xyz == (0, 0, 107)
    assert model.joints[3].limits == (-176, -4)  # the elbow is never straight


def test_a_simulated_panda_socket_cell_is_recovered_within_its_intervals():
    """Three seeded Panda cells (offsets, link errors of 0.2 mm / 0.02°, a ball 40 mm out, play
    0.1 mm): the socket fit finds the hidden offsets and the ball within their 95 % intervals
    for nearly all fitted parameters, and A2–A6's offsets are determined (A1 is the base's turn)."""
    model = load_robot_model(PANDA)
    chain = Chain(model)
    hits = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        truth = true_params(chain, rng)
        ds, _ = simulate(model, truth, rng)
        fit = fit_socket(model, ds, tolerance=(0.2, 0.02))
        ms = chain.marker_slice()
        truth[ms.start:ms.start + 3] = equivalent_ball(chain, truth)
        assert {f"A{i}.offset" for i in range(2, 7)} <= set(fit.free_names), fit.free_names
        assert "A1.offset" in fit.excluded
        for name in fit.free_names:
            i = chain.param_names.index(name)
            hits.append(abs(fit.params[i] - truth[i]) <= 1.96 * fit.std[i])
    assert np.mean(hits) >= 0.85, np.mean(hits)
