"""The next adaptive choice computed while the robot moves (acquire.run.lookahead, issue 27): it
is the choice the run would compute after the measurement, it is thrown away when the state it
assumed did not come true (a failed configuration), and the worker process gives the same
choices as the run computing them itself. Fast: synthetic sample records, no devices."""

from __future__ import annotations

import numpy as np
import pytest

from acquire.plan.schema import load_plan, resolve_configurations
from acquire.run.adaptive import AdaptiveRun, refit_counts
from calib.robot.kinematics import Chain

from run_helpers import small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest
from test_adaptive_order import StandingRobot, record  # noqa: E402

# One xdist worker runs this file: its module fixture (a designed plan) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("acquire/test_adaptive_lookahead")


@pytest.fixture(scope="module")
def plan(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lookahead")
    lp = load_plan(small_plan(tmp, n=12, adaptive={"stop_when": {"held_out_within_pct": 30}, "min_configurations": 10}))
    return lp, resolve_configurations(lp)


def drive(lp, configs, lookahead, k, fail=(), check=None):
    """Run the adaptive loop for k choices; configurations whose position is in ``fail`` fail, the
    rest are 'measured' (same noise draws whatever the look-ahead). ``check(ad, cfg)`` is called
    before each choice is handed on. Returns (AdaptiveRun, chosen ids, choice events)."""
    chain, rng = Chain(lp.model), np.random.default_rng(7)
    robot = StandingRobot(lp.model, None)
    ad = AdaptiveRun(lp, configs, robot, 0.5, 0.3, None, set(), np.zeros(lp.model.n_joints), lookahead=lookahead)
    chosen, events = [], []
    for cfg in ad.choices(lambda kind, **f: events.append(f) if kind == "adaptive_choice" else None):
        chosen.append(cfg.config_id)
        robot.q = np.asarray(cfg.q_rad, dtype=float)
        if len(chosen) - 1 in fail:
            ad.outcome(cfg, "failed", None)
        else:
            ad.outcome(cfg, "measured", record(lp, chain, cfg, rng))
        if check is not None:
            check(ad, cfg)
        if len(chosen) == k:
            break
    return ad, chosen, events


def test_the_choice_computed_ahead_is_the_one_computed_after_the_measurement(plan):
    lp, configs = plan
    seen = []

    def fresh_choice(ad, cfg):
        # after the outcome, before the run takes the choice computed ahead: compute it afresh
        o = ad.order
        o.use_sigma(o.sigma_count())
        if not o.status().stop:
            seen.append(o.choose(np.asarray(cfg.q_rad, dtype=float))[0].config_id)

    ad, ahead, events = drive(lp, configs, "inline", len(configs), check=fresh_choice)
    _, after, _ = drive(lp, configs, None, len(configs))
    assert ad.final is not None and ad.final.reason.startswith("stop rule met")  # to the stop
    assert ahead == after  # the same run, choice for choice
    assert ahead[1:] == seen  # each handed-out choice is the one computed after its predecessor
    assert [e["precomputed"] for e in events] == [False] + [True] * (len(events) - 1)
    # σ was fitted on the schedule along the way (in the look-ahead's jobs; the run has their fits)
    assert set(ad.order._fits) >= {c for c in range(1, len(ahead) - 1) if c in refit_counts(len(ahead))}
    assert ad.summary()["lookahead"] == {**ad.summary()["lookahead"], "used": len(events) - 1, "discarded": 0,
                                         "failed": 0}


def test_a_failed_configuration_discards_the_choice_computed_ahead(plan):
    lp, configs = plan
    ad, chosen, events = drive(lp, configs, "inline", 8, fail=(3,))
    assert [e["precomputed"] for e in events] == [False, True, True, True, False, True, True, True]
    assert ad.lookahead.discarded == 1 and ad.lookahead.used == 6
    assert chosen[3] not in chosen[4:]  # not chosen again
    # the choice after the failure is the one the run computes without a look-ahead
    _, plain, _ = drive(lp, configs, None, 8, fail=(3,))
    assert plain == chosen


def test_the_worker_process_gives_the_choices_the_run_computes_itself(plan, monkeypatch):
    lp, configs = plan
    # What is judged is the worker's answers, not this host's speed: under the full suite a job
    # (the first one starts the process) can take longer than the run's 2 s wait, and a late
    # answer is rightly not used (the ./test run saw 3 used of 4).
    monkeypatch.setattr("acquire.run.lookahead.WAIT_S", 120.0)
    procs = []
    ad, chosen, events = drive(lp, configs, "process", 5, check=lambda ad, cfg: procs.append(ad.lookahead.worker._proc))
    _, plain, _ = drive(lp, configs, None, 5)
    assert chosen == plain
    stats = ad.summary()["lookahead"]
    assert stats["used"] == 4 and stats["discarded"] == 0 and stats["failed"] == 0 and stats["ahead_seconds"] > 0
    # the worker ended when the loop let go of the choices (RunController also closes it): on its
    # own, or ended by the run when still busy with the job it no longer needs
    assert not procs[0].is_alive() and ad.lookahead.worker is None


def test_a_stop_the_records_do_not_confirm_goes_on_choosing_with_their_sigma(plan, monkeypatch):
    # The schedule's σ (one record behind) says stop; σ of every record is larger (here: made so,
    # off the schedule's counts) and the offsets' intervals with it too wide — go on:
    # the next choice is made with that σ (the schedule's would plan nothing), not the one computed ahead.
    from acquire.run.adaptive import AdaptiveOrder

    schedule = refit_counts(100)
    monkeypatch.setattr(AdaptiveOrder, "fast_fit_sigma",
                        lambda self, upto=None: 0.01 if (upto or len(self.records)) in schedule else 0.5)
    lp0, configs = plan
    from dataclasses import replace

    lp = replace(lp0, plan=lp0.plan.model_copy(update={"adaptive": lp0.plan.adaptive.model_copy(
        update={"stop_when": lp0.plan.adaptive.stop_when.model_copy(update={"interval_deg": 0.1, "held_out_within_pct": None})})}))
    ad, chosen, events = drive(lp, configs, "inline", len(configs))
    st = ad.final
    assert st is not None and st.reason.startswith("stop rule met") and len(chosen) in schedule
    held_on = [e for e in events if e["sigma_mm"] == 0.5]
    assert held_on and not any(e["precomputed"] for e in held_on)  # chosen afresh, with every record's σ
    assert len(set(chosen)) == len(chosen)


def test_a_worker_that_cannot_start_leaves_the_run_choosing_itself(plan, monkeypatch):
    import acquire.run.lookahead as la

    def refuse(order):
        raise TypeError("cannot pickle this order")

    monkeypatch.setattr(la, "InlineWorker", refuse)
    lp, configs = plan
    ad, chosen, events = drive(lp, configs, "inline", 4)
    _, plain, _ = drive(lp, configs, None, 4)
    assert chosen == plain and not any(e["precomputed"] for e in events)
    assert ad.summary()["lookahead"]["failed"] == 1


def test_a_worker_that_does_not_answer_in_time_is_waited_for_briefly_then_given_up(plan, monkeypatch):
    import acquire.run.lookahead as la

    class Silent(la.InlineWorker):
        def receive(self, timeout_s):
            return None  # as a starved worker: nothing within the wait

    monkeypatch.setattr(la, "InlineWorker", Silent)
    monkeypatch.setattr(la, "WAIT_S", 0.01)
    lp, configs = plan
    ad, chosen, events = drive(lp, configs, "inline", 6)
    _, plain, _ = drive(lp, configs, None, 6)
    assert chosen == plain and not any(e["precomputed"] for e in events)
    stats = ad.summary()["lookahead"]
    assert stats["late"] == la.MAX_LATE and stats["used"] == 0 and ad.lookahead.worker is None
