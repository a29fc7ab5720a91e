"""Cross-validation folds in worker processes (``calib.fit.parallel``) give the serial fit's numbers
exactly, and the controller's offsets (``calib.fit.entered``) reuse what the model choice fitted:
its folds' offsets+tool fits and its fit of all the data as the start — the same answers.

Simulated tracker cells (``tests.calib.test_model_choice.cell``: a Stäubli TX60 with a three-nest
plate, offsets of N(0, 0.1°), a tool 2 mm off its drawing, 0.02 mm noise).
"""

from __future__ import annotations

import operator
import os

import numpy as np
import pytest

from calib.fit.entered import entered_options, fit_entered, heldout_by_folds
from calib.fit.model_choice import ENTERED, Candidate, choose_model, cross_validate
from calib.fit.offsets import FitOptions, fit_mode
from calib.fit.parallel import JOBS_ENV, fit_jobs, map_in_order
from tests.calib.test_model_choice import cell

QUICK = FitOptions(method="laplace", n_draws=250)


def test_the_processes_follow_the_environment_the_cores_and_the_blas_threads():
    assert fit_jobs(5, {JOBS_ENV: "1"}) == fit_jobs(5, {JOBS_ENV: "serial"}) == 1
    assert fit_jobs(5, {JOBS_ENV: "3"}) == 3 and fit_jobs(2, {JOBS_ENV: "3"}) == 2  # never more than the pieces
    assert fit_jobs(5, {}, cpus=4, load=0.5) == 4 and fit_jobs(5, {JOBS_ENV: "auto"}, cpus=8, load=0.0) == 5
    assert fit_jobs(5, {"OPENBLAS_NUM_THREADS": "2"}, cpus=4, load=0.0) == 2  # processes × BLAS threads ≤ cores
    assert fit_jobs(5, {"OMP_NUM_THREADS": "8"}, cpus=4, load=0.0) == 1
    assert fit_jobs(5, {}, cpus=4, load=2.2) == 2 and fit_jobs(5, {}, cpus=2, load=7.0) == 1  # the busy cores left out
    assert fit_jobs(5, {JOBS_ENV: "2"}, cpus=2, load=7.0) == 2  # (a number is the user's: taken as said)
    assert fit_jobs(5, {}) <= len(os.sched_getaffinity(0))
    with pytest.raises(ValueError, match=f"{JOBS_ENV}='two'.*'auto'.*'serial'"):
        fit_jobs(5, {JOBS_ENV: "two"})
    with pytest.raises(ValueError, match=JOBS_ENV):
        fit_jobs(5, {JOBS_ENV: "0"})


def _square_or_die(parent: int, x: int) -> int:
    if os.getpid() != parent:  # in a worker: a crash (the pool breaks)
        os._exit(3)
    return x * x


def _square(offset: int, x: int) -> int:
    return x * x + offset


def test_pieces_come_back_in_order_and_a_broken_pool_runs_them_here():
    seen = []
    assert map_in_order(_square, 1, [3, 1, 2], 2, done=lambda t, r: seen.append((t, r))) == [10, 2, 5]
    assert sorted(seen) == [(1, 2), (2, 5), (3, 10)]
    assert map_in_order(_square_or_die, os.getpid(), [1, 2, 3], 2) == [1, 4, 9]


def test_beside_another_thread_the_workers_come_from_a_fork_server():
    """A process with another Python thread (the run's end-of-run fit, the daemon) does not fork it."""
    import threading

    from calib.fit import parallel

    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    other.start()
    try:
        assert parallel._start_method() in ("forkserver", "spawn")
        assert map_in_order(operator.mul, 3, [4, 5], 2) == [12, 15]  # (a function whose module is light to import)
    finally:
        stop.set()
        other.join()


def test_parallel_folds_give_the_serial_scores_exactly():
    model, _, cal = cell(5, tool_shift_mm=(0.0, 0.0, 2.0), k=24)
    cands = [Candidate("offsets"), ENTERED]
    out = {}
    for jobs in (1, 2):
        kept: dict = {}
        scores, nominal, n_folds, _ = cross_validate(model, cal, cands, QUICK, None, k=5, entered_folds=kept, jobs=jobs)
        out[jobs] = (scores, nominal, kept)
    (s1, n1, e1), (s2, n2, e2) = out[1], out[2]
    assert np.array_equal(n1.errors_mm, n2.errors_mm)
    for a, b in zip(s1, s2):
        assert not a.failed and np.array_equal(a.errors_mm, b.errors_mm) and np.array_equal(a.configs, b.configs)
        assert a.chi2 == b.chi2 and a.n_chi2 == b.n_chi2 and a.n_params == b.n_params
    assert sorted(e1) == sorted(e2) == list(range(5))
    for f in e1:
        assert np.array_equal(e1[f][0], e2[f][0]) and np.array_equal(e1[f][1], e2[f][1])


def test_the_controller_stage_reuses_the_model_choice_and_scores_alike():
    """The held-out scores from the model choice's fold fits and from fold fits of their own agree to
    the solver's tolerance; the controller's offsets started from the model choice's fit of all the
    data are those of a cold start (the same mode; the same importance draws)."""
    model, _, cal = cell(6, tool_shift_mm=(0.0, 0.0, 2.0), k=24)
    choice = choose_model(model, cal, QUICK, force=ENTERED.name, jobs=1)
    assert sorted(choice.entered_folds) == list(range(choice.folds))
    start = choice.starts[ENTERED.name]
    cold = fit_entered(model, cal, QUICK)
    warm = fit_entered(model, cal, QUICK, start=start)
    assert cold.joints == warm.joints and cold.joints
    for c, w in zip(cold.offsets, warm.offsets):
        assert c["significant"] == w["significant"]
        if c["value_deg"] is not None:
            assert abs(c["value_deg"] - w["value_deg"]) < 1e-3 * c["std_deg"]
            assert abs(c["std_deg"] - w["std_deg"]) < 1e-2 * c["std_deg"]
    options = entered_options(QUICK)
    fitted = np.isin(np.arange(1, model.n_joints + 1), warm.joints)
    reuse_any = any(np.array_equal(m, fitted) for _, m in choice.entered_folds.values())
    own = heldout_by_folds(model, cal, options, warm.joints)
    reused = heldout_by_folds(model, cal, options, warm.joints, start=start, fold_offsets=choice.entered_folds)
    assert np.array_equal(own.configs, reused.configs)
    for name in ("as_found", "entered"):
        assert np.allclose(own.errors[name], reused.errors[name], atol=1e-5, rtol=0)
    assert reuse_any or np.array_equal(own.errors["entered"], reused.errors["entered"])


def test_a_fold_whose_axes_differ_is_fitted_again_not_reused():
    """Offsets of a fold that fitted other axes than those entered are not taken: that fold is fitted."""
    model, _, cal = cell(6, tool_shift_mm=(0.0, 0.0, 2.0), k=24)
    joints = (2, 3, 5)
    bogus = {f: (np.full(model.n_joints, 0.5), np.ones(model.n_joints, bool)) for f in range(5)}  # all axes, 29°
    mf = fit_mode(model, cal, entered_options(QUICK), tol=1e-8)
    held = heldout_by_folds(model, cal, entered_options(QUICK), joints, start=mf, fold_offsets=bogus)
    fresh = heldout_by_folds(model, cal, entered_options(QUICK), joints)
    assert np.allclose(held.errors["entered"], fresh.errors["entered"], atol=1e-5, rtol=0)
    assert held.errors["entered"].mean() < 1.0  # not the bogus 29° offsets
