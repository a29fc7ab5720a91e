"""The drift check: a drifted simulated robot is flagged, a stable one is not (≤ 5 % of 100 re-checks)."""

import numpy as np
import pytest

from acquire.station.drift import check_drift
from acquire.station.history import add_entry, entry_from_result, load_history, mark_entered, reference_for

JOINTS = [f"A{i}" for i in range(1, 7)]


def _entry(run_id, finished, offsets, std, *, kind="calibration", acc_before=0.5, entered=None):
    return {"run_id": run_id, "finished": finished, "site": "", "cell": "c1", "kind": kind,
            "n_configurations": 40 if kind == "calibration" else 8,
            "entered": kind == "calibration" if entered is None else entered, "joints": JOINTS,
            "offsets_deg": list(offsets), "std_deg": list(std), "ci95_deg": [None] * 6,
            "accuracy_mm": {"before": acc_before, "after": 0.1}, "drift": None}


def _measure(rng, truth, std):
    return truth + rng.normal(0, std)


def test_stable_robots_are_rarely_flagged_and_drifted_ones_are():
    """Simulated: the reference calibration's error e_ref ~ N(0, σ_ref) is entered, so a stable
    robot's true residual is −e_ref; each re-check measures it with σ_new. A drifted robot's
    joint A3 moved by 0.08° (7 combined σ)."""
    rng = np.random.default_rng(26)
    std_ref = np.array([0.004, 0.003, 0.004, 0.006, 0.008, 0.010])
    std_new = 2.5 * std_ref  # a short check: fewer configurations, wider intervals
    flagged_stable = flagged_drifted = 0
    for i in range(100):
        e_ref = rng.normal(0, std_ref)
        ref = _entry("ref", "2026-01-01T00:00:00", e_ref, std_ref)
        stable = _entry(f"s{i}", "2026-02-01T00:00:00", _measure(rng, -e_ref, std_new), std_new, kind="check")
        moved = -e_ref + np.array([0, 0, 0.08, 0, 0, 0])
        drifted = _entry(f"d{i}", "2026-02-01T00:00:00", _measure(rng, moved, std_new), std_new, kind="check")
        flagged_stable += check_drift(ref, stable, alpha=0.01).drifted
        v = check_drift(ref, drifted, alpha=0.01)
        flagged_drifted += v.drifted
    assert flagged_stable <= 5
    assert flagged_drifted >= 95
    assert v.joints == ["A3"] or not v.drifted


def test_undetermined_joints_are_left_out_of_the_test():
    ref = _entry("ref", "2026-01-01T00:00:00", [0] * 6, [0.01] * 6)
    new = _entry("n", "2026-02-01T00:00:00", [0, 0, 0, 0, 0, 5.0], [0.01] * 5 + [None], kind="check")
    new["offsets_deg"][5] = None
    v = check_drift(ref, new)
    assert v.dof == 5 and not v.drifted


def test_the_reference_is_the_last_entered_calibration(tmp_path):
    add_entry(tmp_path, "R1", _entry("c1", "2026-01-01T00:00:00", [0] * 6, [0.01] * 6))
    add_entry(tmp_path, "R1", _entry("c2", "2026-02-01T00:00:00", [0] * 6, [0.01] * 6, entered=False))
    add_entry(tmp_path, "R1", _entry("k1", "2026-03-01T00:00:00", [0] * 6, [0.01] * 6, kind="check"))
    add_entry(tmp_path, "R1", _entry("k1", "2026-03-01T00:00:00", [0] * 6, [0.01] * 6, kind="check"))  # re-sent
    hist = load_history(tmp_path, "R1")
    assert [e["run_id"] for e in hist] == ["c1", "c2", "k1"]
    assert reference_for(hist, hist[-1])["run_id"] == "c1"
    mark_entered(tmp_path, "R1", "c2")
    assert reference_for(load_history(tmp_path, "R1"), hist[-1])["run_id"] == "c2"
    with pytest.raises(ValueError, match="has no run 'nope'"):
        mark_entered(tmp_path, "R1", "nope")


def test_a_result_json_becomes_a_history_entry():
    result = {"format": "remaster.fit/1", "data": {"n_configurations": 40},
              "joint_offsets": [{"joint": "A1", "value_deg": 0.1, "std_deg": 0.01, "ci95_deg": [0.08, 0.12],
                                 "identifiable": True},
                                {"joint": "A2", "value_deg": None, "std_deg": None, "identifiable": False}],
              "metrics": {"absolute": {"before": {"mean": 1.2}, "after": {"mean": 0.2}}}}
    e = entry_from_result(result, run_id="r", finished="2026-01-01T00:00:00", site="s", cell="c")
    assert e["kind"] == "calibration" and e["entered"] is False  # an undetermined offset: not entered
    assert e["offsets_deg"] == [0.1, None]
    assert e["entered_deg"] == pytest.approx([0.1, 0.0])  # an older result enters its fitted offsets
    # the fit's own metrics describe its model, not the robot: without the run's log nothing is scored
    assert e["accuracy_mm"]["before"] is None and e["accuracy_mm"]["how"].startswith("not scored")
    with pytest.raises(ValueError, match="no joint_offsets"):
        entry_from_result({}, run_id="r", finished="x", site="", cell="c")


def test_a_later_run_is_expected_to_find_what_the_entry_left():
    """What was typed in (the offsets fitted for the nominal arm, ``entered_deg``) differs from the
    fit's best estimate of the zeros (``offsets_deg``): a stable robot's later run finds the
    difference on an entered axis and the reference's own offset on an axis left unchanged."""
    offsets = [0.30, -0.20, 0.10, 0.0, 0.0, 0.0]
    ref = _entry("ref", "2026-01-01T00:00:00", offsets, [0.005] * 6)
    ref["entered_deg"] = [0.26, -0.20, 0.0, 0.0, 0.0, 0.0]   # A1 entered as fitted for the nominal arm; A3 left
    stable = _entry("k", "2026-02-01T00:00:00", [0.04, 0.0, 0.10, 0, 0, 0], [0.005] * 6, kind="check")
    assert not check_drift(ref, stable).drifted
    assumed = dict(ref, entered_deg=None)   # an entry without entered_deg: every offset taken as entered
    v = check_drift(assumed, stable)
    assert v.drifted and v.joints == ["A1", "A3"]
    moved = _entry("m", "2026-02-01T00:00:00", [0.04, 0.08, 0.10, 0, 0, 0], [0.005] * 6, kind="check")
    assert check_drift(ref, moved).joints == ["A2"]
