"""An adaptive run's next choice, computed while the robot moves (issue 27).

The design's covariance depends on where the robot was and on σ, not on the measured values
(``calib.plan.adaptive``), and the σ a choice uses is fitted one record behind
(``AdaptiveOrder.sigma_count``). So the choice after configuration k can be computed while k is
moved to, settled and measured, assuming it will be measured: ``Lookahead`` keeps one such job
ahead of the run.

- ``submit(order, cfg)`` as the run sets off for ``cfg``: a job with the state the design will
  have once ``cfg`` is measured — measured + cfg, the dropped candidates, σ of the schedule's
  count for that many records (fitted in the job when not yet), the robot standing at ``cfg``;
- ``result(order)`` after the outcome: waits for the job (up to ``WAIT_S``; ``MAX_LATE`` late
  in a row end the look-ahead), hands the σ fits it
  made to ``order``; ``Ahead.choice(order, here)`` is the job's choice when the job's key
  (``AdaptiveOrder.choice_key``: measured, dropped, σ, where the robot stands) is the state's,
  else None: discarded — ``cfg`` failed or was skipped, its record is missing, the robot is
  elsewhere — and the run computes the choice itself. The stop decision is always the run's,
  with the new record.

Where a job runs (``Lookahead.start``): "process" — ``ChoiceWorker``, one process per run,
spawned at the first ``submit`` (while the robot makes its first move), at a lower priority
(``WORKER_NICE``), so that the computation neither holds the run's interpreter lock (sensor
readers, the joint-state tap, the log writer) nor takes a core from the commander's cyclic
exchange, which has its own process (``drivers.exchange``, SCHED_FIFO where permitted);
"inline" — ``InlineWorker``, computed in the caller at ``submit`` (tests, studies: the same
choices without a process). Nothing here moves the robot: every move is the run's
``ConfigurationRunner``'s, with its checks.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import time
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

#: Niceness of the worker process (lower priority than the run, the readers and the exchange).
WORKER_NICE = 10
#: Wall seconds the run waits for a job before it computes the choice itself (a choice takes
#: 0.05–0.8 s: a job not done after the whole move, settle and measure is starved).
WAIT_S = 2.0
#: Jobs late in a row after which the look-ahead stops (the worker cannot keep up on this host).
MAX_LATE = 3


def run_job(order, job: dict) -> dict:
    """Compute ``job``'s choice on ``order`` (the worker's own copy of the run's ``AdaptiveOrder``):
    its records extended by the job's new ones, the job's measured and dropped candidates, σ of
    the job's record count. Returns the job id, the key, the chosen index (None when the stop
    rule holds at that state) and why, the σ fits made, and the seconds it took."""
    t0 = time.perf_counter()
    order.records.extend(job["records"])
    order._fits.update({int(c): v for c, v in job["fits"].items()})  # the run's fits win: one σ per count
    order.design.measured = [int(i) for i in job["measured"]]
    order.dropped = {int(i) for i in job["dropped"]}
    before = set(order._fits)
    order.use_sigma(int(job["sigma_count"]))
    here = np.asarray(job["here"], dtype=float)
    if order.status().stop:  # the rule holds with this σ: no next choice (the run judges the stop)
        return {"id": job["id"], "key": order.choice_key(here), "index": None, "why": {},
                "fits": {c: v for c, v in order._fits.items() if c not in before},
                "seconds": time.perf_counter() - t0}
    cfg, why = order.choose(here)
    return {"id": job["id"], "key": order.choice_key(here), "index": order.index[cfg.config_id], "why": why,
            "fits": {c: v for c, v in order._fits.items() if c not in before},  # made here
            "seconds": time.perf_counter() - t0}


def answer(order, job: dict) -> dict:
    """``run_job``, or the job id and the error (the run then computes the choice itself)."""
    try:
        return run_job(order, job)
    except Exception as exc:  # noqa: BLE001 - a look-ahead must never end the run
        return {"id": job.get("id"), "error": f"{type(exc).__name__}: {exc}"}


def serve(conn, snapshot: bytes) -> None:
    """The worker process: jobs from ``conn`` until None or the run's end of the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the process group; the run decides
    try:
        os.nice(WORKER_NICE)
    except OSError:
        pass
    order = pickle.loads(snapshot)
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            conn.send(answer(order, job))
        except (BrokenPipeError, OSError):
            return


class ChoiceWorker:
    """A worker process holding a copy of the run's ``AdaptiveOrder`` (spawned: the run may be a
    thread of the daemon)."""

    def __init__(self, order) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=serve, args=(child, pickle.dumps(order)), name="adaptive-lookahead",
                                 daemon=True)
        self._proc.start()
        child.close()

    def send(self, job: dict) -> bool:
        try:
            self._conn.send(job)
            return True
        except (BrokenPipeError, OSError):
            return False

    def receive(self, timeout_s: float) -> dict | None:
        """The next answer, or None after ``timeout_s`` or when the worker is gone."""
        try:
            if self._conn.poll(timeout_s):
                return self._conn.recv()
        except (EOFError, OSError):
            pass
        return None

    def close(self) -> None:
        self.send(None)
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        self._conn.close()


