"""What a controller that takes zero-offsets gets (``calib.fit.entered``): offsets fitted for its
nominal arm, entered only where that robot beats the robot as found held out.

Simulated tracker cells (``tests.calib.tracker_sim``: a Stäubli TX60 with a three-nest plate):
zero-offsets of 0.03° (or none), link errors of 0.5 mm / 0.1° (N(0, sd) per parameter), the plate
15 mm further out along the flange's z than the model says (not declared), 0.01 mm noise; the
validation configurations measure the same nests elsewhere in the workspace.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.fit.entered import (Arm, as_found_markers, controller_entries, distances, fit_entered, fitted_arm,
                               for_controller, heldout_on_validation, nominal_arm, place)
from calib.fit.offsets import FitOptions, fit_mode
from calib.measure.dataset import Dataset
from calib.robot.controller import controller_values
from calib.robot.kinematics import Chain
from calib.robot.transforms import pose_to_matrix
from tests.calib.tracker_sim import CAL_NESTS, TRACKER2BASE_POSE, configurations, link_errors, observe, plate_model

TOOL_MM = 15.0
NOISE_MM = 0.01
QUICK = FitOptions(method="laplace", n_draws=250)


def cell(seed: int, offset_deg: float, link_mm: float = 0.5, angle_deg: float = 0.1, k_cal: int = 40, k_val: int = 40):
    """(model, truth chain vector, calibration data, validation data); offsets ±``offset_deg`` on every axis."""
    rng = np.random.default_rng(seed)
    model = plate_model()
    chain = Chain(model)
    truth = link_errors(chain, rng, link_mm, angle_deg) if link_mm else chain.nominal.copy()
    truth[: chain.n] = np.radians(offset_deg * rng.choice([-1.0, 1.0], chain.n))
    ms = chain.marker_slice()
    truth[ms] = (truth[ms].reshape(-1, 3) + [0.0, 0.0, TOOL_MM]).ravel()
    b2s = np.linalg.inv(pose_to_matrix(*TRACKER2BASE_POSE))
    cal = observe(chain, configurations(model, rng, k_cal), truth, CAL_NESTS, b2s, rng, NOISE_MM, "cal")
    val = observe(chain, configurations(model, rng, k_val, 0.6), truth, CAL_NESTS, b2s, rng, NOISE_MM, "val")
    spread = {"std_mm": np.full(len(cal), NOISE_MM), "count": np.ones(len(cal), int)}
    return (model, truth, replace(cal, **spread),
            replace(val, std_mm=np.full(len(val), NOISE_MM), count=np.ones(len(val), int), config=np.char.add("v", val.config)))


def _links_arm(model, cal: Dataset) -> tuple[Arm, np.ndarray]:
    """The full model (offsets, tool and links under a 1 mm / 0.1° prior) at its mode, and its offsets (n,)."""
    mf = fit_mode(model, cal, replace(QUICK, link_tolerance=(1.0, 0.1)), tol=1e-8)
    arm = fitted_arm(mf.post, mf.theta)
    return arm, arm.params[: model.n_joints].copy()


def test_the_offsets_fitted_for_the_nominal_arm_improve_it_where_the_full_models_offsets_make_it_worse():
    model, truth, cal, val = cell(4, 0.03)
    chain = Chain(model)
    full, model_offsets = _links_arm(model, cal)
    doc, entered = for_controller(model, cal, val, QUICK, full_arm=full, full_folds=None, fitted_model="offsets+tool+links")
    h = doc["heldout"]
    # The full model's own offsets, typed into the nominal controller, make this robot worse than as found.
    theirs = heldout_on_validation(chain, {"as_found": nominal_arm(chain), "entered": nominal_arm(chain, model_offsets),
                                           "full_model": full}, val)
    assert theirs.errors["entered"].mean() > theirs.errors["as_found"].mean()
    # The offsets fitted for the nominal arm improve it, by more than the interval, and are entered.
    assert h["scored_on"] == "validation" and h["as_found"]["n"] == h["entered"]["n"] == 40
    assert h["entered"]["mean_mm"] < 0.8 * h["as_found"]["mean_mm"]
    assert h["improvement_mm"]["ci95"][0] > 0 and doc["verdict"] == "enter" and doc["reasons"] == []
    assert h["full_model"]["mean_mm"] < 0.1 * h["entered"]["mean_mm"]  # what compensation could deliver
    assert [o["enter"] for o in doc["offsets"]] == [o["significant"] for o in entered.offsets] and any(
        o["enter"] for o in doc["offsets"])
    for o in doc["offsets"]:
        assert o["enter"] == (o["reason"] == "")
        assert set(o) == {"joint", "index", "value_deg", "std_deg", "enter", "reason"}
    # The values to type are the entered offsets (not the full model's).
    values = controller_values(model, controller_entries(doc))
    typed = {a.axis: a.delta_deg for a in values.axes if a.action == "enter"}
    assert typed == {o["joint"]: o["value_deg"] for o in doc["offsets"] if o["enter"]}
    # "As found" carries the tool the data say (15 mm off the drawing), not the drawing's.
    found = as_found_markers(model, cal)
    true_nests = truth[chain.marker_slice()].reshape(-1, 3)
    for name, xyz in found.items():
        assert np.linalg.norm(xyz - true_nests[chain.marker_names.index(name)]) < 3.0


def test_enter_is_refused_where_no_offset_would_improve_the_robot():
    model, _, cal, val = cell(5, 0.0)  # no offset error, link errors only
    doc, _ = for_controller(model, cal, val, QUICK, full_arm=None, full_folds=None, fitted_model="offsets+tool")
    h = doc["heldout"]
    assert doc["verdict"] == "do not enter" and not any(o["enter"] for o in doc["offsets"])
    assert h["improvement_mm"]["ci95"][0] <= 0 < h["improvement_mm"]["ci95"][1]
    assert any("do not beat the robot as found" in r or "nothing to enter" in r for r in doc["reasons"])
    values = controller_values(model, controller_entries(doc))
    assert {a.action for a in values.axes} == {"leave unchanged"}


def test_placing_a_known_arm_recovers_registration_and_tool_and_leaves_only_noise():
    model, truth, cal, _ = cell(6, 0.05, link_mm=0.0)
    chain = Chain(model)
    true_arm = Arm(truth)
    placed = place(chain, nominal_arm(chain, truth[: chain.n]), cal)
    b2s = np.linalg.inv(pose_to_matrix(*TRACKER2BASE_POSE))
    np.testing.assert_allclose(placed.base2sensor["sensor"], b2s, atol=0.05)
    for name, xyz in placed.markers_mm.items():
        i = chain.marker_slice().start + 3 * chain.marker_names.index(name)
        np.testing.assert_allclose(xyz, truth[i:i + 3], atol=0.05)
    d = distances(chain, true_arm, placed, cal)
    assert np.sqrt(np.mean(d**2)) < 3 * NOISE_MM


@pytest.mark.slow
def test_without_validation_the_folds_score_the_three_robots_held_out():
    model, _, cal, _ = cell(4, 0.03)
    doc, entered = for_controller(model, cal, None, QUICK, full_arm=None,
                                  full_folds=lambda train: _links_arm(model, train)[0], fitted_model="offsets+tool+links")
    h = doc["heldout"]
    assert h["scored_on"] == "cross-validation" and "5-fold" in h["how"]
    assert h["as_found"]["n"] == h["entered"]["n"] == h["full_model"]["n"] == 40
    assert doc["verdict"] == "enter", doc["reasons"]
    assert h["full_model"]["mean_mm"] < h["entered"]["mean_mm"] < h["as_found"]["mean_mm"]


@pytest.mark.slow
def test_the_default_fit_writes_the_entered_verdict_and_types_its_offsets():
    from calib.fit.auto_fit import auto_fit

    model, _, cal, val = cell(4, 0.03)
    done = auto_fit(model, cal, val, QUICK, include_full=False, n_random=50)
    doc = done.doc
    assert set(doc["entered"]) >= {"controller", "verdict", "reasons", "offsets", "heldout"}
    assert set(doc["entered"]["heldout"]) >= {"scored_on", "as_found", "entered", "full_model", "improvement_mm"}
    assert doc["entered"]["verdict"] == "enter" and done.refused == []
    typed = {a["axis"]: a["delta_deg"] for a in doc["controller"]["axes"] if a["action"] == "enter"}
    assert typed == {o["joint"]: o["value_deg"] for o in doc["entered"]["offsets"] if o["enter"]}
    assert "offsets entered on the nominal arm" in done.controller_text
    # The validation "before" is the robot as found (its tool fitted): the offsets' validation gain is
    # the entered robot's, not one measured against the drawing's tool.
    val_abs = doc["metrics"]["validation_absolute"]
    assert val_abs["before"]["mean"] < 3 * doc["entered"]["heldout"]["as_found"]["mean_mm"]


def test_fit_entered_leaves_insignificant_axes_unchanged_and_refits_the_others():
    model, _, cal, _ = cell(4, 0.03)
    entered = fit_entered(model, cal, QUICK)
    for o in entered.offsets:
        if o["value_deg"] is not None and not o["significant"]:
            assert o["reason"].startswith("not significant")
        if o["significant"]:
            assert abs(o["value_deg"]) >= 1.96 * o["std_deg"]
    assert set(entered.result.posterior.mask.offsets.nonzero()[0] + 1) == set(entered.joints)
    assert np.count_nonzero(entered.offsets_rad) == len(entered.joints)


def test_validation_points_of_another_mounting_are_not_judged_with_the_calibrations_registration():
    from calib.robot.controller import earned_reasons

    def doc(before: float, after: float, rereg_before: float) -> dict:
        return {"metrics": {"validation_absolute": {"before": {"mean": before}, "after": {"mean": after}},
                            "validation_absolute_reregistered": {"before": {"mean": rereg_before},
                                                                 "after": {"mean": rereg_before}}}}

    # Same mounting: the offsets that make the validation points worse are refused.
    assert any("get no better" in r for r in earned_reasons(doc(1.025, 1.129, 1.02)))
    # Series B calibrated, series D validated (the tracker moved: 3.6 m off with B's registration).
    assert earned_reasons(doc(3623.578, 3623.653, 1.02)) == []
