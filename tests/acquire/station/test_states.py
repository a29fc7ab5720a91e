"""Each robot state an engineer acts on, from a history: calibrated, drifted (naming the axis), out of
tolerance (relative to what the robot's calibration reached, or absolute), never calibrated, check
due; recomputed when the reference changes; ``fleet enter`` refuses a run that cannot be a reference."""

from datetime import datetime, timezone

import pytest

from acquire.station.history import add_entry, load_history, mark_entered
from acquire.station.states import Policy, robot_state

JOINTS = [f"A{i}" for i in range(1, 7)]
NOW = datetime(2026, 3, 10, tzinfo=timezone.utc)


def _entry(run_id, day, offsets=(0.0,) * 6, std=(0.005,) * 6, *, n_conf=40, entered=None, before=0.8, after=0.6):
    kind = "calibration" if n_conf > 12 else "check"
    return {"run_id": run_id, "finished": f"2026-03-{day:02d}T08:00:00+00:00", "site": "plant-a", "cell": "c1",
            "kind": kind, "n_configurations": n_conf, "entered": kind == "calibration" if entered is None else entered,
            "joints": JOINTS, "offsets_deg": list(offsets), "std_deg": list(std), "ci95_deg": [None] * 6,
            "accuracy_mm": {"before": before, "after": after}, "drift": None}


def test_a_robot_without_an_entered_calibration_is_never_calibrated():
    st = robot_state([_entry("r1", 1, entered=False)], now=NOW)
    assert st["state"] == "never calibrated" and "no calibration entered yet" in st["reasons"][0]
    assert robot_state([], now=NOW)["state"] == "never calibrated"


def test_a_stable_robot_is_calibrated_even_when_its_calibration_reached_more_than_an_example_limit():
    hist = [_entry("cal", 1, offsets=[-0.186] + [0] * 5, before=2.664, after=0.78),
            _entry("chk", 5, offsets=[0.004, -0.003, 0.002, 0, 0.001, 0], std=[0.01] * 6, n_conf=8, before=0.80)]
    st = robot_state(hist, now=NOW)
    assert st["state"] == "calibrated", st
    assert st["reference"] == "cal" and st["accuracy_limit_mm"] == pytest.approx(1.5 * 0.78)


def test_offsets_beyond_their_combined_uncertainty_are_drifted_naming_the_axis():
    hist = [_entry("cal", 1), _entry("chk", 5, offsets=[0, 0, 0.1, 0, 0, 0], std=[0.01] * 6, n_conf=8)]
    st = robot_state(hist, now=NOW)
    assert st["state"] == "drifted" and st["axes"] == ["A3"]
    assert "A3 +0.1000°" in st["reasons"][0]


def test_accuracy_over_the_relative_or_the_absolute_limit_is_out_of_tolerance():
    hist = [_entry("cal", 1, after=0.6), _entry("chk", 5, std=[0.01] * 6, n_conf=8, before=1.0)]
    st = robot_state(hist, now=NOW)
    assert st["state"] == "out of tolerance" and st["accuracy_limit_mm"] == pytest.approx(0.9)
    assert "1.000 mm as the robot runs, over 0.900 mm (1.5 × the 0.600 mm this robot runs with calibration cal " \
        "entered)" in st["reasons"][0]
    assert robot_state(hist, Policy(accuracy_limit_mm=1.2), now=NOW)["state"] == "calibrated"
    assert robot_state(hist, Policy(accuracy_factor=2.0), now=NOW)["state"] == "calibrated"
    st = robot_state(hist, Policy(accuracy_limit_mm=0.5), now=NOW)
    assert st["state"] == "out of tolerance" and "the plant's limit 0.5 mm" in st["reasons"][0]


def test_nothing_measured_for_the_interval_makes_a_check_due():
    hist = [_entry("cal", 1)]
    assert robot_state(hist, Policy(check_interval_days=30), now=NOW)["state"] == "calibrated"
    st = robot_state(hist, Policy(check_interval_days=5), now=NOW)
    assert st["state"] == "check due" and "a check is due every 5 days" in st["reasons"][0]
    assert robot_state(hist, Policy(check_interval_days=None), now=datetime(2030, 1, 1, tzinfo=timezone.utc))[
        "state"] == "calibrated"


def test_states_are_recomputed_when_the_reference_changes(tmp_path):
    """A check is compared with the reference entered before it: entering a wider calibration (σ 0.05°)
    makes a 0.1° offset within the combined uncertainty; undoing it brings the drift back."""
    add_entry(tmp_path, "R1", _entry("cal1", 1))
    add_entry(tmp_path, "R1", _entry("cal2", 3, std=[0.05] * 6, entered=False))
    add_entry(tmp_path, "R1", _entry("chk", 5, offsets=[0, 0, 0.1, 0, 0, 0], std=[0.01] * 6, n_conf=8))
    hist = load_history(tmp_path, "R1")
    assert robot_state(hist, now=NOW)["state"] == "drifted"
    mark_entered(tmp_path, "R1", "cal2")
    hist = load_history(tmp_path, "R1")
    st = robot_state(hist, now=NOW)
    assert st["reference"] == "cal2" and st["state"] == "calibrated", st
    assert hist[-1]["drift"]["reference"] == "cal2" and not hist[-1]["drift"]["drifted"]   # stored verdicts follow
    mark_entered(tmp_path, "R1", "cal2", entered=False)
    hist = load_history(tmp_path, "R1")
    assert hist[-1]["drift"]["reference"] == "cal1" and hist[-1]["drift"]["drifted"]
    assert robot_state(hist, now=NOW)["state"] == "drifted"


def test_enter_refuses_a_check_and_a_run_without_usable_offsets(tmp_path):
    add_entry(tmp_path, "R1", _entry("chk", 2, n_conf=12))
    add_entry(tmp_path, "R1", _entry("dne", 3, offsets=[None] * 6, std=[None] * 6, entered=False)
              | {"do_not_enter": ["held-out error 2.1 mm over the limit"]})
    with pytest.raises(ValueError, match="measured 12 configurations; a reference needs at least 13"):
        mark_entered(tmp_path, "R1", "chk")
    with pytest.raises(ValueError, match="no offset that can be entered: every offset is undetermined or 'do not enter' "
                                         r"\(the fit says: held-out error 2.1 mm over the limit\)"):
        mark_entered(tmp_path, "R1", "dne")
    assert not any(e["entered"] for e in load_history(tmp_path, "R1"))
