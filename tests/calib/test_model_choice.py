"""The data choose the model (``calib.fit.model_choice``), "enter" is earned (``calib.robot.controller``),
and the default posterior is the Laplace Gaussian checked by PSIS (``calib.fit.psis``).

Simulated tracker cells (``tests.calib.tracker_sim``: a Stäubli TX60 with a three-nest plate)
with known zero-offsets, and optionally link errors and a tool that is not where the model says.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calib.fit.auto_fit import auto_fit
from calib.robot.controller import earned_reasons
from calib.measure.dataset import from_arrays
from calib.fit.offsets import FitOptions
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.fit.model_choice import Score, choose_model, fold_labels, one_se_choice
from calib.fit.psis import psis
from calib.robot.transforms import pose_to_matrix
from tests.calib.tracker_sim import CAL_NESTS, TRACKER2BASE_POSE, configurations, link_errors, observe, plate_model

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = 20  # samples averaged per configuration: std_mm is the spread of one, the noise of the mean is /√20


def cell(seed: int, *, link_mm: float = 0.0, angle_deg: float = 0.0, tool_shift_mm=(0.0, 0.0, 0.0),
         noise_mm: float = 0.02, k: int = 36):
    """(model, truth chain vector, calibration data): offsets ~ N(0, 0.1°), link errors of the given
    size, the tool's markers shifted by ``tool_shift_mm`` (flange frame) and not declared, and the
    measured per-sample spread in the data (std_mm, n)."""
    rng = np.random.default_rng(seed)
    model = plate_model()
    chain = Chain(model)
    truth = link_errors(chain, rng, link_mm, angle_deg) if link_mm else chain.nominal.copy()
    truth[: chain.n] = np.radians(rng.normal(0.0, 0.1, chain.n))
    ms = chain.marker_slice()
    truth[ms] = (truth[ms].reshape(-1, 3) + np.asarray(tool_shift_mm)).ravel()
    b2s = np.linalg.inv(pose_to_matrix(*TRACKER2BASE_POSE))
    cal = observe(chain, configurations(model, rng, k), truth, CAL_NESTS, b2s, rng, noise_mm / np.sqrt(SAMPLES), "cal")
    cal = replace(cal, std_mm=np.full(len(cal), noise_mm), count=np.full(len(cal), SAMPLES))
    return model, truth, cal


def test_folds_group_whole_configurations():
    _, _, cal = cell(1, k=12)
    labels, grouping = fold_labels(cal, 5, seed=0)
    assert grouping == "configuration" and set(labels) == set(range(5))
    for c in np.unique(cal.config):
        assert len(set(labels[cal.config == c])) == 1  # a configuration's markers are held out together


def test_one_standard_error_rule_prefers_the_simplest_close_model():
    a = Score("simple", 0, 10, np.array([1.00, 1.10, 0.90, 1.05]))
    b = Score("rich", 1, 30, np.array([0.98, 1.08, 0.88, 1.02]))  # better mean, well within one se
    c = Score("richer", 2, 40, np.array([0.50, 0.55, 0.45, 0.52]))  # clearly better
    assert one_se_choice([a, b]) == "simple"
    assert one_se_choice([a, b, c]) == "richer"
    assert one_se_choice([a, replace(c, failed="fold 1: no")]) == "simple"


def test_clean_data_choose_offsets_only_and_large_link_errors_a_richer_model():
    model, truth, cal = cell(2)
    clean = choose_model(model, cal, FitOptions())
    assert clean.chosen == "offsets", clean.format()
    assert clean.score("offsets").mean_mm < clean.nominal.mean_mm / 10

    model, truth, cal = cell(3, link_mm=0.5, angle_deg=0.1)
    rough = choose_model(model, cal, FitOptions())
    assert rough.chosen in ("offsets+tool+links", "full"), rough.format()
    assert rough.score(rough.chosen).mean_mm < rough.score("offsets").mean_mm / 2
    assert rough.link_scale["length_mm"] >= 0.1  # the evidence asks for a prior as wide as the errors


def _entered_offsets_outside_truth(done, truth) -> list[str]:
    bad = []
    for j in done.doc["joint_offsets"]:
        action = next(a["action"] for a in done.doc["controller"]["axes"] if a["axis"] == j["joint"])
        if action == "enter":
            lo, hi = j["ci95_deg"]
            if not lo <= np.degrees(truth[j["index"] - 1]) <= hi:
                bad.append(j["joint"])
    return bad


def test_an_undeclared_30_mm_tool_never_gets_enter_beside_wrong_offsets():
    model, truth, cal = cell(4, link_mm=0.2, angle_deg=0.02, tool_shift_mm=(30.0, 0.0, 0.0))
    done = auto_fit(model, cal, None, FitOptions(n_draws=300), n_random=50, include_full=False)
    assert done.choice.chosen != "offsets"  # the drawing's tool cannot predict held-out configurations
    assert done.refused or not _entered_offsets_outside_truth(done, truth), (done.refused, done.choice.format())
    # The marker 30 mm from the drawing is outside its ±10 mm prior: the tool warning is open, nothing is entered.
    assert any("outside its prior" in r for r in done.refused)
    assert all(a["action"] != "enter" for a in done.doc["controller"]["axes"])


def test_enter_is_given_on_a_clean_cell_with_offsets_inside_their_intervals():
    model, truth, cal = cell(5)
    done = auto_fit(model, cal, None, FitOptions(n_draws=300), n_random=50, include_full=False)
    assert not done.refused, done.refused
    assert [a["action"] for a in done.doc["controller"]["axes"]].count("enter") >= 4
    assert not _entered_offsets_outside_truth(done, truth)
    assert done.doc["diagnostics"]["importance"]["k_hat"] < 0.7


def test_enter_is_withheld_when_the_held_out_error_is_many_times_the_noise_or_no_better_than_nominal():
    doc = {"model_choice": {"chosen": "offsets", "nominal": {"model": "nominal", "cv_mean_mm": 2.0, "cv_se_mm": 0.1},
                            "candidates": [{"model": "offsets", "cv_rms_mm": 1.0, "cv_mean_mm": 0.9, "cv_se_mm": 0.05,
                                            "failed": None}]},
           "diagnostics": {"error_budget": {"t": {"sample_spread_mm": 0.02, "noise_mm": 0.02, "n_rows": 10}}}}
    assert any("× the measured spread of one sample" in r for r in earned_reasons(doc))
    doc["model_choice"]["candidates"][0].update(cv_rms_mm=0.05, cv_mean_mm=0.045)
    assert earned_reasons(doc) == []
    doc["model_choice"]["nominal"]["cv_mean_mm"] = 0.04
    assert any("no better than the uncalibrated" in r for r in earned_reasons(doc))
    # The case: validation 15.9 mm after the correction never stands beside "enter".
    doc["model_choice"]["nominal"]["cv_mean_mm"] = 2.0
    doc["metrics"] = {"validation_absolute": {"before": {"mean": 20.0}, "after": {"mean": 15.9}}}
    assert any("validation error after the correction 15.900 mm" in r for r in earned_reasons(doc))


def test_the_held_out_error_is_judged_against_the_noise_of_the_averaged_rows_and_an_outlier_is_named():
    """Rows averaging 20 samples of 0.02 mm spread carry 0.0045 mm of noise: a held-out error of
    0.03 mm per axis is within 3× the spread of one sample but 7× the rows' noise — not earned.
    Where one held-out configuration carries the error it is named."""
    per_axis = 0.03
    cand = {"model": "offsets", "cv_rms_mm": per_axis * math.sqrt(3.0), "cv_mean_mm": 0.04, "cv_se_mm": 0.01,
            "cv_median_mm": 0.008, "worst_configurations": [["c7", 0.9], ["c2", 0.01]], "failed": None}
    doc = {"model_choice": {"chosen": "offsets", "nominal": {"model": "nominal", "cv_mean_mm": 2.0}, "candidates": [cand]},
           "diagnostics": {"error_budget": {"t": {"sample_spread_mm": 0.02, "noise_mm": 0.02 / math.sqrt(20),
                                                  "n_rows": 108}}}}
    (reason,) = earned_reasons(doc)
    assert "7× the noise of the averaged measurement" in reason, reason
    assert "configuration c7 (0.9 mm)" in reason and "c2" not in reason and "measure it again" in reason
    cand.update(worst_configurations=[["c7", 0.06], ["c2", 0.05]], cv_median_mm=0.045)  # all off: the model
    (reason,) = earned_reasons(doc)
    assert "the chosen model (offsets) does not describe this robot" in reason
    cand["cv_rms_mm"] = 0.012 * math.sqrt(3.0)  # 2.7× the rows' noise: consistent with it
    assert earned_reasons(doc) == []


# --- PSIS -------------------------------------------------------------------------------------------
def test_pareto_k_is_low_for_a_gaussian_and_high_for_a_banana_under_their_laplace_proposals():
    s = 16000
    rng = np.random.default_rng(0)
    # A Gaussian target N(0, I) and its Laplace proposal (exact): constant weights; a slightly wider
    # proposal (1.2): bounded weights. Both far below 0.7.
    x = rng.normal(0.0, 1.2, (s, 3))
    assert psis(-0.5 * np.sum(x**2, 1) + 0.5 * np.sum((x / 1.2) ** 2, 1)).k_hat < 0.5

    # A banana: x1 ~ N(0, 1), x2 | x1 ~ N(b (x1² − 1), 1); its Laplace Gaussian at the mode
    # (0, −b) is N((0, −b), I), which misses the curved arms: heavy-tailed weights.
    b = 10.0
    ks = []
    for seed in range(3):
        r = np.random.default_rng(seed)
        x = r.normal(0.0, 1.0, (s, 2)) + [0.0, -b]
        log_p = -0.5 * x[:, 0] ** 2 - 0.5 * (x[:, 1] - b * (x[:, 0] ** 2 - 1)) ** 2
        ks.append(psis(log_p + 0.5 * np.sum((x - [0.0, -b]) ** 2, 1)).k_hat)
    assert min(ks) > 0.7, ks


def test_pareto_k_follows_the_theory_of_a_too_narrow_gaussian_proposal():
    """Target N(0, 1), proposal N(0, s²), s < 1: the weights' tail is Pareto with k = 1 − s²."""
    for scale, k_true in ((0.3, 0.91), (0.8, 0.36)):
        ks = []
        for seed in range(4):
            x = np.random.default_rng(seed).normal(0.0, scale, 16000)
            ks.append(psis(-0.5 * x**2 + 0.5 * (x / scale) ** 2).k_hat)
        assert abs(np.mean(ks) - k_true) < 0.12, (scale, ks)


