"""Small plans for the run tests: the bundled example / tracker plans, shrunk, in a temp folder."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]


def small_plan(tmp_path: Path, base: str = "example.yaml", *, n: int = 8, name: str = "plan.yaml", **overrides) -> Path:
    """Write a shrunk copy of ``fixtures/plans/<base>`` (``n`` candidate poses, output in
    ``tmp_path/runs``); ``overrides`` are ``section={key: value}`` updates."""
    doc = yaml.safe_load((ROOT / "fixtures" / "plans" / base).read_text())
    doc["robot"] = str((ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").resolve())
    doc["fake"]["sim_config"] = str((ROOT / "fixtures" / "sim" / "default.yaml").resolve())
    doc["poses"]["generated"]["n"] = n
    doc["output"]["folder"] = str(tmp_path / "runs")
    for section, values in overrides.items():
        if isinstance(values, dict):
            doc.setdefault(section, {}).update(values)
        else:
            doc[section] = values
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def acquire_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "acquire", *args]


def popen(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen(acquire_cmd(*args), cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def run_logs(folder: Path) -> list[Path]:
    """The first segment of every run log under ``folder``."""
    return sorted(p for p in folder.rglob("*.mcap") if ".resume" not in p.name)


@contextmanager
def simulated_run(lp, *, process: bool = True, **kwargs):
    """``(RunController, SimulatedCell)``: the plan's simulated cell started as ``acquire run
    --fake`` starts it, and a run handed its description (``kwargs`` go to the controller).
    ``process=False``: the cell's devices as threads of this process, for a test that reaches
    into one (``sim.launch.trackers``…). The cell is closed on leaving."""
    from acquire.commands.fake import describe_for, simulated_cell
    from acquire.run import RunController

    sim = simulated_cell(lp, process=process).start()
    try:
        yield RunController(lp, cell=describe_for(sim, lp), **kwargs), sim
    finally:
        sim.close()


def fake_controller(lp, **kwargs):
    """A RunController handed the description of the plan's simulated cell, started as ``acquire
    run --fake`` starts it; the cell is ``.sim`` and closes once the run has ended."""
    import threading

    from acquire.commands.fake import describe_for, simulated_cell
    from acquire.run import RunController

    sim = simulated_cell(lp).start()
    rc = RunController(lp, cell=describe_for(sim, lp), **kwargs)
    rc.sim = sim

    def close_after_the_run() -> None:
        try:
            rc.wait()
        finally:
            sim.close()

    threading.Thread(target=close_after_the_run, name="sim-closer", daemon=True).start()
    return rc


# A whole run is judged by whether it moves on, not by a wall-clock guess of its length: on a loaded
# machine (six test workers on two cores) a fake run can take several times as long as on an idle
# one. STALL_S is how long a run may show no progress before the test calls it stuck; RUN_TIMEOUT_S
# is the pytest-timeout backstop for the modules that run whole fake runs.
STALL_S = 120.0
RUN_TIMEOUT_S = 900


def wait_for_run(rc, *, stall_s: float = STALL_S):
    """The run's summary, waited for as long as the run makes progress.

    Raises TimeoutError only when the run's status (state, configurations done, measured, failed,
    skipped, the current one) has not changed for ``stall_s`` seconds (the end-of-run fit counts
    as one step, so ``stall_s`` must cover the fit on a loaded machine)."""
    last, since = None, time.monotonic()
    while True:
        try:
            return rc.wait(1.0)
        except TimeoutError:
            s = rc.status()
            key = (s["state"], s["done"], s["measured"], s["failed"], s["skipped"], s["current"])
            if key != last:
                last, since = key, time.monotonic()
            elif time.monotonic() - since > stall_s:
                raise TimeoutError(f"run {s['run_id']} made no progress for {stall_s:.0f} s: {s}") from None


def aborted_run(lp, after: int):
    """A fake run of ``lp`` (no fit) aborted by the operator once ``after`` configurations are
    measured; its summary (state "aborted" unless the run ended first)."""
    def abort_once_measured(status):
        if status["measured"] >= after and status["state"] == "running":
            rc.abort("test abort")

    rc = fake_controller(lp, on_progress=abort_once_measured, fit=False)
    rc.start()
    return wait_for_run(rc)


def resumed_run(lp, log_path):
    """The fake run of ``lp`` (no fit) resuming the log ``log_path``, to its end; its summary."""
    rc = fake_controller(lp, resume=log_path, fit=False)
    rc.start()
    return wait_for_run(rc)


def faulted_run(lp, fault: str, device: str | None = None, duration_s: float | None = None,
                probability: float | None = None, *, at: str = "moved", nth: int = 1):
    """A fake run of ``lp`` (no fit) with one fault injected through the simulated cell's fault
    API (``CellProcess.inject``, as ``acquire sim``'s stdin does) the ``nth`` time the run logs an
    event of kind ``at`` (``moved``: the robot has just arrived, settling starts). Returns
    ``(summary, contents of the run log, devices hit)``."""
    from acquire.record.recorder import read_run

    rc = fake_controller(lp, fit=False)
    seen, hit = [0], []
    publish = rc.pub.event

    def event(kind: str, **fields) -> None:
        publish(kind, **fields)
        if kind == at:
            seen[0] += 1
            if seen[0] == nth:
                hit.extend(rc.sim.launch.inject(fault, device, duration_s, probability))

    rc.pub.event = event  # the run's own event sink: the fault lands at a known step of the run
    rc.start()
    summary = wait_for_run(rc)
    return summary, read_run(summary.log_path), hit
