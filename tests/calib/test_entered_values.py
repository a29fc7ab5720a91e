"""What a result tells the operator to enter, read back: the controller-fitted ``entered`` section
when there is one, else the ``joint_offsets`` whose status is ``fitted``."""

import pytest

from calib.robot.entered import entered_values

OFFSETS = [
    {"joint": "A1", "index": 1, "value_deg": None, "status": "undetermined", "identifiable": False},
    {"joint": "A2", "index": 2, "value_deg": 0.25, "status": "fitted", "identifiable": True},
    {"joint": "A3", "index": 3, "value_deg": -0.1, "status": "do not enter", "identifiable": False},
    {"joint": "A4", "index": 4, "value_deg": 359.9, "status": "fitted", "identifiable": True},
]


def test_an_older_result_enters_its_fitted_offsets_and_predicts_nothing():
    v = entered_values({"joint_offsets": OFFSETS, "do_not_enter": []})
    assert [(a.axis, a.index) for a in v.axes] == [("A2", 2), ("A4", 4)]
    assert v.axes[1].delta_deg == pytest.approx(-0.1)  # a whole turn is no correction
    assert v.axes[0].correction_deg == pytest.approx(-0.25)
    assert v.source == "joint_offsets" and v.heldout is None
    assert v.delta_deg(["A1", "A2", "A3", "A4"]) == pytest.approx([0.0, 0.25, 0.0, -0.1])


def test_the_entered_section_wins_with_its_prediction():
    heldout = {"as_found": {"rms_mm": 2.0, "mean_mm": 1.8, "max_mm": 4.0, "n": 30},
               "improvement_mm": {"value": 1.2, "ci95": [1.0, 1.4]}}
    # the shape calib.fit.entered writes: every axis listed, only those with enter: true entered
    entered = {"verdict": "enter", "reasons": [], "heldout": heldout,
               "offsets": [{"joint": "A2", "index": 2, "value_deg": 0.25, "std_deg": 0.01, "enter": False,
                            "reason": "not significant"},
                           {"joint": "A3", "index": 3, "value_deg": 0.05, "std_deg": 0.001, "enter": True, "reason": ""}]}
    v = entered_values({"joint_offsets": OFFSETS, "entered": entered})
    assert [a.axis for a in v.axes] == ["A3"] and v.source == "entered" and v.heldout is heldout
    assert v.refused == []
    refused = entered_values({"joint_offsets": OFFSETS, "entered": {**entered, "verdict": "do not enter",
                                                                     "reasons": ["no better than as found"]}})
    assert refused.refused == ["no better than as found"]


def test_not_a_result_is_refused():
    with pytest.raises(ValueError, match="not a fit result"):
        entered_values({"format": "something else"})