class InlineWorker:
    """The same jobs, computed in the caller at ``send`` (on its own copy of the order)."""

    def __init__(self, order) -> None:
        self._order = order.copy()
        self._out: list[dict] = []

    def send(self, job: dict) -> bool:
        self._out.append(answer(self._order, job))
        return True

    def receive(self, timeout_s: float) -> dict | None:
        return self._out.pop(0) if self._out else None

    def close(self) -> None:
        self._out.clear()


@dataclass(frozen=True)
class Ahead:
    """A job's answer: its key (the state it assumed), the chosen candidate and why."""

    key: tuple
    index: int
    why: dict

    def choice(self, order, here_q_rad):
        """(PlannedConfig, event fields) when the state is the one the job assumed, else None."""
        if order.choice_key(here_q_rad) != self.key:
            return None
        return order.configs[self.index], dict(self.why)


class Lookahead:
    """One choice computed ahead of the run (see the module docstring). Counts what was used,
    discarded, and the seconds computed while the robot moved (``stats``)."""

    def __init__(self, make_worker) -> None:
        self._make = make_worker  # order → worker, at the first submit (nothing to end before it)
        self.worker = None
        self._sent = 0  # records the worker has
        self._next_id = 0
        self._pending: int | None = None
        self.used = self.discarded = self.failed = self.late = 0
        self._late_run = 0
        self.ahead_s = self.waited_s = 0.0

    @classmethod
    def start(cls, order, where: str) -> "Lookahead":
        if where not in ("process", "inline"):
            raise ValueError(f"lookahead must be 'process' or 'inline', given {where!r}")
        return cls(ChoiceWorker if where == "process" else InlineWorker)

    def submit(self, order, cfg) -> None:
        """Compute the choice that follows ``cfg`` once it is measured."""
        if self._make is not None:
            make, self._make = self._make, None
            try:
                self.worker, self._sent = make(order), len(order.records)
            except Exception as exc:  # noqa: BLE001 - e.g. an unpicklable order: the run chooses itself
                log.warning("adaptive look-ahead not started (%s: %s); the run chooses after each measurement",
                            type(exc).__name__, exc)
                self.failed += 1
        if self.worker is None:
            return
        n = len(order.records) + 1
        self._next_id += 1
        job = {"id": self._next_id, "measured": list(order.design.measured) + [order.index[cfg.config_id]],
               "dropped": sorted(order.dropped), "records": order.records[self._sent:], "fits": dict(order._fits),
               "sigma_count": order.sigma_count(n), "here": [float(x) for x in np.asarray(cfg.q_rad).ravel()]}
        if self.worker.send(job):
            self._sent = len(order.records)
            self._pending = self._next_id
        else:
            self._lost("the worker is gone")

    def result(self, order) -> Ahead | None:
        """The pending job's answer (waiting up to ``WAIT_S``), its σ fits handed to ``order``;
        None when there is none (no job, an error, a timeout: the run computes the choice)."""
        if self._pending is None or self.worker is None:
            return None
        want, self._pending = self._pending, None
        t0 = time.perf_counter()
        deadline = t0 + WAIT_S
        while True:
            out = self.worker.receive(max(0.0, deadline - time.perf_counter()))
            if out is None:  # late (its answer is dropped when it comes) or gone
                self.waited_s += time.perf_counter() - t0
                self.late += 1
                self._late_run += 1
                if self._late_run >= MAX_LATE:
                    self._lost(f"{self._late_run} jobs in a row without an answer within {WAIT_S:g} s")
                return None
            if out.get("id") == want:
                break  # (answers to earlier jobs are stale: dropped)
        self.waited_s += time.perf_counter() - t0
        self._late_run = 0
        if "error" in out:
            log.warning("adaptive look-ahead: %s (the run chooses itself)", out["error"])
            self.failed += 1
            return None
        self.ahead_s += float(out["seconds"])
        for c, v in out["fits"].items():
            order._fits.setdefault(int(c), v)
        if out["index"] is None:  # the job found the rule met: the run decides with the new record
            return None
        return Ahead(tuple(out["key"]), int(out["index"]), dict(out["why"]))

    def count(self, used: bool) -> None:
        if used:
            self.used += 1
        else:
            self.discarded += 1

    def _lost(self, why: str) -> None:
        log.warning("adaptive look-ahead stopped: %s; the run chooses after each measurement", why)
        self.failed += 1
        self.close()

    def stats(self) -> dict:
        """Choices used and discarded, seconds computed ahead and waited for."""
        return {"used": self.used, "discarded": self.discarded, "failed": self.failed, "late": self.late,
                "ahead_seconds": round(self.ahead_s, 2), "waited_seconds": round(self.waited_s, 2)}

    def close(self) -> None:
        self._make = None
        if self.worker is not None:
            worker, self.worker = self.worker, None
            worker.close()
