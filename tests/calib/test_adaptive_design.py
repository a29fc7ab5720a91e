"""The sequential designer (calib.plan.adaptive) on toy problems with a known answer, and the
fit's linearised model over a real plan (calib.fit.design)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.plan.adaptive import T95, DesignModel, SequentialDesign, StopRule


def toy(rows, prior_sd=10.0) -> DesignModel:
    """Two offsets (rad) measured through 1-row candidates ``rows`` (N, 2); workspace = identity."""
    r = np.asarray(rows, dtype=float)[:, None, :]
    return DesignModel(rows=r, prior=np.eye(2) / prior_sd**2, offsets=np.array([0, 1]),
                       offset_names=("A1.offset", "A2.offset"), workspace=np.eye(2), names=("A1.offset", "A2.offset"))


def test_prefers_the_parameter_not_yet_measured():
    # candidates 0, 1 see parameter 0; candidate 2 sees parameter 1. After 0 is measured, 2 wins.
    d = SequentialDesign(toy([[1, 0], [1, 0], [0, 1]]), StopRule(interval_deg=1.0), sigma_mm=0.1)
    d.add(0)
    assert d.choose(np.ones(3)).index == 2


def test_prefers_the_cheaper_of_two_equally_informative():
    d = SequentialDesign(toy([[1, 0], [1, 0], [0, 1]]), StopRule(workspace_within_pct=10), sigma_mm=0.1)
    d.add(2)
    assert d.choose(np.array([1.0, 5.0, 1.0])).index == 0
    assert d.choose(np.array([5.0, 1.0, 1.0])).index == 1


def test_trades_information_against_seconds():
    # candidate 0 is 4x as informative (2x the row) as 1 on the same parameter; parameter 1 is
    # known already. Gain of the first measurement at σ=1 with a vague prior is ~ all the
    # variance either way, so only a cheap near-useless one loses: 0 (10 s) vs 2 (1 s, row 0.01).
    d = SequentialDesign(toy([[2, 0], [1, 0], [0.01, 0], [0, 1]], prior_sd=1.0), StopRule(interval_deg=1.0),
                         sigma_mm=1.0)
    d.add(3)
    g = d.gains(np.array([0, 1, 2]))["interval"]
    assert g[0] > g[1] > g[2] > 0
    # per second: 0 at 10 s beats 2 at 1 s (gain of 2 is ~1e-4 of 0's)
    assert d.choose(np.array([10.0, 10.0, 1.0, 1.0])).index == 0
    # but when 0 costs 100x as much as 1, the less informative 1 is chosen
    assert d.choose(np.array([1000.0, 10.0, 1000.0, 1.0])).index == 1


def test_gain_is_the_exact_reduction_of_the_linear_model():
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(6, 3, 4))
    model = DesignModel(rows=rows, prior=np.eye(4) * 0.01, offsets=np.array([0, 2]), offset_names=("a", "b"),
                        workspace=np.diag([1.0, 2.0, 0.0, 1.0]))
    d = SequentialDesign(model, StopRule(interval_deg=0.1, workspace_within_pct=5), sigma_mm=0.5)
    d.add(1)
    before = d.covariance()
    g = d.gains(np.array([3]))
    after = d.covariance([1, 3])
    k = [0, 2]
    want_int = (np.trace(before[np.ix_(k, k)]) - np.trace(after[np.ix_(k, k)])) / np.trace(before[np.ix_(k, k)])
    want_ws = (np.sum(model.workspace * before) - np.sum(model.workspace * after)) / np.sum(model.workspace * before)
    assert g["interval"][0] == pytest.approx(want_int, rel=1e-9)
    assert g["workspace"][0] == pytest.approx(want_ws, rel=1e-9)


def test_held_out_criterion_counts_the_sensor_noise():
    # held-out error² = 3σ² + workspace²: with the noise dominating, a few configurations predict
    # nearly as well as all of them, so the held-out rule stops long before the workspace rule.
    rows = np.tile(np.eye(2), (40, 1)).reshape(40, 2, 2)
    model = DesignModel(rows=rows, prior=np.eye(2) * 1e-6, offsets=np.array([0]), offset_names=("a",),
                        workspace=np.eye(2))

    def stops(rule):
        d = SequentialDesign(model, rule, sigma_mm=0.03)
        while not (st := d.status()).stop:
            d.add(d.choose(np.ones(40)).index)
        return len(d.measured), st

    n_held, st = stops(StopRule(held_out_within_pct=10, min_configurations=2))
    n_ws, _ = stops(StopRule(workspace_within_pct=10, min_configurations=2))
    assert st.held_out_mm == pytest.approx(math.sqrt(3 * 0.03**2 + st.workspace_mm**2))
    assert st.held_out_mm <= 1.1 * st.full_held_out_mm and "held-out" in st.reason
    # workspace² = 2σ²/n: within 10 % of all 40 needs n ≥ 40/1.21; held-out: 3σ² + 2σ²/n ≤ 1.21·(3σ² + 2σ²/40), n ≥ 3
    assert n_ws == math.ceil(40 / 1.1**2) and n_held < n_ws / 3


def test_stop_rule_half_width_and_minimum():
    # each candidate measures offset 0 and 1 with σ=0.001 rad-equivalent: sd after n = 0.001/√n rad
    rows = np.tile(np.eye(2), (20, 1)).reshape(20, 2, 2)
    model = DesignModel(rows=rows, prior=np.eye(2) * 1e-6, offsets=np.array([0, 1]), offset_names=("a", "b"),
                        workspace=np.eye(2))
    limit = math.degrees(T95 * 0.001 / math.sqrt(4.5))  # met from the 5th configuration on
    d = SequentialDesign(model, StopRule(interval_deg=limit, min_configurations=3), sigma_mm=0.001)
    seen = []
    while not (st := d.status()).stop:
        seen.append(st.max_half_width_deg)
        d.add(d.choose(np.ones(20)).index)
    assert len(d.measured) == 5 and st.max_half_width_deg <= limit < seen[-1]
    assert "stop rule met" in st.reason
    d2 = SequentialDesign(model, StopRule(interval_deg=1e3, min_configurations=3), sigma_mm=0.001)
    d2.add(0)
    assert not d2.status().stop  # met, but fewer than the minimum
    d2.add(1), d2.add(2)
    assert d2.status().stop


def test_max_configurations_and_exhaustion_stop():
    rows = np.tile(np.eye(2), (4, 1)).reshape(4, 2, 2)
    model = DesignModel(rows=rows, prior=np.eye(2), offsets=np.array([0]), offset_names=("a",), workspace=np.eye(2))
    d = SequentialDesign(model, StopRule(interval_deg=1e-9, max_configurations=2), sigma_mm=1.0)
    d.add(0), d.add(1)
    assert d.status().stop and "max_configurations" in d.status().reason
    d = SequentialDesign(model, StopRule(interval_deg=1e-9), sigma_mm=1.0)
    for i in range(4):
        d.add(i)
    assert d.status().stop and "exhausted" in d.status().reason
    with pytest.raises(ValueError):
        d.add(0)


def test_bad_rules_are_refused():
    with pytest.raises(ValueError, match="a stop rule needs one of interval_deg, region_error_mm"):
        StopRule()
    with pytest.raises(ValueError, match="max_configurations"):
        StopRule(interval_deg=0.1, min_configurations=5, max_configurations=4)


def test_design_model_of_a_plan_leaves_out_what_the_full_plan_cannot_determine():
    from calib.fit.design import design_model
    from calib.fit.offsets import FitOptions
    from calib.robot.model import load_robot_model
    from pathlib import Path

    model = load_robot_model(Path(__file__).resolve().parents[2] / "fixtures/robots/kuka_iiwa14_r820.yaml")
    rng = np.random.default_rng(0)
    q = rng.uniform(model.lower_limits_rad * 0.6, model.upper_limits_rad * 0.6, size=(25, model.n_joints))
    dm = design_model(model, q, {"mocap": [model.marker_names[0]]}, FitOptions(method="laplace"))
    assert dm.rows.shape[:2] == (25, 3)
    # A1 (a turn of the registration) and A7 (the tool's turn about the last axis) are not determinable
    assert "A1.offset" not in dm.offset_names and "A7.offset" not in dm.offset_names
    assert set(dm.offset_names) == {f"A{i}.offset" for i in range(2, 7)}
    d = SequentialDesign(dm, StopRule(workspace_within_pct=10), sigma_mm=0.03)
    full = d.full_workspace_mm()
    for i in range(25):
        d.add(i)
    assert d.status().workspace_mm == pytest.approx(full)


# ---------------------------------------------------------------------------------------------
# The batch plan (plan_route / choose_route) and its tours (calib.plan.route)

def test_cheapest_insertion_and_two_opt_against_brute_force():
    from calib.plan.route import insertion_costs, path_seconds, two_opt

    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 10, size=(9, 2))
    cost = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    path = [0, 3, 1, 5]
    extra, pos = insertion_costs(path, cost, np.array([2, 4, 6]))
    for node, e, k in zip([2, 4, 6], extra, pos):
        tries = [path_seconds(path[:i + 1] + [node] + path[i + 1:], cost) - path_seconds(path, cost)
                 for i in range(len(path))]
        assert e == pytest.approx(min(tries)) and k == int(np.argmin(tries))
    # 2-opt undoes a crossing: on a line, 0 → 2 → 1 → 3 becomes 0 → 1 → 2 → 3
    line = np.abs(np.arange(4.0)[:, None] - np.arange(4.0)[None, :])
    assert two_opt([0, 2, 1, 3], line) == [0, 1, 2, 3]
    shuffled = [0] + list(rng.permutation(np.arange(1, 9)))
    assert path_seconds(two_opt(shuffled, cost), cost) <= path_seconds(shuffled, cost)


def scattered(seed, n=40, L=4):
    """n candidates at random places in a 2-D 'joint space' (move seconds = distance), each with
    3 random rows on L parameters; the robot at the origin."""
    rng = np.random.default_rng(seed)
    rows = rng.normal(size=(n, 3, L)) * rng.uniform(0.2, 1.5, size=(n, 1, 1))
    model = DesignModel(rows=rows, prior=np.eye(L) * 1e-4, offsets=np.arange(L), offset_names=tuple("abcd"[:L]),
                        workspace=np.eye(L))
    xy = rng.uniform(-5, 5, size=(n, 2))
    return model, np.linalg.norm(xy, axis=1), np.linalg.norm(xy[:, None] - xy[None], axis=-1)


def run_to_stop(model, here, between, per, *, batch):
    """(seconds, candidates measured, final status) of a run choosing by choose_route (batch) or
    by the one-step choose."""
    d = SequentialDesign(model, StopRule(workspace_within_pct=15, min_configurations=4), sigma_mm=0.3)
    where, secs = here, 0.0
    while not (st := d.status()).stop:
        c = (d.choose_route(where, between, per) if batch else d.choose(where + per)).index
        secs += where[c] + per
        d.add(c)
        where = between[c]
    return secs, len(d.measured), st


def test_the_planned_route_meets_the_rule_and_its_first_stop_is_the_choice():
    model, here, between = scattered(0)
    d = SequentialDesign(model, StopRule(workspace_within_pct=15, min_configurations=4), sigma_mm=0.3)
    d.add(0)
    route = d.plan_route(here, between, 0.5)
    assert route.status.stop and "stop rule met" in route.status.reason
    assert len(set(route.order)) == len(route.order) and 0 not in route.order
    assert not d.status_of(d.measured + list(route.order[:-1])).stop or len(route.order) == 1
    c = d.choose_route(here, between, 0.5)
    assert c.index == route.order[0] and c.planned == route.order and c.planned_seconds == pytest.approx(route.seconds)
    assert d.choose_route(here, between, 0.5, exclude=[route.order[0]]).index != route.order[0]


def test_the_batch_plan_meets_the_rule_in_less_time_than_the_one_step_choice():
    # A run re-planning its batch after every measurement against one choosing the best gain per
    # second from where the robot stands: both stop when the rule holds (the same predicted error);
    # over seeds the batch run spends less cell time.
    ratios = []
    for seed in range(6):
        model, here, between = scattered(seed)
        t_batch, _, st_b = run_to_stop(model, here, between, 0.5, batch=True)
        t_step, _, st_s = run_to_stop(model, here, between, 0.5, batch=False)
        assert st_b.stop and st_s.stop and "stop rule met" in st_b.reason
        ratios.append(t_batch / t_step)
    assert np.mean(ratios) < 0.95, ratios


def test_the_new_pose_error_takes_each_measured_candidates_own_information_out():
    # With the workspace the candidates' own, the predicted error at a measured candidate is the
    # one of the fit without it (leave-one-out): brute force here, Woodbury in the design.
    rng = np.random.default_rng(3)
    n, r, L = 12, 3, 4
    rows = rng.normal(size=(n, r, L))
    ws = np.einsum("nri,nrj->ij", rows, rows) / (n * r / 3)
    model = DesignModel(rows=rows, prior=0.01 * np.eye(L), offsets=np.array([0]), offset_names=("A2.offset",),
                        workspace=ws, workspace_from_candidates=True)
    d = SequentialDesign(model, StopRule(held_out_within_pct=10, min_configurations=2), sigma_mm=0.2)
    measured = [0, 3, 4, 7, 9]
    var = []
    for c in range(n):
        others = [i for i in measured if i != c]
        cov = d.covariance(others)
        var.append(np.trace(rows[c] @ cov @ rows[c].T))
    want = math.sqrt(np.mean(var) * 3 / r)
    assert d.new_pose_workspace_mm(measured) == pytest.approx(want, rel=1e-9)
    # larger than the in-sample error of the same fit; the status and the rule use it
    assert want > d.workspace_mm(d.covariance(measured))
    d.measured = list(measured)
    st = d.status()
    assert st.workspace_mm == pytest.approx(want, rel=1e-9)
    assert st.held_out_mm == pytest.approx(math.sqrt(3 * 0.2**2 + want**2))
    # the full plan's prediction too: every candidate left out in turn
    full = [np.trace(rows[c] @ d.covariance([i for i in range(n) if i != c]) @ rows[c].T) for c in range(n)]
    assert st.full_workspace_mm == pytest.approx(math.sqrt(np.mean(full) * 3 / r), rel=1e-9)


def test_with_a_pool_the_new_pose_error_and_the_full_plan_stay_the_plans():
    # Candidates 0…7 are the plan's, 8…11 a generated pool. The error at new poses averages over
    # the plan's candidates only (a measured pool candidate adds information, not a place to be
    # scored), and "the full plan" is the plan's eight — brute force against the design.
    rng = np.random.default_rng(5)
    n_plan, n, r, L = 8, 12, 3, 4
    rows = rng.normal(size=(n, r, L))
    ws = np.einsum("nri,nrj->ij", rows[:n_plan], rows[:n_plan]) / (n_plan * r / 3)
    model = DesignModel(rows=rows, prior=0.01 * np.eye(L), offsets=np.array([0]), offset_names=("A2.offset",),
                        workspace=ws, plan_size=n_plan, workspace_from_candidates=True)
    d = SequentialDesign(model, StopRule(held_out_within_pct=10, min_configurations=2), sigma_mm=0.2)

    def brute(measured):
        var = [np.trace(rows[c] @ d.covariance([i for i in measured if i != c]) @ rows[c].T) for c in range(n_plan)]
        return math.sqrt(np.mean(var) * 3 / r)

    measured = [0, 3, 9, 10]  # two of the plan's, two of the pool's
    assert d.new_pose_workspace_mm(measured) == pytest.approx(brute(measured), rel=1e-9)
    assert d.full_workspace_mm() == pytest.approx(brute(list(range(n_plan))), rel=1e-9)
    # measuring the pool as well would predict better than the plan alone: not what the rule compares with
    assert brute(list(range(n))) < d.full_workspace_mm()


# --- issue 35: criteria in the operator's terms, the misfit ------------------------------------
def test_the_region_error_counts_a_misfit_that_no_configuration_reduces():
    # Model error at new poses = sqrt(w² + 3 m²): w falls with every configuration, the misfit m
    # (per axis) does not — a cell whose model leaves more unexplained measures more, and one whose
    # misfit alone exceeds the limit never meets it.
    rows = [[1, 0], [0, 1]] * 20
    limit = 0.5

    def run(misfit):
        d = SequentialDesign(toy(rows), StopRule(region_error_mm=limit), sigma_mm=1.0, misfit_mm=misfit)
        while not d.status().stop:
            d.add(d.choose(np.ones(40)).index)
        return d.status()

    clean, some, much = run(0.0), run(0.2), run(0.3)
    assert clean.reason.startswith("stop rule met") and clean.region_mm <= limit
    assert clean.region_mm == pytest.approx(clean.workspace_mm)  # no misfit: the model's uncertainty alone
    assert some.reason.startswith("stop rule met") and some.n_measured > clean.n_measured
    assert some.region_mm == pytest.approx(math.sqrt(some.workspace_mm**2 + 3 * 0.2**2))
    assert much.reason.startswith("plan exhausted") and much.region_mm > limit  # √3 · 0.3 > 0.5: never met
    assert much.checks[0].name == "region_error_mm" and not much.checks[0].met


def test_joint_space_criteria_average_over_the_declared_joint_space():
    # The joint space sees only the second parameter: its error is sqrt(Σ22 + 3m²), the design
    # chooses what informs it, and the relative criterion compares with the full plan's.
    model = toy([[1, 0], [0, 1], [1, 0], [0, 1], [0.2, 1]])
    model = DesignModel(**{**model.__dict__, "joint_space": np.diag([0.0, 1.0])})
    d = SequentialDesign(model, StopRule(joint_space_error_mm=0.9), sigma_mm=1.0, misfit_mm=0.1)
    first = d.choose(np.ones(5))
    assert first.index in (1, 3, 4) and set(first.gain) == {"joint_space"}
    d.add(first.index)
    st = d.status()
    assert st.joint_space_mm == pytest.approx(math.sqrt(d.covariance()[1, 1] + 3 * 0.1**2))
    full = math.sqrt(np.linalg.inv(model.prior + model.rows[:, 0, :].T @ model.rows[:, 0, :])[1, 1] + 0.03)
    assert st.full_joint_space_mm == pytest.approx(full)
    rel = SequentialDesign(model, StopRule(joint_space_within_pct=10), sigma_mm=1.0, measured=[1, 3, 4])
    check = rel.status().checks[0]
    assert check.predicted == pytest.approx(100 * (rel.status().joint_space_mm / full_without_misfit(model) - 1))
    with pytest.raises(ValueError, match="needs the working joint space"):
        SequentialDesign(toy([[1, 0]]), StopRule(joint_space_error_mm=1.0), sigma_mm=1.0).status()


def full_without_misfit(model):
    return math.sqrt(np.linalg.inv(model.prior + model.rows[:, 0, :].T @ model.rows[:, 0, :])[1, 1])


def test_the_batch_weighs_only_the_criteria_not_yet_met():
    model = toy([[1, 0], [0, 1]])
    model = DesignModel(**{**model.__dict__, "joint_space": np.diag([1.0, 0.0])})
    d = SequentialDesign(model, StopRule(interval_deg=1.0, joint_space_error_mm=0.5), sigma_mm=1.0)
    assert set(d.gains(np.array([0, 1]))) == {"interval", "joint_space"}
    only = d.gains(np.array([0, 1]), criteria=["joint_space_error_mm"])
    assert set(only) == {"joint_space"} and only["joint_space"][0] > 0 and only["joint_space"][1] == 0
