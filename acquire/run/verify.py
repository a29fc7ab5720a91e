"""A verification run: fresh configurations measured after the offsets were entered, scored as
the robot now runs, against what the calibration predicted.

``fresh_configurations(lp, ...)`` samples the plan's generated region again with another seed
(ids ``v07-b1``), leaving out any configuration the calibration measured. The run itself is an
ordinary ``RunController`` run of those configurations without a fit (its MCAP log, resumable);
``verify_log(log, lp, result)`` then scores it (``calib.fit.verification.verify_entry``) against
the calibration's prediction and writes ``verify.json`` and ``verify.html`` beside the log.

The prediction is ``result.json["entered"]["heldout"]``. A result written before the fit said
what the controller gets (no ``entered`` section) tells the operator its ``joint_offsets`` with
status ``fitted``; its prediction is then made here, held out, from the calibration's own log
(``calib.fit.as_running.predict_entry``: offsets fitted for the nominal arm), when that log is
where the result says it is.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from calib.robot.entered import EnteredValues, read_entered

log = logging.getLogger(__name__)

#: The fresh configurations' seed when none is given: the plan's generated seed plus this (the
#: adaptive pool uses + 1).
FRESH_SEED_OFFSET = 1000
#: Id prefix of the fresh configurations.
PREFIX = "v"
#: A fresh configuration this close (rad, every joint) to one the calibration measured is left out
#: (the measured angles sit within the settling tolerance of their targets).
SAME_Q_RAD = 1e-3


def fresh_configurations(lp, *, poses: int | None = None, seed: int | None = None,
                         exclude_q_rad: np.ndarray | None = None) -> list:
    """Configurations of the plan's generated region not measured by the calibration: ``poses``
    candidate poses (default the plan's ``n``) with ``seed`` (default the plan's + ``FRESH_SEED_OFFSET``),
    every feasible IK branch, less those within ``SAME_Q_RAD`` of a row of ``exclude_q_rad`` (k, n).
    Raises ConfigError (at the plan's poses) for a plan without a generated region or a seed that is
    the plan's own."""
    from acquire.plan.schema import region_configurations

    g = lp.plan.poses.generated if lp.plan.poses is not None else None
    if g is not None and seed is not None and seed == g.seed:
        raise lp.error(("poses", "generated", "seed"), f"the verification's poses must be other than the calibration's "
                                                       f"(given seed {seed}, the plan's own; allowed: another seed)")
    configs = region_configurations(lp, poses or (g.n if g is not None else 0),
                                    (g.seed + FRESH_SEED_OFFSET) if seed is None and g is not None else (seed or 0),
                                    PREFIX, what="fresh configuration")
    if exclude_q_rad is not None and len(exclude_q_rad):
        old = np.asarray(exclude_q_rad, dtype=float)
        configs = [c for c in configs if not np.any(np.all(np.abs(old - c.q_rad) < SAME_Q_RAD, axis=1))]
    return configs


def calibration_log(result_path: Path, doc: dict) -> Path | None:
    """The calibration's own log as the result names it (``data.source``), if it is still there."""
    source = (doc.get("data") or {}).get("source")
    if not source:
        return None
    path = Path(source)
    if not path.is_absolute():
        path = result_path.parent / path
    return path if path.is_file() else None


def load_result(result_path: Path) -> tuple[dict, EnteredValues]:
    """The result document and what it enters; ValueError naming the file when it cannot be read."""
    values = read_entered(result_path)
    return json.loads(Path(result_path).read_text(encoding="utf-8")), values


def prediction_for(result_path: Path, doc: dict, values: EnteredValues, model) -> tuple[dict | None, str]:
    """(the held-out prediction, where it comes from): the result's own, else one made from the
    calibration's log (see the module docstring), else None."""
    if values.heldout:
        return values.heldout, "the result's held-out prediction (entered.heldout)"
    cal_log = calibration_log(result_path, doc)
    if cal_log is None:
        return None, "none: the result has no held-out prediction and its calibration log is not at hand"
    from acquire.record.datasets import load_dataset
    from calib.fit.as_running import predict_entry

    tool_prior = (doc.get("tool") or {}).get("prior_mm") or 10.0
    try:
        data = load_dataset(cal_log, model)
        return (predict_entry(model, data.calibration(), tool_prior_mm=float(tool_prior)),
                f"made here from the calibration log {cal_log} (offsets fitted for the nominal arm, held out)")
    except ValueError as exc:
        log.warning("no prediction from the calibration log %s: %s", cal_log, exc)
        return None, f"none: the calibration log {cal_log} could not be scored ({exc})"


def verify_log(log_path: Path, lp, result_path: Path, *, out_dir: Path | None = None) -> tuple[dict, Path, Path | None]:
    """Score the verification run log ``log_path`` against the result ``result_path``; write
    ``verify.json`` and ``verify.html`` beside the log (or into ``out_dir``). Returns (document,
    json path, report path). Raises ValueError (DatasetError) for a log or a result that cannot be
    used, OSError for a folder that cannot be written."""
    from acquire.record.datasets import load_dataset
    from calib.fit.result import write_result
    from calib.fit.verification import verify_entry

    model = lp.model
    doc, values = load_result(result_path)
    robot = (doc.get("robot") or {}).get("axes")
    if robot is not None and list(robot) != list(model.axis_names):
        raise ValueError(f"{result_path}: the result is for axes {robot}, the plan's robot {model.name} has "
                         f"{model.axis_names}")
    data = load_dataset(Path(log_path), model)
    prediction, source = prediction_for(Path(result_path), doc, values, model)
    tool_prior = float((doc.get("tool") or {}).get("prior_mm") or 10.0)
    out = verify_entry(model, data, values.delta_deg(model.axis_names), prediction, tool_prior_mm=tool_prior)
    out.update({"result": str(result_path), "log": str(log_path), "entered_from": values.source,
                "prediction_from": source})
    cal_log = calibration_log(Path(result_path), doc)
    if cal_log is not None:
        out["calibration_log"] = str(cal_log)
    folder = Path(out_dir) if out_dir is not None else Path(log_path).parent
    path = write_result(folder / "verify.json", out)
    report = folder / "verify.html"
    try:
        from calib.report.report_verify import render_verify_report

        report.write_text(render_verify_report(out), encoding="utf-8")
    except (ValueError, OSError) as exc:
        log.warning("verify.html not written: %s", exc)
        report = None
    return out, path, report