def test_psis_weights_give_the_target_moments():
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 1.5, 8000)  # proposal N(0, 1.5²) for the target N(0.3, 1)
    res = psis(-0.5 * (x - 0.3) ** 2 + 0.5 * (x / 1.5) ** 2)
    assert res.reliable and 2000 < res.ess < 8000
    assert abs(np.sum(res.weights * x) - 0.3) < 0.05
    assert abs(np.sum(res.weights * (x - 0.3) ** 2) - 1.0) < 0.08


def test_psis_refuses_too_few_weights():
    with pytest.raises(ValueError, match="at least 20"):
        psis(np.zeros(10))


def test_a_posterior_the_laplace_gaussian_misses_goes_to_the_random_walk():
    """A strongly correlated target (ρ = 0.99, scales 1 and 10) offered a proposal that ignores the
    correlation and is too narrow (identity): k̂ ≥ 0.7, and the random walk in that proposal's
    whitened coordinates, its step adapted, recovers the covariance with R-hat near 1."""
    from calib.fit.laplace_sampling import laplace_importance, random_walk
    from calib.fit.sampling import split_rhat

    cov = np.array([[1.0, 0.99 * 10.0], [0.99 * 10.0, 100.0]])
    prec = np.linalg.inv(cov)

    def target(x):
        return -0.5 * np.einsum("...i,ij,...j->...", x, prec, x)

    chains, diag = laplace_importance(target, np.zeros(2), np.eye(2), n_chains=4, n_draws=2000, seed=0, adapt=0)
    assert chains is None and diag["k_hat"] >= 0.7
    draws = random_walk(target, np.zeros(2), np.eye(2), seed=0)
    np.testing.assert_allclose(np.cov(draws.flat.T), cov, rtol=0.2, atol=0.15)
    assert split_rhat(draws.samples).max() < 1.05 and draws.diagnostics["settled"], draws.diagnostics


