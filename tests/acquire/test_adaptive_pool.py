"""An adaptive plan's generated candidate pool (``adaptive.candidates``, issue 27): validated with
file, line and field; every generated configuration inside the limits less the commander's margin
and aimed at the sensor from the region the plan declares; a run with a pool stops with its rule
met — judged against the plan's own full plan — and resumes without repeating a configuration.
Fast: synthetic sample records, no devices (as tests/acquire/test_adaptive_order.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from acquire.plan.schema import load_plan, resolve_candidate_pool, resolve_configurations
from acquire.run.adaptive import AdaptiveRun, fit_options
from calib.io.yamlfile import ConfigError
from calib.robot.kinematics import Chain
from drivers.protocols import JointLimits

from run_helpers import small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest
from test_adaptive_order import StandingRobot, record  # noqa: E402

# One xdist worker runs this file: its module fixture (a pooled design) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("acquire/test_adaptive_pool")

RULE = {"stop_when": {"held_out_within_pct": 10}, "min_configurations": 12}


@pytest.fixture(scope="module")
def pooled(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pool")
    lp = load_plan(small_plan(tmp, n=12, adaptive={**RULE, "candidates": {"extra_poses": 24, "seed": 5}}))
    return lp, resolve_configurations(lp), resolve_candidate_pool(lp)


# --- the plan's section ---------------------------------------------------------------------------
def test_a_plan_with_a_pool_validates_and_generates_other_configurations(pooled):
    lp, configs, pool = pooled
    assert lp.plan.adaptive.candidates.extra_poses == 24 and lp.plan.adaptive.candidates.seed == 5
    assert len(pool) >= 24 * lp.plan.poses.generated.min_solutions // 2  # most poses give ≥ 2 branches
    ids = [c.config_id for c in pool]
    assert len(set(ids)) == len(ids) and all(i.startswith("x") for i in ids)
    assert not set(ids) & {c.config_id for c in configs}
    assert [c.config_id for c in resolve_candidate_pool(lp)] == ids  # seeded: a resume finds the same ones


@pytest.mark.parametrize("candidates, field, allowed", [
    ({"extra_poses": 0}, "adaptive.candidates.extra_poses", "allowed [1, 2000]"),
    ({"extra_poses": 10, "seed": 1}, "adaptive.candidates.seed", "allowed: another seed"),
    ({"extra_posses": 10}, "adaptive.candidates", "extra_poses"),
    ({"seed": 3}, "adaptive.candidates.extra_poses", "Field required"),
])
def test_a_bad_pool_names_file_line_field_and_what_is_allowed(tmp_path, candidates, field, allowed):
    path = small_plan(tmp_path, n=4, adaptive={**RULE, "candidates": candidates})  # the plan's seed is 1
    with pytest.raises(ConfigError) as info:
        load_plan(path)
    text = str(info.value)
    line = [ln for ln in text.splitlines() if field in ln]
    assert line and f"{path}:" in line[0] and allowed in text, text
    assert int(line[0].split(":")[1]) > 1  # at the adaptive section's line, not the file's top


def test_a_pool_needs_the_region_of_generated_poses(tmp_path):
    from tests.acquire.test_plan import minimal, write

    path = write(tmp_path, minimal(adaptive={**RULE, "candidates": {"extra_poses": 10}}))  # explicit joints
    with pytest.raises(ConfigError, match=r"plan.yaml:\d+:\d+: adaptive.candidates: a candidate pool is generated "
                                          r"in the region poses.generated declares \(given poses.joints"):
        load_plan(path)


def test_every_generated_candidate_passes_the_plans_checks(pooled):
    # Checked here from the model, not from the generator's own bookkeeping: inside the joint limits
    # less the commander's margin; the flange's z-axis aimed at the plan's sensor origin; the flange in
    # the radius and height the plan declares.
    lp, _, pool = pooled
    g = lp.plan.poses.generated
    margin = lp.commander_margin_rad
    assert margin > 0  # fri keeps 0.5° clear
    q = np.stack([c.q_rad for c in pool])
    lo, hi = lp.model.lower_limits_rad + margin, lp.model.upper_limits_rad - margin
    assert np.all(q >= lo) and np.all(q <= hi)
    t = Chain(lp.model).fk(q)
    xyz, z = t[:, :3, 3], t[:, :3, 2]
    to_sensor = np.asarray(g.sensor_origin_mm) - xyz
    cos = np.sum(z * to_sensor, axis=1) / np.linalg.norm(to_sensor, axis=1)
    assert np.all(cos > 1 - 1e-9)
    radius = np.hypot(xyz[:, 0], xyz[:, 1])
    assert np.all((radius >= g.radius_mm[0] - 1e-6) & (radius <= g.radius_mm[1] + 1e-6))
    assert np.all((xyz[:, 2] >= g.height_mm[0] - 1e-6) & (xyz[:, 2] <= g.height_mm[1] + 1e-6))


def test_candidates_the_commander_would_refuse_are_not_chosen(pooled):
    # A commander reporting tighter limits than the model's: generated candidates outside them are
    # left out of the design (the plan's own were checked when it loaded).
    from acquire.run.adaptive import admissible_pool

    lp, _, pool = pooled
    lim = JointLimits.from_model(lp.model)
    q = np.stack([c.q_rad for c in pool])
    cut = float(np.median(q[:, 1]))
    tight = JointLimits(lim.lower_rad, np.where(np.arange(len(lim.upper_rad)) == 1, cut, lim.upper_rad),
                        lim.max_velocity_rad_s, lim.max_acceleration_rad_s2, lim.names)
    kept = admissible_pool(pool, tight, lp.commander_margin_rad)
    assert 0 < len(kept) < len(pool)
    assert all(c.q_rad[1] <= cut - lp.commander_margin_rad for c in kept)


# --- a run with a pool ----------------------------------------------------------------------------
def run_pooled(lp, configs, pool, k=None, resumed=None, robot=None):
    """The adaptive loop with synthetic records; returns (AdaptiveRun, records, chosen ids, choice events)."""
    chain, rng = Chain(lp.model), np.random.default_rng(3)
    robot = robot or StandingRobot(lp.model, None)
    ad = AdaptiveRun(lp, configs, robot, 0.5, 0.3, resumed, set(), np.zeros(lp.model.n_joints), pool)
    records, chosen, events = [], [], []
    for cfg in ad.choices(lambda kind, **f: events.append(f)):
        chosen.append(cfg.config_id)
        rec = record(lp, chain, cfg, rng)
        records.append(rec)
        robot.q = np.asarray(cfg.q_rad, dtype=float)
        ad.outcome(cfg, "measured", rec)
        if k is not None and len(chosen) == k:
            break
    return ad, records, chosen, events


def test_a_run_with_a_pool_stops_with_its_rule_met_against_the_plans_own_full_plan(pooled):
    from calib.fit.design import design_model
    from calib.plan.adaptive import SequentialDesign

    lp, configs, pool = pooled
    ad, _, chosen, events = run_pooled(lp, configs, pool)
    summ = ad.summary()
    assert summ["stopped"] and summ["reason"].startswith("stop rule met"), summ["reason"]
    generated = [e for e in events if e.get("generated")]
    assert generated, "the pool gave nothing the design wanted"
    assert all(e["config_id"].startswith("x") and len(e["q_deg"]) == lp.model.n_joints for e in generated)
    assert summ["generated_measured"] == len(generated) and summ["plan_configurations"] == len(configs)
    assert summ["candidates"] == len(configs) and summ["generated_candidates"] == len(pool)
    from acquire.commands.run_summary import adaptive_summary_lines

    text = "\n".join(adaptive_summary_lines(summ))
    assert f"stopped after {len(chosen)} of {len(configs)}" in text and f"{len(generated)} of them generated" in text
    # The rule, recomputed independently: the full plan is the plan's configurations only, and the
    # workspace its errors average over is theirs too.
    sensors = {s.name: list(s.markers) for s in lp.plan.sensors}
    plan_only = SequentialDesign(design_model(lp.model, np.stack([c.q_rad for c in configs]), sensors, fit_options(lp)),
                                 ad.order.design.rule, ad.order.design.sigma_mm)
    full_held = plan_only.held_out_mm(plan_only.full_workspace_mm())
    assert summ["full_held_out_mm"] == pytest.approx(full_held, rel=1e-3)
    assert summ["held_out_mm"] <= 1.10 * full_held + 1e-6
    # the full plan's time is the plan's configurations in the run's usual order, not the pool's
    from acquire.run.sequencer import move_times, order_configurations

    lim, start = JointLimits.from_model(lp.model), np.zeros(lp.model.n_joints)
    tour = order_configurations(configs, start, lim, 0.5)
    assert summ["full_plan_seconds"] == pytest.approx(move_times(tour, start, lim, 0.5).sum() + 0.3 * len(configs),
                                                      abs=0.06)


def test_a_resumed_run_with_a_pool_continues_its_choices_and_repeats_none(pooled):
    lp, configs, pool = pooled
    _, _, straight, _ = run_pooled(lp, configs, pool, k=9)
    _, records, first, _ = run_pooled(lp, configs, pool, k=5)
    assert first == straight[:5]
    everything = {c.config_id: c for c in configs + pool}
    robot = StandingRobot(lp.model, everything[first[-1]].q_rad)
    ad2, _, then, _ = run_pooled(lp, configs, pool, k=4, resumed=SimpleNamespace(samples=records), robot=robot)
    assert ad2.resumed_n == 5 and not set(then) & set(first)
    assert then == straight[5:9]
    assert any(i.startswith("x") for i in straight[:9])  # generated ones among them, resumed by id


@pytest.mark.slow  # ~30 s: two runs of the simulated cell; the logic is tested above without a cell
@pytest.mark.timeout(300)
def test_a_pooled_run_on_the_simulated_cell_logs_its_generated_choices_and_resumes(tmp_path):
    from collections import Counter

    from acquire.record.recorder import read_run
    from run_helpers import aborted_run, resumed_run

    lp = load_plan(small_plan(tmp_path, n=10, sequencing={"samples": 5, "settle_window_s": 0.2},
                              fake={"time_scale": 6.0},
                              adaptive={**RULE, "candidates": {"extra_poses": 16}}))

    first = aborted_run(lp, 4)
    assert first.state == "aborted", first.reason
    before = [s["config_id"] for s in read_run(first.log_path).samples]
    second = resumed_run(lp, first.log_path)
    assert second.state == "finished", second.reason
    run = read_run(first.log_path)
    counts = Counter(s["config_id"] for s in run.samples)
    assert max(counts.values()) == 1 and set(before) <= set(counts)
    pool = {c.config_id: c for c in resolve_candidate_pool(lp)}
    choices = [e for e in run.events if e["kind"] == "adaptive_choice"]
    generated = [e for e in choices if e.get("generated")]
    assert generated and all(e["config_id"] in pool for e in generated)
    for e in generated:  # the log says where a configuration the plan file does not list was
        assert np.allclose(e["q_deg"], np.degrees(pool[e["config_id"]].q_rad), atol=1e-5)
    stop = [e for e in run.events if e["kind"] == "adaptive_stop"][-1]
    assert stop["stopped"] and stop["measured"] == len(counts)
    assert stop["generated_measured"] == sum(1 for c in counts if c in pool)
