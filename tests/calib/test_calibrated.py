"""``calib.robot.calibrated``: a fit's result.json applied to the nominal model it was fitted to."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.robot.calibrated import ResultError, apply_result, read_result
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.urdf import random_configurations

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
KR6 = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
OFFSETS_DEG = [0.0, 0.31, -0.22, 0.15, -0.4, 0.27]


def _fit_doc(model=KR6, statuses=None) -> dict:
    statuses = statuses or ["undetermined"] + ["fitted"] * (model.n_joints - 1)
    return {
        "format": "remaster.fit/1",
        "robot": {"name": model.name, "controller": model.controller, "axes": model.axis_names},
        "joint_offsets": [
            {"joint": ax, "index": i + 1, "value_deg": None if s == "undetermined" else OFFSETS_DEG[i],
             "status": s, "reason": "not determined by this data" if s == "undetermined" else ""}
            for i, (ax, s) in enumerate(zip(model.axis_names, statuses))],
    }


def test_fitted_offsets_make_the_model_at_reading_q_the_nominal_arm_at_q_plus_delta():
    cal = apply_result(KR6, _fit_doc())
    assert cal.applied == [f"A{i}.offset" for i in range(2, 7)]
    assert any(n.startswith("A1.offset kept nominal (undetermined") for n in cal.notes)
    q = random_configurations(KR6, 30, seed=7)
    delta = np.radians(OFFSETS_DEG)  # A1's value is 0 here, so kept nominal is the same as applied
    np.testing.assert_allclose(Chain(cal.model).fk(q), Chain(KR6).fk(q + delta), atol=1e-9)
    assert np.abs(Chain(cal.model).fk(q)[:, :3, 3] - Chain(KR6).fk(q)[:, :3, 3]).max() > 1.0
    assert cal.model.name == f"{KR6.name} (calibrated)" and cal.model.convention == "dh"


def test_offsets_marked_do_not_enter_stay_nominal():
    doc = _fit_doc(statuses=["fitted", "fitted", "do not enter", "fitted", "fitted", "fitted"])
    doc["joint_offsets"][2]["reason"] = "weakly determined"
    cal = apply_result(KR6, doc)
    assert "A3.offset" not in cal.applied and "A3.offset kept nominal (do not enter: weakly determined)" in cal.notes
    assert cal.model.joints[2].theta == KR6.joints[2].theta
    assert cal.model.joints[1].theta == pytest.approx(KR6.joints[1].theta + OFFSETS_DEG[1])


def test_results_that_do_not_belong_to_the_model_are_refused():
    with pytest.raises(ResultError, match="fitted to robot 'KUKA KR 6 R900-2', the model is 'Staubli TX60'"):
        apply_result(load_robot_model(ROBOTS / "staubli_tx60.yaml"), _fit_doc())
    doc = _fit_doc()
    doc["robot"]["axes"] = ["J1", "J2", "J3", "J4", "J5", "J6"]
    with pytest.raises(ResultError, match="axes"):
        apply_result(KR6, doc)
    with pytest.raises(ResultError, match="nothing in it may be applied"):
        apply_result(KR6, _fit_doc(statuses=["undetermined"] * 6))
    with pytest.raises(ResultError, match="not a result this version understands"):
        apply_result(KR6, {"robot": {"name": KR6.name}})


def _full_doc(model=KR6, change=None) -> dict:
    chain = Chain(model)
    change = change or {"A2.a": 0.4, "A3.alpha": -0.05, "A4.offset": 0.2}
    params = []
    for i, name in enumerate(chain.param_names):
        kind = name.rsplit(".", 1)[1]
        f = math.degrees if kind in ("offset", "alpha", "beta") else float
        params.append({"name": name, "unit": "deg" if f is math.degrees else "mm", "nominal": f(chain.nominal[i]), "value": f(chain.nominal[i]) + change.get(name, 0.0),
                       "identified": name in change})
    return {"method": "full", "robot": model.name, "parameters": params}


def test_full_identification_values_are_applied_and_equal_the_chain_with_those_parameters():
    cal = apply_result(KR6, _full_doc())
    assert sorted(cal.applied) == ["A2.a", "A3.alpha", "A4.offset"]
    q = random_configurations(KR6, 20, seed=8)
    np.testing.assert_allclose(Chain(cal.model).fk(q), Chain(KR6).fk(q, cal.params), atol=1e-9)
    assert cal.model.joints[1].a == pytest.approx(455.4)


def test_a_full_result_on_a_model_with_other_nominal_values_is_refused():
    doc = _full_doc()
    next(p for p in doc["parameters"] if p["name"] == "A4.d")["nominal"] = 421.0
    with pytest.raises(ResultError, match="A4.d was 421.0 mm in the model the fit used, this model has 420"):
        apply_result(KR6, doc)


def test_read_result_names_the_file(tmp_path):
    with pytest.raises(ResultError, match="no such result file"):
        read_result(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ResultError, match=f"{bad}: not a JSON result file"):
        read_result(bad)


def test_a_socket_result_applies_its_kinematic_parameters_but_not_the_ball():
    doc = _fit_doc(statuses=["fitted", "fitted", "fitted", "do not enter", "fitted", "undetermined"])
    doc.update(kind="socket", method="fast", robot={"name": KR6.name})
    del doc["format"]
    doc["parameters"] = [
        {"name": "A2.offset", "nominal": 0.0, "value": 0.31, "unit": "deg"},
        {"name": "A4.offset", "nominal": 0.0, "value": 0.15, "unit": "deg"},  # "do not enter"
        {"name": "A3.a", "nominal": -25.0, "value": -24.6, "unit": "mm"},
        {"name": "smr.x", "nominal": None, "value": 3.0, "unit": "mm"},  # the ball, not a marker
    ]
    cal = apply_result(KR6, doc)
    assert cal.applied == ["A2.offset", "A3.a"]
    assert "A4.offset kept nominal (do not enter)" in cal.notes and "A6.offset kept nominal (undetermined: not determined by this data)" in cal.notes
    assert cal.model.tool == KR6.tool and cal.model.joints[2].a == pytest.approx(-24.6)
    assert cal.model.joints[1].theta == pytest.approx(KR6.joints[1].theta + 0.31)


# --- everything the fit found: link terms, compliance, entered offsets ---------------------------
from calib.robot.gravity import gravity_torques  # noqa: E402
from tests.calib.calibrated_sim import COMPLIANCE, full_result, offsets_result, with_masses  # noqa: E402

KR6_SAGGING = with_masses(KR6)


def _truth(model, doc):
    """The arm a synthetic result describes, computed here from its numbers: chain vector (P,)."""
    chain = Chain(model)
    params = chain.nominal.copy()
    if doc.get("method") == "full":
        for e in doc["parameters"]:
            i = chain.param_names.index(e["name"])
            params[i] = math.radians(e["value"]) if e["unit"] == "deg" else e["value"]
    else:
        for e in doc["joint_offsets"]:
            params[chain.param_names.index(f"{e['joint']}.offset")] = math.radians(e["value_deg"])
        for name, e in doc["diagnostics"]["link_prior"]["parameters"].items():
            i = chain.param_names.index(name)
            params[i] += math.radians(e["mean"]) if name.rsplit(".", 1)[1] in ("alpha", "beta") else e["mean"]
    return params


@pytest.mark.parametrize("make", [full_result, offsets_result], ids=["full", "offsets+tool+links+compliance"])
def test_links_and_sag_of_every_result_kind_are_applied(make):
    doc = make(KR6_SAGGING)
    cal = apply_result(KR6_SAGGING, doc)
    assert {"A2.a", "A3.alpha", "A4.d", "A2.compliance"} <= set(cal.applied)
    chain = Chain(KR6_SAGGING)
    params = _truth(KR6_SAGGING, doc)
    q = random_configurations(KR6_SAGGING, 50, seed=4)
    sag = chain.sign * COMPLIANCE * gravity_torques(chain, q, params)
    assert np.abs(np.degrees(sag)).max() > 0.005  # the sag is there to be seen
    np.testing.assert_allclose(cal.fk(q), chain.fk(q + sag, params), atol=1e-9)
    rigid = apply_result(KR6_SAGGING, make(KR6_SAGGING, compliance=False))
    assert rigid.compliance is None and np.abs(rigid.fk(q)[:, :3, 3] - cal.fk(q)[:, :3, 3]).max() > 0.05


def test_entered_offsets_move_the_arm_into_the_controllers_new_angles():
    doc = full_result(KR6_SAGGING)
    cal = apply_result(KR6_SAGGING, doc)
    doc["entered"] = {"verdict": "enter", "offsets": [
        {"joint": "A2", "index": 2, "value_deg": 0.12, "enter": True},
        {"joint": "A3", "index": 3, "value_deg": -0.2, "enter": False},
        {"joint": "A5", "index": 5, "value_deg": None, "enter": True}]}
    from calib.robot.calibrated import entered_offsets

    entered = entered_offsets(doc, KR6_SAGGING)
    np.testing.assert_allclose(np.degrees(entered), [0, 0.12, 0, 0, 0, 0])
    after = cal.after_entering(entered)
    q_old = random_configurations(KR6_SAGGING, 20, seed=5)
    np.testing.assert_allclose(after.fk(q_old + entered), cal.fk(q_old), atol=1e-9)  # the same physical arm
    assert entered_offsets(full_result(KR6_SAGGING), KR6_SAGGING) is None
    with pytest.raises(ResultError, match="entered.offsets\\[0\\] names axis 'J9'"):
        entered_offsets({"entered": {"offsets": [{"joint": "J9", "value_deg": 1, "enter": True}]}}, KR6_SAGGING)


def test_a_compliance_result_on_a_model_without_masses_is_refused():
    with pytest.raises(ResultError, match="no link masses"):
        apply_result(KR6, full_result(KR6_SAGGING) | {"robot": KR6.name})