def test_the_random_walk_gets_a_40_parameter_correlated_posterior_right():
    """40 parameters in mm and rad (scales 1e-6…10), correlated, and a Laplace covariance 0.3–1×
    the truth per principal direction: the walk's spread is the target's within 10 % in every
    parameter, its mean log density the target's (−d/2), and R-hat of the log density near 1.
    (emcee's differential-evolution ensemble left the spread 8–12 % short after 5900 steps.)"""
    from calib.fit.laplace_sampling import random_walk

    d = 40
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    lam, scales = np.logspace(-2, 0, d), np.logspace(-6, 1, d)
    cov = ((q * lam) @ q.T) * np.outer(scales, scales)
    prec = np.linalg.inv(cov)

    def target(x):
        return -0.5 * np.einsum("...i,ij,...j->...", x, prec, x)

    laplace = ((q * lam * rng.uniform(0.3, 1.0, d)) @ q.T) * np.outer(scales, scales)
    draws = random_walk(target, np.zeros(d), laplace, seed=1, max_steps=12000)  # the test's budget: it settles at 28 000
    ratio = np.sqrt(np.diag(np.cov(draws.flat.T)) / np.diag(cov))
    assert 0.9 < ratio.min() and ratio.max() < 1.1, (ratio.min(), ratio.max())
    assert abs(target(draws.flat).mean() + d / 2) < 1.0
    assert draws.diagnostics["rhat_log_density"] < 1.05 and draws.diagnostics["ess_min"] > 200, draws.diagnostics


