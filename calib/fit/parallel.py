"""Independent pieces of a fit (the cross-validation folds of ``calib.fit.model_choice``) in
parallel processes, where the machine has cores for them.

How many: ``fit_jobs``. ``REMASTER_FIT_JOBS`` decides — ``1`` (or ``serial``) keeps every fit in
its own process, a number caps the processes, unset or ``auto`` takes the CPUs this process may
run on (``os.sched_getaffinity``, so a ``taskset`` or a container's CPU set is respected) divided
by the BLAS threads each process runs (``OPENBLAS_NUM_THREADS`` / ``OMP_NUM_THREADS`` /
``MKL_NUM_THREADS``, 1 unless the user says otherwise: ``calib/__init__.py``), so that processes ×
threads never exceed the cores, and no more than the cores the load average leaves free. Never
more processes than pieces.

How: ``map_in_order`` runs ``fn(context, task)`` for every task and returns the results in the
tasks' order, whatever order they finish in, so a parallel fit gives the serial fit's numbers
exactly (each piece is deterministic and computed alike either way; ``tests/calib/test_parallel_folds.py``).
Workers are forked from this process where it runs no other Python thread (no copy of the data,
no imports), else started from a fork server (fork beside running threads can copy a lock that
another thread holds). A pool that breaks (a worker killed) is not fatal: the pieces run here.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterable, Mapping, TypeVar

log = logging.getLogger(__name__)

#: The environment variable that sets the processes (``fit_jobs``).
JOBS_ENV = "REMASTER_FIT_JOBS"
#: At most this many processes however many cores: the folds are five by default.
MAX_JOBS = 16
_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

C = TypeVar("C")
T = TypeVar("T")
R = TypeVar("R")


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (not on Linux)
        return os.cpu_count() or 1


def blas_threads(env: Mapping[str, str] = os.environ) -> int:
    """The BLAS threads one process runs, by the variables that set them (the largest; 1 unset)."""
    out = 1
    for var in _BLAS_ENV:
        try:
            out = max(out, int(env.get(var, "1")))
        except ValueError:
            continue
    return out


def fit_jobs(n_tasks: int, env: Mapping[str, str] = os.environ, cpus: int | None = None,
             load: float | None = None) -> int:
    """Processes for ``n_tasks`` independent pieces (see the module's text); ValueError for a
    ``REMASTER_FIT_JOBS`` that is not ``auto``, ``serial`` or a positive whole number. ``auto`` also
    leaves out the cores the machine is already busy with: at most ``cpus − load + 1`` processes
    (``load``: the 1-minute load average, ``os.getloadavg``; the +1 is this process) — on a busy
    machine workers gain no wall time and cost their start (UR10 series D at load 7 on 2 cores:
    17.6 s wall with two workers, 11.3 s serial)."""
    raw = env.get(JOBS_ENV, "auto").strip().lower() or "auto"
    if raw == "serial":
        return 1
    if raw == "auto":
        cpus = available_cpus() if cpus is None else cpus
        if load is None:
            try:
                load = os.getloadavg()[0]
            except OSError:  # (not available)
                load = 0.0
        cap = max(1, min(cpus // blas_threads(env), int(cpus - load + 1.0)))
    else:
        try:
            cap = int(raw)
        except ValueError:
            cap = 0
        if cap < 1:
            raise ValueError(f"{JOBS_ENV}={env.get(JOBS_ENV)!r}: use 'auto' (the cores this process may run on), "
                             "'serial' or 1 (no worker processes), or a positive number of processes")
    return max(1, min(cap, MAX_JOBS, n_tasks))


_CONTEXT: object = None


def _set_context(context) -> None:
    global _CONTEXT
    _CONTEXT = context


def _call(fn: Callable, task):
    return fn(_CONTEXT, task)


def _start_method() -> str:
    methods = multiprocessing.get_all_start_methods()
    if "fork" in methods and threading.active_count() == 1:
        return "fork"
    return "forkserver" if "forkserver" in methods else "spawn"


def map_in_order(fn: Callable[[C, T], R], context: C, tasks: Iterable[T], jobs: int, *,
                 done: Callable[[T, R], None] | None = None) -> list[R]:
    """``[fn(context, t) for t in tasks]``, in ``jobs`` processes where ``jobs`` > 1. ``fn``: a
    module-level function (workers import it by name); ``context``: what every piece shares, given
    to each worker once; ``done(task, result)``: called here as each piece finishes (progress)."""
    tasks = list(tasks)
    if jobs > 1 and len(tasks) > 1:
        try:
            return _in_pool(fn, context, tasks, jobs, done)
        except BrokenProcessPool as exc:
            log.warning("the fit's worker processes stopped (%s): the remaining pieces run in this process", exc)
    out = []
    for t in tasks:
        out.append(fn(context, t))
        if done is not None:
            done(t, out[-1])
    return out


def _in_pool(fn, context, tasks, jobs, done):
    method = _start_method()
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":  # the server imports fn's module once; each worker forks from it
        ctx.set_forkserver_preload([fn.__module__])
    results: dict[int, object] = {}
    with ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=ctx, initializer=_set_context,
                             initargs=(context,)) as pool:
        futures = {pool.submit(_call, fn, t): i for i, t in enumerate(tasks)}
        for fut in as_completed(futures):
            i = futures[fut]
            results[i] = fut.result()
            if done is not None:
                done(tasks[i], results[i])
    return [results[i] for i in range(len(tasks))]
