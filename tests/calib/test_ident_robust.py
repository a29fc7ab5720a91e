"""Issue 14: robust identification on a tracker dataset shaped like a real one.

The cell (``tests.calib.tracker_sim``): a Stäubli TX60 with link errors, a nest plate whose three
calibration nests and fourth validation nest are up to 10 mm from where the model puts them,
36 calibration configurations, tracker noise 0.03 mm per coordinate.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.cli import app
from calib.measure.dataset import from_arrays, read_csv, write_csv
from calib.fit.identification import IdentOptions, ident_result_dict, identify, locate_unseen_markers, write_model_yaml
from calib.robot.kinematics import Chain
from calib.fit.metrics import registered_errors
from calib.robot.model import load_robot_model
from calib.robot.transforms import apply
from tests.calib.tracker_sim import CAL_NESTS, observe, tracker_cell

log = logging.getLogger(__name__)

#: Many random starts, wider than the default, another seed: the reference for "the best minimum".
REFERENCE = IdentOptions(n_starts=30, seed=1234, start_spread=(5.0, 3.0))


def _reference_cost(model, cal) -> float:
    ref = identify(model, cal, REFERENCE)
    log.info("reference: %d starts, costs %s", len(ref.starts), ", ".join(f"{s['cost']:.4g}" for s in ref.starts))
    return ref.starts[0]["cost"]


def test_full_method_without_options_reaches_the_best_minimum_on_a_tracker_dataset(tmp_path):
    cell = tracker_cell(seed=3)
    write_model_yaml(cell.model, tmp_path / "robot.yaml")
    write_csv(cell.cal, tmp_path / "cal.csv")
    write_csv(cell.val, tmp_path / "val.csv")
    out = tmp_path / "full.json"
    res = CliRunner().invoke(app, ["fit", str(tmp_path / "cal.csv"), "--robot", str(tmp_path / "robot.yaml"),
                                   "--validate", str(tmp_path / "val.csv"), "--method", "full", "-o", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    model = load_robot_model(tmp_path / "robot.yaml")
    cal = read_csv(tmp_path / "cal.csv", model)
    best = _reference_cost(model, cal)
    costs = [s["cost"] for s in doc["starts"]]
    log.info("acquire fit --method full: starts %s; reference best %.6g; rms %.4f mm",
             ", ".join(f"{s['label']} {s['cost']:.6g} (rms {s['rms_mm']:.4f})" for s in doc["starts"]), best, doc["rms_mm"])
    assert costs[0] <= best * (1 + 1e-6)
    assert doc["rms_mm"] < 0.04  # the noise: 0.03 mm per coordinate
    assert not doc["warnings"], doc["warnings"]
    v = doc["metrics"]["validation_unseen_markers"]  # n4 was never measured: not the headline
    assert "validation" not in doc["metrics"]
    log.info("validation n4 EACPE: before %.3f mm, after %.4f mm (calibration registration), re-registered after %.4f mm",
             v["before"]["EACPE"], v["after"]["EACPE"], v["reregistered"]["after"]["EACPE"])
    assert v["after"]["EACPE"] < 0.07 and v["before"]["EACPE"] > 2.0
    assert any("n4" in n and "rigid transform" in n for n in doc["metric_notes"])
    # The corrected model carries the fourth nest where the scoring put it, not at the drawing's place.
    assert set(doc["model_file_markers_located"]) == {"n4"}
    corrected = load_robot_model(doc["model_file"])
    true_n4 = cell.truth[Chain(model).marker_slice()].reshape(-1, 3)[3]
    assert np.linalg.norm(np.subtract(corrected.tool.markers[3].xyz, true_n4)) < 1.0 < np.linalg.norm(
        np.subtract(model.tool.markers[3].xyz, true_n4))


def test_validation_is_scored_with_the_calibration_registration_not_re_registered():
    cell = tracker_cell(seed=4)
    result = identify(cell.model, cell.cal)
    doc = ident_result_dict(result, cell.cal, cell.val)
    chain = Chain(cell.model)
    params, located = locate_unseen_markers(result, ["n4"])
    assert set(located) == {"n4"}
    pred = chain.marker_positions(cell.val.q_rad, params)[:, chain.marker_names.index("n4")]
    with_cal_reg = registered_errors(cell.val, pred, result.base2sensor)
    v = doc["metrics"]["validation_unseen_markers"]
    assert v["after"]["EACPE"] == pytest.approx(with_cal_reg.mean())
    assert v["reregistered"]["after"]["EACPE"] < v["after"]["EACPE"]  # re-registering absorbs part of the error
    # The located fourth nest is where the true plate has it, up to what the calibration leaves.
    true_n4 = cell.truth[chain.marker_slice()].reshape(-1, 3)[3]
    model_n4 = params[chain.marker_slice()].reshape(-1, 3)[3]
    assert np.linalg.norm(model_n4 - true_n4) < 1.0  # the last link's own errors (flange vs plate): unobservable
    assert np.linalg.norm(chain.nominal[chain.marker_slice()].reshape(-1, 3)[3] - true_n4) > 4.0


def _poor_nominal(seed: int):
    """The tracker cell whose true J4 zero is 180° from the model's (a convention slip in the
    model file): a start from nominal is far from the truth."""
    cell = tracker_cell(seed)
    chain = Chain(cell.model)
    truth = cell.truth.copy()
    truth[3] += np.pi
    rng = np.random.default_rng(seed)
    cal = observe(chain, cell.cal.q_rad[::len(CAL_NESTS)], truth, CAL_NESTS, cell.base2sensor, rng, 0.03, "cal")
    return cell.model, cal


@pytest.mark.slow
def test_staged_solve_finds_the_best_minimum_where_the_plain_start_does_not(seed=0):
    model, cal = _poor_nominal(seed)
    result = identify(model, cal)
    by_label = {s["label"]: s for s in result.starts}
    log.info("seed %d, J4 180° off: %s", seed,
             "; ".join(f"{s['label']} cost {s['cost']:.4g} rms {s['rms_mm']:.4f} mm" for s in result.starts))
    best = _reference_cost(model, cal)
    staged, plain = by_label["staged from nominal"], by_label["plain from nominal"]
    assert staged["cost"] <= best * (1 + 1e-6) and staged["same_minimum"]
    assert result.rms_mm < 0.04
    # The plain one-stage solve from nominal stops in a worse minimum, and the fit says so.
    assert plain["cost"] > 100 * staged["cost"] and not plain["same_minimum"]
    (warning,) = [w for w in result.warnings if "starts disagree" in w]
    assert "plain from nominal" in warning and f"rms {plain['rms_mm']:.4g} mm" in warning
    # The staged solve alone reaches it too: the extra starts are a check, not the cure.
    alone = identify(model, cal, IdentOptions(n_starts=1))
    assert alone.starts[0]["cost"] == pytest.approx(staged["cost"], rel=1e-6) and not alone.warnings


@pytest.mark.slow
def test_a_minimum_the_random_starts_miss_is_reached_by_the_flipped_zero_start():
    """The same poor nominal, another seed: the staged solve from nominal fits the data as well
    (same rms) but with the tool turned half a turn on the flange and J5 with it, 140 mm outside
    the tool's ±10 mm prior, and no random start does better (the reference's many starts find the
    best once). The screened start with J4's zero turned 180° reaches the best minimum; the fit
    keeps it, without the prior's warning, and reports J4's offset near ±180°."""
    model, cal = _poor_nominal(1)
    result = identify(model, cal)
    best = _reference_cost(model, cal)
    log.info("seed 1, J4 180° off: %s; reference best %.4g",
             "; ".join(f"{s['label']} cost {s['cost']:.4g} rms {s['rms_mm']:.4f} mm" for s in result.starts), best)
    by_label = {s["label"]: s for s in result.starts}
    assert by_label["staged from nominal"]["cost"] > 2 * best
    assert result.starts[0]["label"] == "staged from J4 zero +180°"
    assert result.starts[0]["cost"] <= best * (1 + 1e-6) and result.rms_mm < 0.04
    assert not [w for w in result.warnings if "far outside their prior" in w]
    assert abs(abs(np.degrees(result.params[3])) - 180.0) < 1.0


def test_starts_that_agree_raise_no_warning_and_the_solve_is_deterministic():
    cell = tracker_cell(seed=5)
    a, b = identify(cell.model, cell.cal, IdentOptions(seed=7)), identify(cell.model, cell.cal, IdentOptions(seed=7))
    assert all(s["same_minimum"] for s in a.starts) and not [w for w in a.warnings if "starts" in w]
    np.testing.assert_array_equal(a.params, b.params)
    assert [s["cost"] for s in a.starts] == [s["cost"] for s in b.starts]


def test_the_corrected_model_places_a_second_unseen_tool_where_the_true_arm_does():
    """Tool A: the nest plate (10 mm off). Tool B: a point 120 mm out on the true flange, never
    measured. The flange's own placement on the last axis (its offset, d, a, α, β) is made exact
    here: no data of one tool can tell it from the tool's position (test_tool_unknowns bounds
    that part); every other link error is there."""
    cell = tracker_cell(seed=6, link_mm=0.5, angle_deg=0.1)
    chain = Chain(cell.model)
    truth = cell.truth.copy()
    last = [chain.index(k)[-1] for k in ("d", "a", "alpha", "beta")] + [chain.n - 1]
    truth[last] = chain.nominal[last]
    rng = np.random.default_rng(60)
    q_cal = cell.cal.q_rad[::len(CAL_NESTS)]
    cal = observe(chain, q_cal, truth, CAL_NESTS, cell.base2sensor, rng, 0.03, "cal")
    result = identify(cell.model, cal)
    tool_b = np.array([0.0, 120.0, 80.0])

    def at(params, q):
        p = params.copy()
        p[chain.marker_slice().start: chain.marker_slice().start + 3] = tool_b
        return chain.marker_positions(q, p)[:, 0]

    q = rng.uniform(cell.model.lower_limits_rad * 0.7, cell.model.upper_limits_rad * 0.7, (200, chain.n))
    seen = apply(cell.base2sensor, at(truth, q))  # where the tracker would see tool B: no noise
    after = np.linalg.norm(apply(result.base2sensor["sensor"], at(result.params, q)) - seen, axis=1)
    nominal_reg = identify(cell.model, cal, IdentOptions(n_starts=1, exclude=tuple(
        n for n in chain.param_names if not n.startswith(CAL_NESTS)))).base2sensor  # nominal arm, best registration
    before = np.linalg.norm(apply(nominal_reg["sensor"], at(chain.nominal, q)) - seen, axis=1)
    log.info("tool B over 200 configurations: corrected model mean %.4f / max %.4f mm; nominal mean %.3f / max %.3f mm",
             after.mean(), after.max(), before.mean(), before.max())
    assert after.mean() < 0.05 and after.max() < 0.15  # tracker noise: 0.03 mm per coordinate
    assert before.mean() > 20 * after.mean()


def test_noise_free_data_do_not_make_rounding_level_costs_disagree():
    """Without noise every start ends at a cost of rounding level, in ratios that mean nothing."""
    cell = tracker_cell(seed=8, noise_mm=0.0)
    result = identify(cell.model, cell.cal)
    assert result.rms_mm < 1e-6
    assert not [w for w in result.warnings if "starts disagree" in w] and all(s["same_minimum"] for s in result.starts)


@pytest.mark.slow  # a multi-start search over data no model describes (11 CPU-s); the verdict's path: test_fit.py's far marker
def test_a_minimum_that_does_not_describe_the_data_is_refused_with_exit_status_1(tmp_path):
    """The data's J2 and J3 columns exchanged (a robot model that is not this arm's: no parameter
    set describes it; a zero 120°–180° off is now reached by the flipped-zero starts): no start
    comes near (the best leaves about 100 mm), and the command says not to use the model and
    exits 1 — after writing what it found."""
    cell = tracker_cell(2)
    chain = Chain(cell.model)
    cal = observe(chain, cell.cal.q_rad[::len(CAL_NESTS)], cell.truth, CAL_NESTS, cell.base2sensor,
                  np.random.default_rng(2), 0.03, "cal")
    swapped = cal.q_rad.copy()
    swapped[:, [1, 2]] = swapped[:, [2, 1]]
    # the tracker's stated spread (0.03 mm, one sample a row): judged against the sensor's noise, not
    # an estimate from residuals (tests/calib/test_estimated_noise_guard.py covers data without spreads)
    cal = from_arrays(swapped, cal.xyz_mm, marker=cal.marker, std_mm=np.full(len(cal), 0.03), count=np.ones(len(cal), int))
    write_model_yaml(cell.model, tmp_path / "robot.yaml")
    write_csv(cal, tmp_path / "cal.csv")
    out = tmp_path / "full.json"
    res = CliRunner().invoke(app, ["fit", str(tmp_path / "cal.csv"), "--robot", str(tmp_path / "robot.yaml"),
                                   "--method", "full", "-o", str(out)])
    doc = json.loads(out.read_text())
    log.info("J2/J3 exchanged: rms %.1f mm; %s", doc["rms_mm"], doc["do_not_use"])
    assert res.exit_code == 1 and "DO NOT USE this identified model" in res.output
    assert doc["rms_mm"] > 10 and "does not describe the data" in doc["do_not_use"][0]