def test_too_few_configurations_to_cross_validate_fit_the_simplest_model_and_enter_nothing():
    model, truth, cal = cell(6, k=3)
    done = auto_fit(model, cal, None, FitOptions(n_draws=200), n_random=20, include_full=False)
    assert done.choice.chosen == "offsets" and all(s.failed for s in done.choice.scores)
    assert "too few configurations" in done.choice.format()
    assert any("could not be fitted in every cross-validation fold" in r for r in done.model_refused)
    assert done.refused and done.doc["entered"]["verdict"] == "do not enter"  # nothing can be scored held out
    assert all(a["action"] != "enter" for a in done.doc["controller"]["axes"])


# --- real data: a UR10 measured by a Leica laser tracker (../shared/fixtures/ur10-ipa-tracker-6dof/) ---------
UR10_SERIES_B = (Path(__file__).resolve().parents[3] / "shared" / "fixtures" / "ur10-ipa-tracker-6dof" / "Series_B"
                 / "measurements_joint_configurations.csv")


def _ur10_series(path: Path, rows: slice, split: str):
    """Rows of an IPA series as a dataset: ';' separated, decimal comma, joints in radians, the
    T-Mac position in mm, its per-axis standard deviation as the per-sample spread."""
    lines = path.read_text(encoding="utf-8").splitlines()
    head = lines[0].split(";")
    a = np.array([[float(v.replace(",", ".")) for v in line.split(";")] for line in lines[1:] if line.strip()])[rows]
    col = {h: i for i, h in enumerate(head)}
    q = a[:, [col[k] for k in ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                               "wrist_2_joint", "wrist_3_joint")]]
    xyz = a[:, [col[f"measurement_{c}"] for c in "xyz"]]
    std = np.sqrt(np.mean(a[:, [col[f"measurement_std_{c}"] for c in "xyz"]] ** 2, axis=1))
    return from_arrays(q, xyz, marker="tmac", sensor="tracker", config=np.array([f"c{i}" for i in range(len(a))]),
                       std_mm=std, count=np.ones(len(a)), split=split)


@pytest.mark.skipif(not UR10_SERIES_B.is_file(), reason="the shared UR10 tracker data is not next to the repository")
def test_real_ur10_tracker_data_get_an_answer_and_enter_only_where_earned():
    """Calibrate on 120 configurations of series B, score 300 others: the default answers (the
    Laplace check passes), chooses a model that predicts held-out configurations far better than
    the uncalibrated robot, and withholds "enter" while the held-out error is many times the
    tracker's spread (robot error no candidate describes)."""
    model = load_robot_model(ROOT / "fixtures" / "robots" / "ur10.yaml")
    cal = _ur10_series(UR10_SERIES_B, slice(0, 120), "cal")
    val = _ur10_series(UR10_SERIES_B, slice(120, 420), "val")
    done = auto_fit(model, cal, val, FitOptions(n_draws=300), n_random=50, include_full=False)
    chosen = done.choice.score(done.choice.chosen)
    assert done.choice.chosen != "offsets" and chosen.mean_mm < done.choice.nominal.mean_mm / 5, done.choice.format()
    assert done.doc["diagnostics"]["importance"]["k_hat"] < 0.7
    # The chosen model's own offsets on the nominal arm are judged against the robot as found (its tool
    # fitted, not the drawing's): where they do not help the held-out points, its guard says so.
    v = done.doc["metrics"]["validation_absolute"]
    if v["after"]["mean"] >= v["before"]["mean"]:
        assert any("the validation points get no better" in r for r in done.model_refused)
    spread = float(np.sqrt(np.mean(cal.std_mm**2)))
    if chosen.rms_mm / np.sqrt(3) > 3 * spread:
        assert any("the measured spread of one sample" in r for r in done.model_refused)
    # What the controller gets is earned held out against the robot as found (calib.fit.entered).
    entered = done.doc["entered"]
    assert entered["heldout"]["scored_on"] == "validation" and entered["heldout"]["as_found"]["n"] == 300
    earned = entered["heldout"]["improvement_mm"]["ci95"][0] > 0 and not entered["reasons"]
    assert (entered["verdict"] == "enter") == earned
    typed = {a["axis"] for a in done.doc["controller"]["axes"] if a["action"] == "enter"}
    assert typed == {o["joint"] for o in entered["offsets"] if o["enter"]}


