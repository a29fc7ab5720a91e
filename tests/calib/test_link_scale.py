"""Per-group link-prior scales by the Laplace evidence (``calib.fit.link_scale``,
``calib.fit.model_choice.empirical_link_scale``) on simulated tracker cells: a length scale and an
angle scale, each following its own truth; the linearised evidence agrees with refitted modes."""

from __future__ import annotations

from dataclasses import replace

import pytest

from calib.fit.link_scale import maximise_evidence
from calib.fit.model_choice import CV_TOL, empirical_link_scale, linearised_log_evidence, log_evidence
from calib.fit.offsets import FitOptions, fit_mode
from tests.calib.test_model_choice import cell


def test_hill_climbing_finds_the_grid_maximum_of_a_single_peak():
    calls = []

    def ev(mm, deg):
        calls.append((mm, deg))
        return -((mm - 1.0) ** 2) - 100 * (deg - 0.01) ** 2

    found = maximise_evidence(ev)
    assert (found["length_mm"], found["angle_deg"]) == (1.0, 0.01) and len(calls) < 30
    assert maximise_evidence(ev, exhaustive=True)["length_mm"] == 1.0


@pytest.mark.parametrize("length_mm, angle_deg", [(1.0, 0.005), (0.02, 0.2)])
def test_length_and_angle_scales_follow_their_own_truth(length_mm, angle_deg):
    """A cell with large length and tiny angle errors, and one the other way round: the evidence's
    scales land within a grid step (~3×) of each truth, not on one shared ratio."""
    model, _, cal = cell(4, link_mm=length_mm, angle_deg=angle_deg)
    found = empirical_link_scale(model, cal, FitOptions())
    assert length_mm / 3.5 <= found["length_mm"] <= length_mm * 3.5, found
    assert angle_deg / 3.5 <= found["angle_deg"] <= angle_deg * 3.5, found


def test_linearised_evidence_equals_the_refitted_evidence():
    model, _, cal = cell(4, link_mm=1.0, angle_deg=0.005)
    ref = fit_mode(model, cal, replace(FitOptions(), link_tolerance=(0.3, 0.03)), tol=CV_TOL)
    ev = linearised_log_evidence(ref)
    for mm, deg in ((0.3, 0.03), (1.0, 0.003), (0.1, 0.1)):
        exact = log_evidence(fit_mode(model, cal, replace(FitOptions(), link_tolerance=(mm, deg)), tol=CV_TOL))
        assert abs(exact - ev(mm, deg)) < 0.1, (mm, deg, exact, ev(mm, deg))
