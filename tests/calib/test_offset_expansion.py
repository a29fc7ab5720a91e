"""The fast sampler's expanded predictor against the chain walk it stands for."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.fit.offsets import FitOptions, fit_offsets
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.fit.offset_expansion import expand_offsets
from calib.fit.posterior import EXPANSION_TOLERANCE_MM
from tests.calib.test_fit import IIWA, KR6, simulate

ROOT = Path(__file__).resolve().parents[2]
TX60 = load_robot_model(ROOT / "fixtures" / "robots" / "staubli_tx60.yaml")


def _case(model, seed: int):
    """Configurations, a reference parameter vector (offsets ~0.5°, tool as nominal) and its chain."""
    rng = np.random.default_rng(seed)
    chain = Chain(model)
    q = rng.uniform(model.lower_limits_rad, model.upper_limits_rad, (40, chain.n))
    ref = chain.with_offsets(np.radians(rng.normal(0.0, 0.5, chain.n)))
    return rng, chain, q, ref


def test_offsets_and_tool_to_third_order():
    """Every offset 2e-3 rad (a far proposal: ~5 posterior stds) and the tool 1 mm away from the
    reference: the expansion matches the chain walk within the sampler's tolerance, and halving
    the step cuts the error about eightfold (third order)."""
    for model in (IIWA, KR6, TX60):
        rng, chain, q, ref = _case(model, 3)
        marker = np.zeros(len(q), dtype=int)
        offsets = np.arange(1, chain.n)  # the first axis held, as the fit does
        tool = np.arange(chain.marker_slice().start, chain.marker_slice().start + 3)
        exp = expand_offsets(chain, q, marker, ref, offsets, np.zeros(0, int), tool)
        eps = rng.choice([-1.0, 1.0], (1, offsets.size)) * 2e-3
        dm = rng.normal(0.0, 1.0, (1, 3))
        errors = []
        for scale in (1.0, 0.5):
            p = ref.copy()
            p[offsets] += scale * eps[0]
            p[tool] += scale * dm[0]
            walked = chain.marker_positions(q, p)[:, 0]
            got = exp.positions(scale * eps, np.zeros((1, 0)), scale * dm)[0]
            errors.append(np.abs(got - walked).max())
        assert errors[0] < EXPANSION_TOLERANCE_MM, (model.name, errors)
        assert errors[0] / errors[1] > 6.0, (model.name, errors)


def test_link_terms_are_the_first_order_term():
    """Link deviations enter through the marker Jacobian: the error shrinks with the square of the
    deviation (0.2 mm / 0.02° → below 1e-3 mm; a tenth of that → a hundredth of the error)."""
    rng, chain, q, ref = _case(IIWA, 5)
    links = np.concatenate([chain.index("d"), chain.index("a"), chain.index("alpha")])
    exp = expand_offsets(chain, q, np.zeros(len(q), dtype=int), ref, np.arange(chain.n), links, np.zeros(0, int))
    lam = np.concatenate([rng.normal(0, 0.2, 2 * chain.n), np.radians(rng.normal(0, 0.02, chain.n))])
    errors = []
    for scale in (1.0, 0.1):
        p = ref.copy()
        p[links] += scale * lam
        walked = chain.marker_positions(q, p)[:, 0]
        got = exp.positions(np.zeros((1, chain.n)), scale * lam[None], np.zeros((1, 0)))[0]
        errors.append(np.abs(got - walked).max())
    assert errors[0] < 1e-3, errors
    assert 50 < errors[0] / errors[1] < 200, errors


def test_default_fit_samples_by_the_checked_expansion():
    """The default fit's sampler used the expansion, and it agreed with the chain walk at the
    farthest proposals of every batch."""
    ds, _, wrong = simulate(IIWA, seed=13, k=80, link_mm=0.1)
    res = fit_offsets(IIWA, ds, FitOptions(registration={"sensor": wrong}, seed=3, n_draws=500))
    check = res.diagnostics["expansion_check"]
    assert check["checked"] >= 2 and check["walked_batches"] == 0
    assert 0 < check["max_error_mm"] < EXPANSION_TOLERANCE_MM
