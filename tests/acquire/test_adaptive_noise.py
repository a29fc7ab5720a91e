"""An adaptive run sees the instrument the cell has (issue 35): σ of a configuration as measured
(the spread of its averaged readings over √count, then the fit's σ), the misfit the model leaves
(the fit's σ beyond the spread), choices and stops that follow them, a stop rule in the operator's
terms predicted by ``--dry-run``, and the stop decision reported with what backs it. Fast:
synthetic sample records from the nominal arm, no devices."""

from __future__ import annotations

import math

import numpy as np
import pytest

from acquire.plan.schema import load_plan, resolve_configurations
from acquire.run.adaptive import PLAN_SIGMA_DOF, AdaptiveOrder, AdaptiveRun, found_after_the_fact
from calib.robot.kinematics import Chain
from drivers.protocols import JointLimits

from run_helpers import small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest
from test_adaptive_order import StandingRobot  # noqa: E402

# One xdist worker runs this file: its module fixture (a designed plan and its cells) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("acquire/test_adaptive_noise")

RULE = {"interval_deg": 0.015, "region_error_mm": 0.05}


@pytest.fixture(scope="module")
def plan(tmp_path_factory):
    """The packaged example plan's region, fewer poses (12: 24 configurations; 5 readings of 0.03 mm)."""
    tmp = tmp_path_factory.mktemp("noise")
    lp = load_plan(small_plan(tmp, n=12, adaptive={"stop_when": RULE, "min_configurations": 12}))
    return lp, resolve_configurations(lp)


class Readings:
    """A cell that reads the nominal marker ``count`` times with ``per_reading_mm`` noise, plus an
    error per configuration the model cannot explain (``misfit_mm`` per axis, fixed per configuration)."""

    def __init__(self, lp, per_reading_mm: float, misfit_mm: float = 0.0, seed: int = 0, count: int = 5):
        self.chain, self.rng = Chain(lp.model), np.random.default_rng(seed)
        self.m = self.chain.marker_names.index("sir")
        self.noise, self.misfit, self.count = per_reading_mm, misfit_mm, count

    def record(self, cfg) -> dict:
        true = self.chain.marker_positions(np.asarray(cfg.q_rad)[None, :])[0, self.m]
        true = true + self.rng.normal(0, self.misfit, 3)
        reads = true + self.rng.normal(0, self.noise, (self.count, 3))
        return {"config_id": cfg.config_id, "q_measured_deg": np.degrees(cfg.q_rad).tolist(),
                "markers": [{"sensor": "mocap", "marker": "sir", "mean_mm": reads.mean(axis=0).tolist(),
                             "std_mm": reads.std(axis=0, ddof=1).tolist(), "count": self.count}]}


def run_cell(lp, configs, cell: Readings):
    """The run's adaptive loop to its stop: (AdaptiveRun, chosen ids)."""
    robot = StandingRobot(lp.model, None)
    ad = AdaptiveRun(lp, configs, robot, 0.5, 0.3, None, set(), np.zeros(lp.model.n_joints))
    chosen = []
    for cfg in ad.choices(lambda kind, **f: None):
        chosen.append(cfg.config_id)
        robot.q = np.asarray(cfg.q_rad, dtype=float)
        ad.outcome(cfg, "measured", cell.record(cfg))
    return ad, chosen


@pytest.fixture(scope="module")
def cells(plan):
    """Two cells: a quiet one (0.02 mm per reading) and one with more noise (0.035 mm) and an error
    per configuration its model cannot explain (0.015 mm per axis)."""
    lp, configs = plan
    return {"quiet": run_cell(lp, configs, Readings(lp, 0.02, seed=0)),
            "troubled": run_cell(lp, configs, Readings(lp, 0.035, 0.015, seed=1))}


