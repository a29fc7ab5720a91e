"""Identifiability wording: "exact" only at rounding level, otherwise graded by condition and noise."""

from __future__ import annotations

import numpy as np
import pytest

from calib.plan.identifiability import analyse, describe_loadings, exact_tolerance, verdicts

NAMES = ["A1.offset", "A2.offset", "s.x", "s.gamma"]


def _jacobian(singular: list[float], seed: int = 0, rows: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """A (rows, 4) matrix with the given singular values and a random orthogonal V; returns (J, V)."""
    rng = np.random.default_rng(seed)
    u, _ = np.linalg.qr(rng.normal(size=(rows, 4)))
    v, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    return u @ np.diag(singular) @ v.T, v


def test_a_structural_null_direction_is_exact_and_named_by_its_components():
    rng = np.random.default_rng(1)
    j = rng.normal(size=(60, 3))
    j = np.column_stack([j[:, 0], j[:, 1], j[:, 2], 0.5 * j[:, 0] - 2.0 * j[:, 2]])  # s.gamma = 0.5 A1 − 2 s.x
    ident = analyse(j, NAMES, np.ones(4))
    (null,) = ident.null_space
    assert null.exact and null.singular_value <= exact_tolerance(ident.singular_values[0], j.shape)
    w = np.array([null.loadings.get(n, 0.0) for n in NAMES])
    np.testing.assert_allclose(w / w[3], [-0.5, 0.0, 2.0, 1.0], atol=1e-9)
    assert set(null.loadings) == {"A1.offset", "s.x", "s.gamma"}
    assert null.describe().split()[0].endswith("·s.x")  # largest weight first
    assert "exact null direction" in null.explain()
    (v,) = [d for d in verdicts(ident.singular_values, j.shape, 0.03, 10.0) if d.verdict == "not determined"]
    assert "exact" in v.why


def test_condition_number_5_7e9_is_not_called_exact():
    j, v = _jacobian([20.0, 5.0, 1.0, 20.0 / 5.7e9])
    ident = analyse(j, NAMES, np.ones(4))
    assert ident.condition_number == pytest.approx(5.7e9, rel=1e-3)
    (null,) = ident.null_space  # below rel_tol: the fit still fixes a parameter for it …
    assert not null.exact  # … but it is not an exact null direction
    assert "condition number 5.7e+09" in null.explain() and "exact" not in null.explain()
    grades = verdicts(ident.singular_values, j.shape, sigma_mm=0.03, undetermined_mm=13.0)
    assert [g.verdict for g in grades] == ["determined"] * 3 + ["not determined"]
    assert "exact" not in grades[-1].why and grades[-1].std_mm == pytest.approx(0.03 * 5.7e9 / 20.0, rel=1e-3)


def test_grades_follow_the_noise():
    sigma = 0.05
    # std = σ/s: 0.0025, 0.05 (= σ), 1.0 (20σ: weak), 100 (beyond the 13 mm limit).
    j, _ = _jacobian([20.0, 1.0, 0.05, 0.0005])
    ident = analyse(j, NAMES, np.ones(4))
    assert not ident.deficient  # all above rel_tol: all sampled
    grades = verdicts(ident.singular_values, j.shape, sigma_mm=sigma, undetermined_mm=13.0)
    assert [g.verdict for g in grades] == ["determined", "determined", "weakly determined", "not determined"]
    np.testing.assert_allclose([g.std_mm for g in grades], [0.0025, 0.05, 1.0, 100.0], rtol=1e-9)
    np.testing.assert_allclose([g.condition for g in grades], [1.0, 20.0, 400.0, 40000.0], rtol=1e-9)
    # The same data with 40 times the noise: the weak direction (std 40 mm) becomes undetermined.
    assert [g.verdict for g in verdicts(ident.singular_values, j.shape, 2.0, 13.0)] == ["determined"] * 2 + ["not determined"] * 2


def test_directions_carry_every_component_above_the_cut_and_describe_the_largest():
    j, v = _jacobian([20.0, 5.0, 1.0, 0.5], seed=3)
    ident = analyse(j, NAMES, np.ones(4))
    dirs = ident.directions(min_loading=0.0)
    for d, col in zip(dirs, v.T):
        w = np.array([d.loadings[n] for n in NAMES])
        assert abs(abs(w @ col) - 1.0) < 1e-9  # the right singular vector itself, up to sign
        assert not d.exact
    # A unit vector: components until 95 % of its squared length (0.64 + 0.25 + 0.09).
    text = describe_loadings({"a": 0.3, "b": -0.8, "c": 0.5, "d": 0.1, "e": -0.1})
    assert text == "-0.80·b +0.50·c +0.30·a (+2 smaller)"