def test_each_fold_estimates_the_link_scale_on_its_training_configurations_only(monkeypatch):
    """The link scale is fitted to data: a fold that used the scale of all the data would have
    seen its held-out configurations. Every fold's scale is estimated on configurations disjoint
    from the ones it scores, and the table says what the folds found."""
    import calib.fit.model_choice as mc

    model, truth, cal = cell(3, link_mm=0.5, angle_deg=0.1, k=20)
    seen: list[set] = []
    real = mc.empirical_link_scale

    def spy(model, data, base, *args, **kwargs):
        seen.append(set(np.unique(data.config).tolist()))
        return real(model, data, base, *args, **kwargs)

    monkeypatch.setattr(mc, "empirical_link_scale", spy)
    labels, _ = fold_labels(cal, 5, seed=0)
    choice = choose_model(model, cal, FitOptions(), include_full=False)
    everything = set(np.unique(cal.config).tolist())
    assert seen[0] == everything  # the chosen model's final fit: the scale of all the data
    folds = seen[1:]
    assert len(folds) == 5 and len(choice.link_scale["per_fold"]) == 5
    for f, train in enumerate(folds):
        held_out = set(np.unique(cal.config[labels == f]).tolist())
        assert held_out and not train & held_out and train | held_out == everything
    assert all(t is not None and t[0] in (0.01, 0.03, 0.1, 0.3, 1.0, 3.0) for t in choice.link_scale["per_fold"])
    assert "each fold its own (on its training configurations)" in choice.format()


def test_a_forced_model_is_the_only_one_fitted_and_still_scored_on_held_out_configurations(monkeypatch):
    """``--model offsets+tool``: no other candidate is fitted (no fold fits of them, no link-scale
    search for the links model), and the forced one is still cross-validated, so its held-out error
    and misfit stand beside the nominal model's. Another forced model is scored beside offsets+tool
    only: the offsets to enter are that model's, and its misfit widens their intervals."""
    import calib.fit.model_choice as mc

    model, _, cal = cell(4, k=20)
    fitted: list[str] = []
    real = mc._candidate_distances

    def spy(candidate, *args, **kwargs):
        fitted.append(candidate.name)
        return real(candidate, *args, **kwargs)

    def no_scale(*args, **kwargs):
        raise AssertionError("the link scale is searched only for a links model")

    monkeypatch.setattr(mc, "_candidate_distances", spy)
    monkeypatch.setattr(mc, "empirical_link_scale", no_scale)
    choice = choose_model(model, cal, FitOptions(), force="offsets+tool")
    assert choice.chosen == "offsets+tool" and choice.forced
    assert [s.name for s in choice.scores] == ["offsets+tool"] and set(fitted) == {"offsets+tool"}
    assert len(fitted) == choice.folds == 5
    forced = choice.score("offsets+tool")
    assert not forced.failed and forced.mean_mm < choice.nominal.mean_mm and forced.misfit is not None
    assert "only it was fitted" in choice.format() and "← chosen (--model)" in choice.format()
    fitted.clear()
    other = choose_model(model, cal, FitOptions(), force="offsets")  # … beside offsets+tool, the controller's model
    assert [s.name for s in other.scores] == ["offsets", "offsets+tool"] and set(fitted) == {"offsets", "offsets+tool"}
