"""Before a run moves anything: the output folder takes a file, the plan's configurations
less what a resumed log already has, the run's id and its log."""

from __future__ import annotations

import logging
import math
import os
import tempfile
from datetime import datetime, timezone
from pathlib import Path

from acquire.run.summary import RunError
from acquire.run.sequencer import SequencingSettings

log = logging.getLogger(__name__)

#: Expected sample rate (Hz) per sensor driver, for the cell-time estimate only.
SENSOR_RATE_HZ = {"natnet": 120.0, "tracker": 1000.0, "emscon": 1000.0}


def plan_settings(plan) -> SequencingSettings:
    """The plan's ``sequencing`` section in SI units (rad, s, mm)."""
    s = plan.sequencing
    return SequencingSettings(
        speed=float(s.speed),
        settle_window_s=float(s.settle_window_s),
        settle_tolerance_rad=math.radians(float(s.settle_tolerance_deg)),
        sensor_stable_mm=float(s.sensor_stable_mm),
        samples=int(s.samples),
        move_timeout_s=float(s.move_timeout_s),
        measure_timeout_s=float(s.measure_timeout_s),
        retries=int(s.retries),
        robot_fault_wait_s=float(s.robot_fault_wait_s),
        sensor_fault_wait_s=float(s.sensor_fault_wait_s),
    )


def make_run_id(cell: str, now: datetime | None = None) -> str:
    """``<cell>-<UTC yyyymmddThhmmss>-<ms>``."""
    now = now or datetime.now(timezone.utc)
    return f"{cell}-{now.strftime('%Y%m%dT%H%M%S')}-{int(now.microsecond / 1000):03d}"


def check_output(out_dir: Path, resume_path: Path | None) -> None:
    """Refuse, before any device is opened, a run whose log and results cannot be written:
    the output folder (created if missing) must take a new file, and a resumed log must be
    writable. Raises RunError saying which folder or file and what to do."""
    hint = "choose a writable folder with --out or the plan's output.folder"
    if resume_path is not None:
        target, hint = resume_path.parent, "copy the log to a writable folder and resume from there"
        if not os.access(resume_path, os.W_OK):
            raise RunError(f"--resume {resume_path}: the log is not writable; {hint}")
    else:
        target = out_dir
        try:
            target.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunError(f"output folder {target}: cannot create it ({exc.strerror or exc}); {hint}") from exc
    try:
        fd, probe = tempfile.mkstemp(prefix=".remaster-write-test-", dir=target)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise RunError(f"output folder {target}: cannot write in it ({exc.strerror or exc}); {hint}") from exc


def remaining(configs, resumed, *, plan_text: str, resume_path: Path | None, skip_failed: bool):
    """What is left to measure: ``(todo, ended, (measured, skipped, failed))``.

    Drops configurations the resumed log already measured, and those it skipped (the
    operator's or the plan's decision). Failed ones (a refused or faulted move, timeouts) are
    measured again unless ``skip_failed``. Without a resumed log everything is to do.
    """
    if resumed is None:
        return list(configs), set(), (0, 0, 0)
    if resumed.plan_text != plan_text:
        raise RunError(f"{resume_path}: the log was recorded with a different plan; resume it with "
                       "the plan it was recorded with")
    done = {s["config_id"] for s in resumed.samples}
    skipped = {e.get("config_id") for e in resumed.events if e.get("kind") == "skipped"} - done
    failed = {e.get("config_id") for e in resumed.events if e.get("kind") == "failed"} - done - skipped
    ended = skipped | failed if skip_failed else skipped
    if failed and not skip_failed:
        log.info("resume: measuring %d failed configuration(s) again: %s", len(failed), sorted(failed)[:10])
        failed = set()
    stray = done - {c.config_id for c in configs}
    if stray:
        raise RunError(f"{resume_path}: samples for configurations the plan does not have: {sorted(stray)[:5]}")
    todo = [c for c in configs if c.config_id not in done and c.config_id not in ended]
    return todo, done | ended, (len(done), len(skipped), len(failed))


def open_run_log(lp, *, run_id: str, out_dir: Path, resumed_path: Path | None, n_configs: int,
                 cell_metadata: dict, live=None):
    """The run's MCAP log: appended to on resume, else ``<out>/<run-id>/<run-id>.mcap`` with
    the plan and model texts and the cell's own metadata. Returns (RunLog, path)."""
    from acquire.record.recorder import RunLog

    out_dir.mkdir(parents=True, exist_ok=True)
    if resumed_path is not None:
        return RunLog.append_to(resumed_path, live=live), resumed_path
    run_dir = out_dir / run_id
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / f"{run_id}.mcap"
    meta = {"cell": lp.plan.cell, "robot": lp.model.name, "plan_path": str(lp.path),
            "model_path": str(lp.model_path), "n_configurations": str(n_configs)}
    meta.update({str(k): str(v) for k, v in cell_metadata.items()})
    return RunLog.create(path, run_id=run_id, plan_text=lp.text, model_text=lp.model_text, metadata=meta,
                         live=live), path