def test_sigma_of_a_configuration_is_its_readings_spread_over_root_count_then_the_fits(plan):
    lp, configs = plan
    order = AdaptiveOrder(lp, configs, JointLimits.from_model(lp.model), 0.5, 0.3)
    assert order.design.sigma_mm == pytest.approx(0.03 / math.sqrt(5))  # the plan's, per configuration
    cell = Readings(lp, 0.05)
    for cfg in configs[:3]:
        order.mark(cfg.config_id, cell.record(cfg))
    order.update_sigma()
    # pooled by degrees of freedom with the plan's σ: independently, from the records
    s2 = [np.square(m["std_mm"]) / m["count"] for r in order.records for m in r["markers"]]
    want = math.sqrt((PLAN_SIGMA_DOF * 0.03**2 / 5 + 4 * np.sum(s2)) / (PLAN_SIGMA_DOF + 4 * 3 * len(s2)))
    assert order.fitted_sigma_mm is None and order.design.sigma_mm == pytest.approx(want)
    assert order.design.sigma_mm > 0.03 / math.sqrt(5) and order.design.misfit_mm == 0
    for cfg in configs[3:]:
        order.mark(cfg.config_id, cell.record(cfg))
    order.update_sigma()
    fitted = order.fitted_sigma_mm
    # the fit's σ once it is determined, never below the readings' own spread
    assert fitted is not None and order.design.sigma_mm == max(fitted, order.spread_sigma_mm)
    assert 0.5 < fitted / (0.05 / math.sqrt(5)) < 1.5
    assert order.design.misfit_mm == pytest.approx(math.sqrt(max(0.0, fitted**2 - order.spread_sigma_mm**2)))


def test_a_cell_with_more_noise_and_misfit_chooses_differently_and_measures_more(cells):
    (quiet, q_ids), (troubled, t_ids) = cells["quiet"], cells["troubled"]
    for ad in (quiet, troubled):
        assert ad.final is not None and ad.final.reason.startswith("stop rule met"), ad.final
    assert t_ids[: len(q_ids)] != q_ids  # the choices follow the data…
    assert len(t_ids) > len(q_ids)  # …and the cell with more unexplained error measures more
    q, t = quiet.order.design, troubled.order.design
    assert t.misfit_mm > q.misfit_mm and t.misfit_mm > 0.005
    # σ is each cell's own (the fit's, misfit included), not the plan's 0.03 / √5
    assert q.sigma_mm == pytest.approx(0.02 / math.sqrt(5), rel=0.35)
    assert t.sigma_mm == pytest.approx(math.sqrt(0.035**2 / 5 + 0.015**2), rel=0.35)


def test_the_dry_run_predicts_the_stop_with_the_plans_noise_per_configuration(plan):
    from acquire.commands.run import adaptive_dry_run_lines

    lp, configs = plan
    text = "\n".join(adaptive_dry_run_lines(lp, configs, JointLimits.from_model(lp.model), 0.5, 0.3,
                                            np.zeros(lp.model.n_joints)))
    assert "σ 0.0134 mm per configuration" in text
    stops = int(text.split("stops after ")[1].split(" ")[0])
    assert 12 <= stops < len(configs)  # the interval and region rule stops early
    assert "predicted at that stop: largest half-width" in text and "(working joint space)" in text


def test_the_stop_decision_is_reported_with_what_backs_it_predicted_and_found(cells):
    from acquire.commands.run_summary import adaptive_summary_lines
    from calib.report.report_adaptive import adaptive_section

    ad, chosen = cells["quiet"]
    summ = ad.summary()
    dec = summ["decision"]
    assert [c["criterion"] for c in dec["checks"]] == list(RULE) and all(c["met"] for c in dec["checks"])
    assert dec["checks"][0]["predicted"] == pytest.approx(ad.final.max_half_width_deg, abs=1e-6)
    n = dec["noise"]
    assert n["fitted_mm"] is not None and n["used_mm"] == max(n["fitted_mm"], n["spread_mm"])
    p = dec["predicted"]
    assert p["max_half_width_deg"] <= 0.015 and p["full_max_half_width_deg"] < p["max_half_width_deg"]
    assert p["full_joint_space_mm"] < p["joint_space_mm"]
    # found after the fact, from a fit's result document
    fit = {"joint_offsets": [{"joint": f"A{i}", "ci95_deg": [-0.004 * i, 0.004 * i]} for i in range(1, 8)],
           "sigma_mm": {"mocap": {"value": 0.011, "std": 0.001}}}
    summ["found"] = found = found_after_the_fact(summ, fit)
    assert found["max_half_width_deg"] == pytest.approx(0.024) and found["determined"] == 5  # A2…A6
    assert found["misfit_mm"] == pytest.approx(math.sqrt(max(0.0, 0.011**2 - dec["noise"]["spread_mm"] ** 2)), abs=1e-6)
    text = "\n".join(adaptive_summary_lines(summ))
    assert "the stop decision: interval_deg ≤ 0.015°" in text and "region_error_mm ≤ 0.05 mm" in text
    assert "found by the fit: largest half-width 0.0240°" in text and "misfit" in text
    html = "\n".join(adaptive_section(summ))
    assert "The stop decision" in html and "found by the fit" in html and "0.0240" in html
