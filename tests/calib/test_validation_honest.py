"""Honest validation of --method full: the headline validation figure is scored only on markers
the calibration measured, and equals an independent computation on the same points; held-out
points of a marker the calibration never measured are scored apart, labelled, with the
estimated placement's uncertainty."""

import numpy as np
import pytest

from calib.fit.identification import ident_result_dict, identify
from calib.robot.kinematics import Chain
from tests.calib.test_canonical import _dh_flange
from tests.calib.tracker_sim import CAL_NESTS, configurations, observe, tracker_cell


def test_validation_headline_equals_an_independent_scorer_on_the_measured_markers():
    cell = tracker_cell(seed=4)
    chain = Chain(cell.model)
    rng = np.random.default_rng(40)
    q_val = configurations(cell.model, rng, 25, 0.6)
    val = observe(chain, q_val, cell.truth, ("n1", "n2", "n3", "n4"), cell.base2sensor, rng, 0.03, "val")
    result = identify(cell.model, cell.cal)
    doc = ident_result_dict(result, cell.cal, val)
    head = doc["metrics"]["validation"]
    seen = np.isin(val.marker, list(CAL_NESTS))
    assert head["n_points"] == int(seen.sum()) == 75 and head["markers"] == list(CAL_NESTS)

    # Independent: an explicit product of the convention's link matrices (not calib.robot.kinematics),
    # the identified marker positions, the calibration's registration; |measured − predicted|.
    markers = dict(zip(chain.marker_names, result.params[chain.marker_slice()].reshape(-1, 3)))
    t = result.base2sensor["sensor"]
    errors = []
    for q, m, xyz in zip(val.q_rad[seen], val.marker[seen], val.xyz_mm[seen]):
        p = _dh_flange(cell.model, result.params, q) @ np.append(markers[m], 1.0)
        errors.append(np.linalg.norm(xyz - (t @ p)[:3]))
    errors = np.array(errors)
    assert head["after"]["EACPE"] == pytest.approx(errors.mean(), rel=1e-9)
    assert head["after"]["EMCPE"] == pytest.approx(errors.max(), rel=1e-9)
    assert errors.mean() < 0.1  # the noise is 0.03 mm per coordinate

    # The never-measured n4: apart, labelled, its placement an estimate with an uncertainty.
    other = doc["metrics"]["validation_unseen_markers"]
    assert other["n_points"] == 25 and other["markers"] == ["n4"] and "not the validation headline" in other["label"]
    assert other["placement"]["n4"]["uncertainty_mm"] > 0 and "layout" in other["placement"]["n4"]["how"]

    # A drawing that puts n4 2 mm from where it is: the headline does not move (n4 is not in it);
    # the separate figure does.
    d = cell.model.model_dump()
    d["tool"]["markers"][3]["xyz"] = tuple(np.add(d["tool"]["markers"][3]["xyz"], (2.0, 0.0, 0.0)))
    wrong = type(cell.model).model_validate(d)
    doc2 = ident_result_dict(identify(wrong, cell.cal), cell.cal, val)
    assert doc2["metrics"]["validation"]["after"]["EACPE"] == pytest.approx(head["after"]["EACPE"], rel=1e-6)
    assert doc2["metrics"]["validation_unseen_markers"]["after"]["EACPE"] > 1.0 > 10 * other["after"]["EACPE"]


def test_without_a_measured_marker_there_is_no_headline():
    cell = tracker_cell(seed=4)  # its validation set holds only n4, never measured in calibration
    result = identify(cell.model, cell.cal)
    doc = ident_result_dict(result, cell.cal, cell.val)
    assert "validation" not in doc["metrics"] and "validation_unseen_markers" in doc["metrics"]
    assert any("no validation headline" in n for n in doc["metric_notes"])


def _kabsch(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (4, 4) taking points p (k, 3) onto q (k, 3), by SVD."""
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = r, qc - r @ pc
    return t


def test_fast_fit_validation_headline_is_the_measured_markers_scored_independently():
    """The fast fit's validation_absolute (calib.fit.metrics.accuracy_metrics): the validation points
    of measured markers only, with the calibration's least-squares registration — recomputed here
    with an explicit DH product and an SVD registration; n4's points are apart."""
    from calib.fit.metrics import accuracy_metrics

    cell = tracker_cell(seed=5)
    chain = Chain(cell.model)
    rng = np.random.default_rng(50)
    val = observe(chain, configurations(cell.model, rng, 20, 0.6), cell.truth, ("n1", "n4"), cell.base2sensor, rng,
                  0.03, "val")
    offsets = np.radians([0.0, 0.01, -0.02, 0.03, 0.0, 0.0])
    m = accuracy_metrics(chain, cell.cal, offsets, offsets[None] + np.zeros((20, 6)), 0.05, validation=val,
                         n_random=10, n_draws=20)
    params = chain.with_offsets(offsets)
    mk = dict(zip(chain.marker_names, params[chain.marker_slice()].reshape(-1, 3)))

    def predicted(ds):
        return np.array([(_dh_flange(cell.model, params, q) @ np.append(mk[name], 1.0))[:3]
                         for q, name in zip(ds.q_rad, ds.marker)])

    reg = _kabsch(predicted(cell.cal), cell.cal.xyz_mm)
    seen = val.marker == "n1"
    p = predicted(val.subset(seen))
    errors = np.linalg.norm(val.xyz_mm[seen] - (p @ reg[:3, :3].T + reg[:3, 3]), axis=1)
    head = m["validation_absolute"]["after"]
    # equal to the independent scorer's to 1e-9 mm (the must-show; seen: 1e-12 relative)
    assert head["count"] == 20 and head["mean"] == pytest.approx(errors.mean(), abs=1e-9, rel=0)
    assert head["max"] == pytest.approx(errors.max(), abs=1e-9, rel=0)
    assert m["validation_absolute_unseen_markers"]["after"]["count"] == 20
