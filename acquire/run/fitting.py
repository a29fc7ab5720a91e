"""Handing a closed run log to the fitter: ``result.json`` and ``report.html`` (and the socket
fit's corrected ``model.yaml``) beside the log.

``preload_fit(lp)`` imports what that fit needs (the fit's modules and the reports', and scipy's
optimisers and statistics where the run has not loaded them yet: up to about 1 CPU-s, seconds of
wall on a busy host) in a thread while the robot moves, so that none of it falls between the last
measurement and the result; the run joins it before it fits (``acquire.run.ending.finish``).
Nothing is fitted ahead: the fit is the same.
"""

from __future__ import annotations

import importlib
import logging
import threading
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: The modules the default fit of a run imports where it needs them (its lazy imports, and theirs:
#: scipy.optimize, scipy.stats, scipy.linalg), for ``preload_fit``. ``tests/acquire/test_run_fit_wall.py``
#: checks that a fit after them imports nothing more.
FIT_MODULES = (
    "acquire.record.recorder", "calib.fit.auto_fit", "calib.fit.entered", "calib.fit.offsets",
    "calib.fit.model_choice", "calib.fit.parallel", "calib.fit.posterior", "calib.fit.attitude",
    "calib.fit.laplace_sampling", "calib.fit.sampling", "calib.fit.metrics", "calib.fit.result",
    "calib.fit.regstats", "calib.fit.pose_scoring", "calib.fit.identification", "calib.fit.progress",
    "calib.robot.controller", "calib.robot.gravity", "calib.plan.identifiability", "calib.report.html",
    "calib.report.report_figures", "calib.report.report_ident", "scipy.optimize", "scipy.stats",
)
#: A socket run's fit (``fit_socket_run_log``).
SOCKET_FIT_MODULES = (
    "acquire.run.socket_fit", "calib.fit.socket_choice", "calib.fit.model_choice", "calib.fit.identification",
    "calib.robot.controller", "calib.report.report_socket", "scipy.optimize", "scipy.stats",
)


def preload_fit(lp) -> threading.Thread:
    """Start importing the modules the end-of-run fit of ``lp``'s plan needs (``FIT_MODULES``, or
    ``SOCKET_FIT_MODULES``) in a daemon thread; returns it (join it before fitting: an import
    that fails is only logged here, the fit meets it again and says so). The run's own thread may
    import meanwhile: calib's modules import one another without a cycle at their top level, so
    two threads importing them wait at most for each other's module, never for each other."""
    names = SOCKET_FIT_MODULES if getattr(lp.plan, "socket", None) is not None else FIT_MODULES

    def load() -> None:
        for name in names:
            try:
                importlib.import_module(name)
            except Exception as exc:  # noqa: BLE001 - the fit imports it again and reports it
                log.debug("preloading the fit: %s: %s", name, exc)

    thread = threading.Thread(target=load, name="fit-preload", daemon=True)
    thread.start()
    return thread


def _link_tolerance(fit) -> tuple[float, float] | None:
    """The plan's link-parameter prior (mm, deg), or None for the paper's model."""
    mm, deg = getattr(fit, "link_tolerance_mm", 0.2), getattr(fit, "link_tolerance_deg", 0.02)
    return None if mm is None or deg is None else (float(mm), float(deg))


def fit_run_log(log_path: Path, lp, *, n_random: int = 500, progress=None) -> tuple[dict, Path, Path | None]:
    """Fit the zero-offsets from a run log; write ``result.json`` and ``report.html`` beside it.

    Returns (result document, result path, report path). The plan's ``fit`` section chooses
    the method, joints, error model, registration handling and validation fraction. ``progress``:
    a ``calib.fit.progress.Progress`` the default fit tells what it is doing (the run's status).
    """
    if getattr(lp.plan, "socket", None) is not None:
        return fit_socket_run_log(log_path, lp)
    from acquire.record.recorder import dataset_from_run
    from calib.robot.controller import apply_guards
    from calib.fit.entered import as_found_markers, attach, for_controller
    from calib.fit.offsets import FitOptions, fit_offsets
    from calib.robot.kinematics import Chain
    from calib.fit.metrics import accuracy_metrics
    from calib.fit.result import result_dict, write_result

    model = lp.model
    ds = dataset_from_run(Path(log_path), model)
    fit = lp.plan.fit
    frac = getattr(fit, "validate_fraction", None) or 0.0
    if frac > 0:
        configs = np.unique(ds.config)
        rng = np.random.default_rng(0)
        n_val = int(round(frac * len(configs)))
        val_ids = set(rng.choice(configs, size=n_val, replace=False).tolist()) if n_val else set()
        is_val = np.array([c in val_ids for c in ds.config])
        ds = ds.with_split("cal")
        ds.split[is_val] = "val"
    cal = ds.calibration()
    val = ds.validation() if np.any(ds.split == "val") else None
    joints = getattr(fit, "joints", None)
    options = FitOptions(
        method=getattr(fit, "method", "fast") or "fast",
        joints=tuple(joints) if joints else None,
        fix_registration=bool(getattr(fit, "fix_registration", False)),
        error=getattr(fit, "error", "gaussian") or "gaussian",
        link_tolerance=_link_tolerance(fit),
        compliance=bool(getattr(fit, "compliance", False)),
        tool_prior_mm=float(getattr(fit, "tool_prior_mm", 10.0)),
    )
    base = Path(log_path)
    if options.method == "auto":
        return _fit_run_auto(base, model, cal, val, options, fit, n_random, progress)
    result = fit_offsets(model, cal, options)
    metrics = accuracy_metrics(Chain(model), cal, result.applied_offsets_rad, result.offset_samples_rad,
                               result.applied_sigma_mm, validation=val, n_random=n_random, seed=0,
                               markers_mm=result.fitted_markers_mm, before_markers_mm=as_found_markers(model, cal))
    doc = result_dict(result, cal, metrics=metrics)
    # An offsets-only fit: its offsets are the controller's, judged against the robot as found held out.
    entered, _ = for_controller(model, cal, val, options, full_arm=None, full_folds=None, fitted_model=options.method,
                                own=result, more_guards=apply_guards(doc))
    _, text = attach(model, doc, entered)
    result_path = base.with_name("result.json")
    write_result(result_path, doc)
    report_path = None
    try:
        from calib.report.html import write_report

        report_path = base.with_name("report.html")
        write_report(report_path, result, cal, doc, text)
    except (ImportError, ValueError, RuntimeError, OSError) as exc:
        log.warning("report not written (use `acquire fit %s`): %s", log_path, exc)
        report_path = None
    return doc, result_path, report_path


def _fit_run_auto(base: Path, model, cal, val, options, fit, n_random: int,
                  progress=None) -> tuple[dict, Path, Path | None]:
    """The plan's ``fit.method: auto``: ``calib.fit.auto_fit`` (the data choose the model, full
    identification among the candidates; a link scale set in the plan is used instead of the
    empirical Bayes one; ``fit.compliance``: only the candidates with compliance, which leaves full
    identification out — the table says so). When full identification is chosen, the corrected
    model ``model.yaml`` is written beside the log and the report is the identification's."""
    from dataclasses import replace

    from calib.fit.auto_fit import auto_fit
    from calib.fit.result import write_result

    given = getattr(fit, "model_fields_set", set()) & {"link_tolerance_mm", "link_tolerance_deg"}
    done = auto_fit(model, cal, val, replace(options, method="laplace", compliance=False),
                    link_tolerance=_link_tolerance(fit) if given else None, n_random=n_random,
                    force=getattr(fit, "model", None), compliance_only=bool(getattr(fit, "compliance", False)) and model.has_dynamics,
                    progress=progress)
    if done.ident is not None:
        from calib.fit.identification import corrected_model, write_model_yaml

        model_path = base.with_name("model.yaml")
        write_model_yaml(corrected_model(model, done.ident.params), model_path)
        done.doc["model_file"] = str(model_path)
    result_path = base.with_name("result.json")
    write_result(result_path, done.doc)
    report_path = base.with_name("report.html")
    try:
        if done.ident is not None:
            from calib.report.report_ident import write_ident_report

            write_ident_report(report_path, done.ident, cal, done.doc)
        else:
            from calib.report.html import write_report

            write_report(report_path, done.result, cal, done.doc, done.controller_text)
    except (ImportError, ValueError, RuntimeError, OSError) as exc:
        log.warning("report not written (use `acquire fit %s`): %s", base, exc)
        report_path = None
    return done.doc, result_path, report_path


def fit_socket_run_log(log_path: Path, lp) -> tuple[dict, Path, Path | None]:
    """Fit a socket run (``acquire.run.socket_fit.run_socket_fit``; held-out placements with
    three or more): ``result.json``, ``report.html`` (``calib.report.report_socket``) and the
    corrected model ``model.yaml`` beside the log; returns (document, result path, report path). The
    plan's ``fit.method`` auto (the default) lets the data choose the model (a link prior set in the
    plan fixes its scale), fast uses the link prior (``link_tolerance_*``), paper/full identify
    without it."""
    from acquire.run.socket_fit import read_socket_run, run_socket_fit, write_socket_model
    from calib.fit.result import write_result

    model, fit = lp.model, lp.plan.fit
    ds = read_socket_run(Path(log_path), model.n_joints, distance_mm=lp.plan.socket.distance_mm)
    if ds is None:
        raise ValueError(f"{log_path}: no socket records to fit")
    method = getattr(fit, "method", "auto") or "auto"
    method = method if method in ("auto", "fast") else "full"
    given = getattr(fit, "model_fields_set", set()) & {"link_tolerance_mm", "link_tolerance_deg"}
    tolerance = _link_tolerance(fit) if method == "fast" or given else None
    compliance = bool(getattr(fit, "compliance", False))
    doc, result = run_socket_fit(model, ds, method=method, link_tolerance=tolerance, compliance=compliance,
                                 force=getattr(fit, "model", None) if method == "auto" else None)
    base = Path(log_path)
    doc["model_file"] = str(write_socket_model(model, result, base.with_name("model.yaml")))
    result_path = base.with_name("result.json")
    write_result(result_path, doc)
    report_path = base.with_name("report.html")
    try:
        from calib.report.report_socket import write_socket_report

        write_socket_report(report_path, doc)
    except (ImportError, ValueError, RuntimeError, OSError) as exc:
        log.warning("report not written (use `acquire fit %s --report report.html`): %s", log_path, exc)
        report_path = None
    return doc, result_path, report_path
