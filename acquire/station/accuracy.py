"""How accurate a robot is as it runs, judged from an archived run: never the fit's model.

What a controller that takes zero offsets runs is its nominal arm at the angles it reports, plus
what was entered. ``run_accuracy(log_path, result)`` scores exactly that on the run's own
configurations with ``calib.fit.as_running.score_as_running`` (the robot model's text and the
measurements come from the run's MCAP log; per fold the registration and the tool are fitted on
the other folds, the fold's configurations scored; nothing scored was fitted on). Returns, in mm
(the mean over configurations of each one's rms distance measured − predicted)::

    {"before": the robot as it ran in this run (the controller's zeros as they were: whatever was
               entered earlier is in the reported angles),
     "after":  the same configurations with this run's values to enter added to the reported
               angles (``calib.robot.entered``: the ``entered`` section, or an older result's
               fitted ``joint_offsets``; nothing when the result says "do not enter"): the robot
               once they are entered,
     "n": configurations scored, "how": a sentence}

or ``{"before": None, "after": None, "n": 0, "how": why not}`` when the log cannot be scored (no
log archived, a log that is not MCAP, too few configurations for held-out folds).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def not_scored(why: str) -> dict:
    """The accuracy of a run that could not be scored, and why."""
    return {"before": None, "after": None, "n": 0, "how": f"not scored: {why}"}


def run_log_of(folder: Path, run_id: str) -> Path | None:
    """The first segment of the run's MCAP log in an archived run's ``folder`` (None: none there)."""
    path = Path(folder) / f"{run_id}.mcap"
    if path.is_file():
        return path
    return next((p for p in sorted(Path(folder).glob("*.mcap")) if ".resume" not in p.name), None)


def entered_shift_rad(result: dict, axis_names) -> np.ndarray:
    """(n,) rad: what ``result`` tells the operator to enter, per axis (0 where nothing is entered,
    and everywhere when the result says "do not enter")."""
    from calib.robot.entered import entered_values

    values = entered_values(result)
    if values.refused:
        return np.zeros(len(axis_names))
    return np.radians(values.delta_deg(axis_names))


def run_accuracy(log_path: Path | None, result: dict) -> dict:
    """The run's accuracy as the robot runs, before and after entering its values (module docstring)."""
    if log_path is None:
        return not_scored("no run log (.mcap) archived with the result")
    import yaml

    from acquire.record.datasets import load_dataset
    from acquire.record.recorder import RunLogError, read_run
    from calib.fit.as_running import FOLDS, score_as_running
    from calib.robot.model import robot_model_from_dict

    try:
        model = robot_model_from_dict(yaml.safe_load(read_run(log_path).model_text))
        data = load_dataset(Path(log_path), model)
        tool_prior = float((result.get("tool") or {}).get("prior_mm") or 10.0)
        shift = entered_shift_rad(result, model.axis_names)
        before = score_as_running(model, data, tool_prior_mm=tool_prior)
        after = score_as_running(model, data, joint_shift_rad=shift, tool_prior_mm=tool_prior)
    except (RunLogError, ValueError, TypeError, KeyError, yaml.YAMLError) as exc:
        log.warning("%s: accuracy not scored: %s", log_path, exc)
        return not_scored(f"{Path(log_path).name}: {exc}")
    n = int(before.errors_mm.size)
    return {"before": before.summary()["mean_mm"], "after": after.summary()["mean_mm"], "n": n,
            "how": f"the controller's nominal arm at the reported angles (after: plus the values to enter), "
                   f"{n} configurations of this run held out in {FOLDS} folds (registration and tool fitted on the "
                   "other folds)"}
