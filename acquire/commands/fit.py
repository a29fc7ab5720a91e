"""``acquire fit``: fit joint zero-offsets to a measurement file; write result.json and a report.

Example::

    acquire fit fixtures/datasets/iiwa14_sim_cal.csv --robot fixtures/robots/kuka_iiwa14_r820.yaml \\
        --validate fixtures/datasets/iiwa14_sim_val.csv -o result.json --report report.html

Prints the offsets ± std with their status, σ, sampler diagnostics, the accuracy metrics before
and after, and the values to enter on the controller. Input files are read by a loader chosen by
suffix (``LOADERS``); ``.csv`` is the format of ``calib.measure.dataset``. A run's MCAP log plugs in by
adding its loader here. Bad input exits non-zero with the file, line and column.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from acquire.record.datasets import load_dataset

if TYPE_CHECKING:  # the fit's modules load when it runs, not for `acquire fit --help`
    from calib.measure.dataset import Dataset
    from calib.fit.offsets import FitResult
    from calib.robot.model import RobotModel

log = logging.getLogger(__name__)



def _link_tolerance(text: str) -> tuple[float, float] | None:
    if text.strip().lower() == "none":
        return None
    try:
        mm, deg = (float(p) for p in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"expected MM,DEG like 0.2,0.02 or 'none', given {text!r}", param_hint="--link-tolerance") from None
    if not (0 < mm <= 5 and 0 < deg <= 1):
        raise typer.BadParameter(f"expected 0 < MM ≤ 5 and 0 < DEG ≤ 1, given {text!r}", param_hint="--link-tolerance")
    return mm, deg


def _joints(text: str | None, n: int) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        joints = tuple(int(p) for p in text.split(",") if p.strip())
    except ValueError:
        raise typer.BadParameter(f"expected axis numbers like 2,3,4, given {text!r}", param_hint="--joints") from None
    bad = [j for j in joints if not 1 <= j <= n]
    if not joints or bad:
        raise typer.BadParameter(f"axis numbers must lie in 1…{n}, given {text!r}", param_hint="--joints")
    return joints


def metric_notes(result: FitResult) -> list[str]:
    notes = [
        "before: nominal (current) offsets; after: the fitted offsets where identifiable, unchanged elsewhere.",
        "theoretical metrics: TCP = flange origin; posterior draws of the offsets, with and without the isotropic error σ (Sec. V-C).",
    ]
    held = [ax for ax, s in zip(result.model.axis_names, result.offset_status) if s != "fitted"]
    if held:
        notes.append(
            f"offsets of {', '.join(held)} are not determined (or not fitted) and held at nominal in the posterior draws: "
            "the theoretical metrics do not include their error."
        )
    notes.append(
        "the standard deviations assume independent isotropic errors (eq. 10); systematic errors the model lacks "
        "(link lengths, sag) bias the offsets beyond them — compare the validation metrics with the calibration ones."
    )
    return notes


def format_summary(doc: dict, controller_text: str, choice_text: str | None = None) -> str:
    """The terminal summary of a fit (``choice_text``: the model-choice table, ``ModelChoice.format``)."""
    lines = [f"robot: {doc['robot']['name']}", f"data: {doc['data']['source']} ({doc['data']['n_measurements']} measurements)", ""]
    if choice_text:
        lines += [choice_text, ""]
    lines.append(f"{'joint':<6} {'offset (deg)':>12} {'± std':>8} {'95 % interval':>22}  status")
    for j in doc["joint_offsets"]:
        if j["identifiable"]:
            ci = f"[{j['ci95_deg'][0]:+.4f}, {j['ci95_deg'][1]:+.4f}]"
            lines.append(f"{j['joint']:<6} {j['value_deg']:+12.4f} {j['std_deg']:8.4f} {ci:>22}  fitted")
        else:
            shown = "—" if j["value_deg"] is None else f"{j['value_deg']:+.4f}"
            lines.append(f"{j['joint']:<6} {shown:>12} {'—':>8} {'—':>22}  {j['status']}: {j['reason']}")
    lines.append("")
    for s, sig in doc["sigma_mm"].items():
        corr = doc["registration"][s]["corrections"]
        lines.append(
            f"sensor {s}: σ = {sig['value']:.3f} ± {sig['std']:.3f} mm; registration correction "
            + ", ".join(f"{k} {v['value']:+.3f}" for k, v in corr.items())
        )
    weight = doc.get("attitude_weight")
    if weight:
        lines.append(f"attitude rows weighted {weight['median_mm_per_rad']:.0f} mm/rad (median): {weight['how']}")
    tool = doc.get("tool") or {}
    for t in tool.get("markers") or []:
        lines.append(
            f"tool marker {t['marker']} (flange frame): "
            + ", ".join(f"{c} {v:+.3f} ± {sd:.3f} mm (model {nom:+.1f})"
                        for c, v, sd, nom in zip("xyz", t["value_mm"], t["std_mm"], t["nominal_mm"]))
            + f"; prior ±{t['prior_mm']:g} mm")
    if tool and not tool.get("markers"):
        lines.append("tool markers: the model's positions taken as exact (--tool-prior-mm 0)")
    d = doc["diagnostics"]
    lp = d.get("link_prior")
    if lp:
        lines.append(
            f"link parameters marginalised: {len(lp['parameters'])} (prior std {lp['length_mm']} mm, {lp['angle_deg']}°) — "
            "the intervals include what link errors of that size could shift"
        )
    for s, b in d.get("error_budget", {}).items():
        if b.get("noise_mm") is not None:
            lines.append(
                f"error budget {s}: sensor noise {b['noise_mm']:.3f} mm, unmodelled robot error {b['unmodelled_mm']:.3f} mm "
                f"({b['unmodelled_share']:.0%} of σ²) — the intervals treat it as random; where it is systematic "
                "(link errors, sag) the offsets are biased beyond them: compare with --method full"
            )
    rhat = d.get("rhat_max")
    ess = d.get("ess_min")
    imp = d.get("importance")
    if imp and not imp.get("fallback"):
        lines.append(f"posterior: Laplace (the least-squares solution and its covariance, as a Student t) checked by "
                     f"importance sampling: Pareto k̂ "
                     f"{imp['k_hat']:.2f} (< {imp['k_hat_max']}: used), effective draws {imp['ess']:.0f} of "
                     f"{imp['n_proposals']}, {d['seconds_total']:.2f} s")
    else:
        if imp:
            lines.append(f"posterior: the Laplace approximation failed its importance-sampling check (Pareto k̂ "
                         f"{imp['k_hat']:.2f} ≥ {imp['k_hat_max']}): sampled by {d['sampler']}")
        lines.append(
            f"sampler: {d['sampler']} ({d['method']}), {d['n_chains']} chain(s) × {d['n_draws']} draws, "
            f"R-hat max {'—' if rhat is None else f'{rhat:.3f}'}, ESS min {'—' if ess is None else f'{ess:.0f}'}, "
            f"acceptance {min(d['acceptance']):.2f}–{max(d['acceptance']):.2f}, {d['seconds_total']:.2f} s"
        )
    if rhat is not None and rhat > 1.05:
        lines.append(f"WARNING: R-hat {rhat:.3f} > 1.05 — the sampler has not converged; do not enter these values")
    ratios = {j["joint"]: j["sandwich_std_ratio"] for j in doc["joint_offsets"] if j.get("sandwich_std_ratio")}
    if ratios and max(ratios.values()) > 1.25:
        worst = max(ratios, key=ratios.get)
        lines.append(
            f"WARNING: the errors are not independent and isotropic as the model assumes: a model-robust "
            f"(sandwich) std of {worst} is {ratios[worst]:.2f}× the posterior's — its interval is too narrow"
        )
    for c in d.get("compliance") or []:
        if c["status"] == "fitted":
            lines.append(f"compliance {c['joint']}: {c['value'] * 1e6:.2f} ± {c['std'] * 1e6:.2f} µrad/(N·m), "
                         f"95 % [{c['ci95'][0] * 1e6:.2f}, {c['ci95'][1] * 1e6:.2f}]")
        else:
            lines.append(f"compliance {c['joint']}: undetermined — {c['reason']}")
    sag = d.get("gravity_sag")
    if sag and sag["significant"]:
        worst = sorted(sag["joints"], key=sag["joints"].get, reverse=True)[:2]
        lines.append(
            f"WARNING: the residuals follow the joints' gravity torques (score test χ² = {sag['statistic']:.1f} on "
            f"{sag['dof']} dof, p = {sag['p_value']:.1g}; mostly {', '.join(worst)}): the arm sags under its weight, "
            "which this fit does not model, so the offsets absorb part of it beyond their intervals — fit the joint "
            "compliances too: --compliance (a plan: fit.compliance: true)"
        )
    if ess is not None and ess < 100:
        lines.append(f"WARNING: ESS {ess:.0f} < 100 — too few effective draws for reliable means and standard deviations")
    metrics = doc.get("metrics", {})
    if metrics:
        lines += ["", f"{'accuracy (mm)':<40} {'before: mean [2.5 %, 97.5 %]':>30} {'after: mean [2.5 %, 97.5 %]':>30}"]
        for key, m in metrics.items():
            if isinstance(m, dict) and "before" in m and isinstance(m["before"], dict):
                b, a = m["before"], m["after"]
                lines.append(
                    f"{key:<40} {b['mean']:10.3f} [{b['p2_5']:.3f}, {b['p97_5']:.3f}]".ljust(71)
                    + f" {a['mean']:10.3f} [{a['p2_5']:.3f}, {a['p97_5']:.3f}]"
                )
        share = metrics.get("offsets_share")
        if share:
            lines.append(f"share of workspace error from the offsets alone: before {share['before']:.0%}, after {share['after']:.0%}")
    lines += ["", controller_text]
    return "\n".join(lines)


def fit(
    data: Path = typer.Argument(..., help="Measurements: CSV (calib.measure.dataset format)."),
    robot: Path = typer.Option(..., "--robot", help="Robot model YAML file (fixtures/robots/...)."),
    validate: Optional[Path] = typer.Option(None, "--validate", help="Validation measurements (Table VIII)."),
    method: str = typer.Option(
        "auto", "--method",
        help="auto (default: candidate models compared by cross-validated held-out error, the simplest within one "
        "standard error of the best fitted; Laplace posterior checked by Pareto-smoothed importance sampling), "
        "fast (exact independence sampler), paper (the paper's Metropolis), or full (identify every identifiable "
        "kinematic parameter by Levenberg–Marquardt).",
    ),
    model_name: Optional[str] = typer.Option(
        None, "--model",
        help="auto: force this candidate (offsets, offsets+tool, offsets+tool+links, full; socket data: offsets, "
        "offsets+ball, offsets+ball+links, full; +compliance with link masses): only this model is fitted; its held-out error against the nominal "
        "model is still scored and printed.",
    ),
    joints: Optional[str] = typer.Option(None, "--joints", help="Axes to fit, e.g. 2,3,4,5,6,7 (default: all)."),
    fix_registration: bool = typer.Option(False, "--fix-registration", help="Keep the initial registration (no T* correction)."),
    error: str = typer.Option("gaussian", "--error", help="Error model: gaussian (the paper's) or student (robust)."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    link_tolerance: Optional[str] = typer.Option(
        None, "--link-tolerance",
        help="fast, paper: MM,DEG: prior std of the link parameters (d, a in mm; α, β in degrees) the fit "
        "marginalises, so link errors widen the offsets' intervals instead of biasing them; 'none': the paper's "
        "model. Default 0.2,0.02. (full identifies the link parameters themselves.)",
    ),
    tool_prior_mm: float = typer.Option(
        10.0, "--tool-prior-mm",
        help="Prior std (mm, per coordinate) of the measured markers' positions on the flange about the robot "
        "model's: every method fits them and writes them to the corrected model; 0: the model's positions are exact.",
    ),
    draws: Optional[int] = typer.Option(None, "--draws", help="fast: draws per chain (4 chains). Default 1000."),
    paper_samples: Optional[int] = typer.Option(
        None, "--paper-samples", help="paper: Metropolis samples; the last 1/8 are kept. Default 200000."),
    n_random: Optional[int] = typer.Option(
        None, "--random-configs", help="fast, paper: random workspace configurations for the theoretical metric. Default 1000."),
    starts: Optional[int] = typer.Option(
        None, "--starts",
        help="full: starts of the identification — the staged solve from nominal, the plain one, then random starts "
        "(seeded by --seed); the best is kept and disagreeing starts are reported. Default 6.",
    ),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Write result.json here."),
    report: Optional[Path] = typer.Option(None, "--report", help="Write a self-contained report.html here."),
    model_out: Optional[Path] = typer.Option(
        None, "--model-out", help="full: write the identified robot model YAML here (default: beside -o as <name>.model.yaml)."
    ),
    compliance: bool = typer.Option(
        False, "--compliance",
        help="also fit one joint compliance per axis (gravity sag; the robot model needs link masses); auto: "
        "compare only the candidates with compliance.",
    ),
    socket_distance: Optional[float] = typer.Option(
        None, "--socket-distance",
        help="Socket data: distance between the sockets of each placement, mm (default: the file's "
        "'# socket_distance_mm:' line; without either the scale is undetermined).",
    ),
) -> None:
    """Fit the joint zero-offsets (and the sensor registration and σ) to measured marker positions."""
    if method not in ("auto", "fast", "paper", "full"):
        raise typer.BadParameter(f"expected auto, fast, paper or full, given {method!r}", param_hint="--method")
    refuse_options(method, {"--link-tolerance": link_tolerance is not None, "--draws": draws is not None,
                            "--paper-samples": paper_samples is not None, "--random-configs": n_random is not None,
                            "--error": error != "gaussian", "--starts": starts is not None,
                            "--model": model_name is not None})
    fixed_link_tolerance = link_tolerance
    link_tolerance = "0.2,0.02" if link_tolerance is None else link_tolerance
    draws = 1000 if draws is None else draws
    paper_samples = 200_000 if paper_samples is None else paper_samples
    n_random = 1000 if n_random is None else n_random
    if starts is not None and starts < 1:
        raise typer.BadParameter(f"must be at least 1 (the staged solve from nominal), given {starts}", param_hint="--starts")
    if error not in ("gaussian", "student"):
        raise typer.BadParameter(f"expected gaussian or student, given {error!r}", param_hint="--error")
    for name, value, low in (("--draws", draws, 10), ("--paper-samples", paper_samples, 80), ("--random-configs", n_random, 1)):
        if value < low:
            raise typer.BadParameter(f"must be at least {low}, given {value}", param_hint=name)
    # The fit's own modules: imported here, so that `acquire fit --help` and a refused option cost
    # no numpy and no fitter.
    import numpy as np

    from calib.robot.controller import apply_guards
    from calib.fit.entered import as_found_markers, attach, for_controller
    from calib.io.csvdialect import is_socket_csv
    from calib.measure.dataset import DatasetError
    from calib.fit.offsets import FitOptions, fit_offsets
    from calib.robot.kinematics import Chain
    from calib.fit.metrics import accuracy_metrics
    from calib.robot.model import load_robot_model
    from calib.fit.result import result_dict, write_result
    from calib.io.yamlfile import ConfigError

    try:
        model = load_robot_model(robot)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--robot") from exc
    socket_run = None
    if data.suffix.lower() == ".mcap" and data.is_file():
        from acquire.run.socket_fit import SocketDataError, read_socket_run  # the socket fit only for its data

        try:
            socket_run = read_socket_run(data, model.n_joints, distance_mm=socket_distance)
        except SocketDataError as exc:
            raise typer.BadParameter(str(exc), param_hint="DATA") from exc
        except (ValueError, OSError):
            socket_run = None  # not readable as a run here: load_dataset below says why
    if socket_run is not None or is_socket_csv(data):
        from acquire.commands.socket_fit import fit_socket_file

        sensor_only = {"--validate": validate is not None, "--joints": joints is not None, "--fix-registration": fix_registration,
                       "--error": error != "gaussian", "--method paper": method == "paper",
                       "--starts": starts is not None}
        refused = [k for k, v in sensor_only.items() if v]
        if refused:
            raise typer.BadParameter(f"{', '.join(refused)} do not apply to socket data (no sensor, no registration; "
                                     "held-out placements are scored automatically)", param_hint="DATA")
        # auto: the data choose the model (a --link-tolerance given fixes its link prior); fast: the
        # link prior of --link-tolerance (default 0.2 mm / 0.02°); full: no link prior.
        given = fixed_link_tolerance if method == "auto" else link_tolerance
        fit_socket_file(data, model, method=method, distance_mm=socket_distance,
                        link_tolerance=None if given is None else _link_tolerance(given),
                        output=output, model_out=model_out, compliance=compliance, dataset=socket_run, force=model_name, report=report)
        return
    refuse_options(method, {"--model-out": model_out is not None})  # a socket fit writes its model (above)
    if socket_distance is not None:
        raise typer.BadParameter("--socket-distance applies to socket data (a CSV ending in placement,socket)",
                                 param_hint="--socket-distance")
    try:
        ds = load_dataset(data, model)
    except DatasetError as exc:
        raise typer.BadParameter(str(exc), param_hint="DATA") from exc
    from calib.measure.ipa_tracker import is_ipa_series

    for path in (data, validate):
        if path is not None and is_ipa_series(path):
            typer.echo(f"note: {path} read as an IPA tracker series (';', decimal comma, joints in radians, T-Mac position "
                       f"mm and X-Y-Z Euler angles deg), marker {model.marker_names[0]!r}")
    val = None
    if validate is not None:
        try:
            val = load_dataset(validate, model)
        except DatasetError as exc:
            raise typer.BadParameter(str(exc), param_hint="--validate") from exc
    elif np.any(ds.split == "val"):
        val = ds.validation()
    cal = ds.calibration()
    if cal.has_orientation and method == "auto":
        typer.echo(f"note: {int(cal.oriented.sum())} rows carry a measured orientation: the chosen model is fitted on "
                   "their positions and attitudes together; the candidates are cross-validated on positions")
    if compliance and method == "paper":
        raise typer.BadParameter("the paper's model has no compliance: use --method fast or full", param_hint="--compliance")
    if not (math.isfinite(tool_prior_mm) and 0 <= tool_prior_mm <= 100):
        raise typer.BadParameter(f"expected 0 ≤ MM ≤ 100 (0: the markers' positions are exact), given {tool_prior_mm}",
                                 param_hint="--tool-prior-mm")
    noise = _estimate_noise(model, cal, FitOptions(joints=_joints(joints, model.n_joints), fix_registration=fix_registration,
                                                   seed=seed, tool_prior_mm=tool_prior_mm))
    if noise is not None:
        cal, noise = noise
    if method == "auto":
        _fit_auto(model, cal, val, FitOptions(joints=_joints(joints, model.n_joints), fix_registration=fix_registration,
                                              error=error, seed=seed, n_draws=draws, tool_prior_mm=tool_prior_mm),
                  model_name, None if fixed_link_tolerance is None else _link_tolerance(fixed_link_tolerance),
                  n_random, starts or 6, _full_exclusions(model, cal, _joints(joints, model.n_joints), fix_registration),
                  output, model_out, report, compliance, noise=noise)
        return
    if method == "full":
        from calib.fit.identification import IdentOptions  # the identification loads only for --method full

        options = IdentOptions(compliance=compliance, tool_prior_mm=tool_prior_mm, seed=seed, n_starts=starts or 6,
                               exclude_reasons=_full_exclusions(model, cal, _joints(joints, model.n_joints), fix_registration))
        _fit_full(model, cal, val, output, model_out, report, options,
                  entered_base=FitOptions(method="laplace", joints=_joints(joints, model.n_joints), seed=seed,
                                          fix_registration=fix_registration, tool_prior_mm=tool_prior_mm), noise=noise)
        return
    options = FitOptions(
        link_tolerance=_link_tolerance(link_tolerance),
        method=method,
        joints=_joints(joints, model.n_joints),
        fix_registration=fix_registration,
        error=error,
        seed=seed,
        n_draws=draws,
        paper_samples=paper_samples,
        paper_burn_in=paper_samples - max(paper_samples // 8, 40),
        compliance=compliance,
        tool_prior_mm=tool_prior_mm,
    )
    try:
        result = fit_offsets(model, cal, options)
    except ValueError as exc:  # DatasetError, or data a registration cannot use (e.g. collinear points)
        raise typer.BadParameter(str(exc), param_hint="DATA") from exc
    log.info("fitted %d measurements in %.2f s (%s)", len(cal), result.diagnostics["seconds_total"], method)
    metrics = accuracy_metrics(
        Chain(model), cal, result.applied_offsets_rad, result.offset_samples_rad, result.applied_sigma_mm,
        validation=val, n_random=n_random, seed=seed, markers_mm=result.fitted_markers_mm,
        before_markers_mm=as_found_markers(model, cal),
    )
    metrics["notes"] = metric_notes(result) + metrics.get("notes", [])
    doc = result_dict(result, cal, metrics=metrics)
    if result.posterior.attitude is not None:
        doc["attitude_weight"] = result.posterior.attitude.weight_info
    if noise is not None:
        doc["noise_estimate"] = noise
    model_refused = apply_guards(doc)
    # An offsets-only fit: the controller's offsets are the fit's own; scored against the robot as found.
    entered, _ = for_controller(model, cal, val, options, full_arm=None, full_folds=None, fitted_model=method, own=result,
                                more_guards=model_refused)
    refused, text = attach(model, doc, entered)
    typer.echo(format_summary(doc, text))
    if output is not None:
        write_result(output, doc)
        typer.echo(f"\nwrote {output}")
    if report is not None:
        from calib.report.html import write_report  # the report's modules only when one is asked for

        write_report(report, result, cal, doc, text)
        typer.echo(f"wrote {report}")
    _verdict_lines(refused, [], method)
    if refused or not math.isfinite(result.pooled_sigma_mm):
        raise typer.Exit(1)


#: Options that only some methods use, with what to use instead elsewhere.
METHOD_OPTIONS = {
    "--link-tolerance": (("fast", "paper", "auto"), "--method full identifies the link parameters themselves: drop --link-tolerance"),
    "--draws": (("fast", "auto"), "only the fast sampler takes draws (--method paper: --paper-samples; full samples nothing)"),
    "--paper-samples": (("paper",), "only the paper's Metropolis takes samples (--method fast: --draws)"),
    "--random-configs": (("fast", "paper", "auto"), "--method full scores the measured configurations and --validate data only"),
    "--error": (("fast", "paper", "auto"), "--method full is least squares (Gaussian errors): use --method fast or paper for "
                                   "the Student-t error model, or drop --error"),
    "--model-out": (("full", "auto"), "only --method full (and a socket fit) changes the robot model; the fast and paper fits write "
                               "their offsets with -o; `acquire model export MODEL --result RESULT.json` applies them to a URDF"),
    "--starts": (("full", "auto"), "the fast and paper fits start from their least-squares mode: --starts applies to --method full"),
    "--model": (("auto",), "--model chooses among the default's candidate models: drop --method, or drop --model"),
}


def refuse_options(method: str, given: dict[str, bool]) -> None:
    """Exit 2 naming an option ``method`` does not use and what to use instead."""
    for name, used in given.items():
        methods, instead = METHOD_OPTIONS[name]
        if used and method not in methods:
            raise typer.BadParameter(f"{name} does not apply to --method {method}: {instead}", param_hint=name)


def _full_exclusions(model: RobotModel, cal: Dataset, joints: tuple[int, ...] | None,
                     fix_registration: bool) -> tuple[tuple[str, str], ...]:
    """(parameter, reason) that --method full keeps nominal by the user's options: the zero-offsets
    of the axes --joints leaves out (their link parameters are still identified), the registration
    with --fix-registration (the least-squares one of the nominal model)."""
    out = []
    if joints is not None:
        out += [(f"{ax}.offset", "zero-offset kept nominal: the axis is not in --joints")
                for i, ax in enumerate(model.axis_names) if i + 1 not in joints]
    if fix_registration:
        from calib.fit.identification import REG

        out += [(f"{s}.{r}", "registration kept at the nominal model's least-squares one (--fix-registration)")
                for s in cal.sensors for r in REG]
    return tuple(out)


def _fit_full(model: RobotModel, cal: Dataset, val: Dataset | None, output: Path | None, model_out: Path | None,
              report: Path | None, options, *, done=None, entered_base=None, noise: dict | None = None) -> None:
    """``--method full``: Levenberg–Marquardt identification (``options``: ``calib.fit.identification.IdentOptions``),
    corrected model YAML, EACPE/EMCPE, and with ``report`` an HTML report (``calib.report.report_ident``); the
    offsets fitted for the controller's nominal arm (``entered_base``: their options; ``calib.fit.entered``),
    scored held out beside the identified model (without ``--validate``: each fold identified on its own).
    ``done``: a ``calib.fit.auto_fit.AutoFit`` that chose and identified the full model already."""
    from dataclasses import replace

    from calib.fit.entered import attach, for_controller, identified_arm
    from calib.fit.identification import corrected_model, ident_result_dict, identify, locate_unseen_markers, write_model_yaml
    from calib.fit.result import write_result

    if done is not None:
        result, doc = done.ident, done.doc
        refused, model_refused, entered_text = done.refused, done.model_refused, done.controller_text
    else:
        try:
            result = identify(model, cal, options)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="DATA") from exc
        doc = ident_result_dict(result, cal, val)
        entered, _ = for_controller(model, cal, val, entered_base, full_arm=identified_arm(result), fitted_model="full",
                                    full_folds=lambda train: identified_arm(identify(model, train, replace(options, n_starts=1))))
        refused, entered_text = attach(model, doc, entered)
        model_refused = list(result.do_not_use)
    if noise is not None:
        doc["noise_estimate"] = noise
    lines = ([done.choice.format(), ""] if done is not None else []) + [f"full identification of {model.name}: {len(result.free_names)} parameters from {len(cal)} measurements",
             f"rms residual {doc['rms_mm']:.4f} mm, scaled condition number {doc['condition_number']:.3g}"]
    lines += [f"warning: {w}" for w in result.warnings]
    lines.append("starts (best first): " + "; ".join(
        f"{s['label']} rms {s['rms_mm']:.4f} mm{'' if s['same_minimum'] else ' (worse minimum)'}" for s in result.starts))
    lines.append(f"{'parameter':<14}{'nominal':>12}{'identified':>14}{'± std':>10}")
    for p in doc["parameters"]:
        if p["identified"] and abs(p["change"]) > 0:
            lines.append(f"{p['name']:<14}{p['nominal']:>12.4f}{p['value']:>14.4f}{p['std']:>10.4f} {p['unit']}")
    for c in doc.get("compliance") or []:
        if c["status"] == "fitted":
            lines.append(f"compliance {c['joint']}: {c['value'] * 1e6:.2f} ± {c['std'] * 1e6:.2f} µrad/(N·m)")
    lines.append(f"kept nominal ({len(result.excluded)}):")
    lines += [f"  {k}: {v}" for k, v in result.excluded.items()]
    for part, m in doc["metrics"].items():
        b, a = m["before"], m["after"]
        lines.append(f"{part}: EACPE {b['EACPE']:.3f} → {a['EACPE']:.3f} mm, EMCPE {b['EMCPE']:.3f} → {a['EMCPE']:.3f} mm"
                     + (f", EACAE {b['EACAE']:.4f} → {a['EACAE']:.4f}°, EMCAE {b['EMCAE']:.4f} → {a['EMCAE']:.4f}°"
                        if b.get("EACAE") is not None and a.get("EACAE") is not None else ""))
        if "reregistered" in m:
            rb, ra = m["reregistered"]["before"], m["reregistered"]["after"]
            lines.append(f"{part}, re-registered on its own points (optimistic): EACPE {rb['EACPE']:.3f} → {ra['EACPE']:.3f} mm")
    lines += [f"note: {n}" for n in doc.get("metric_notes", [])]
    typer.echo("\n".join(lines))
    if model_out is None and output is not None:
        model_out = output.with_name(output.stem + ".model.yaml")
    if model_out is not None:
        # Markers the data did not measure move with the fitted ones (a nest plate), where that is known.
        unfitted = [m for m in model.marker_names if f"{m}.x" not in result.free_names]
        params, located = locate_unseen_markers(result, unfitted)
        write_model_yaml(corrected_model(model, params), model_out)
        doc["model_file"] = str(model_out)
        doc["model_file_markers_located"] = located
        typer.echo(f"wrote {model_out}" + (f" (unmeasured markers {', '.join(located)} moved with the fitted ones)" if located else ""))
    if output is not None:
        write_result(output, doc)
        typer.echo(f"wrote {output}")
    if report is not None:
        from calib.report.report_ident import write_ident_report  # the report's modules only when one is asked for

        write_ident_report(report, result, cal, doc)
        typer.echo(f"wrote {report}")
    typer.echo("\n" + entered_text)
    if result.do_not_use:
        typer.echo("DO NOT USE this identified model: " + "; ".join(result.do_not_use), err=True)
    _verdict_lines(refused, [], "full")
    if model_refused or refused:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add the ``fit`` sub-command to ``app``."""
    app.command("fit")(fit)


@contextlib.contextmanager
def fit_progress():
    """A ``calib.fit.progress.Progress`` for the default fit: on a terminal a live line on stderr
    (what the fit is doing, the time left in that stage, the time so far); otherwise its lines go
    to the log at INFO, one every 2 s at most, never a control character."""
    from acquire.live.progress import format_eta
    from calib.fit.progress import Progress

    t0 = time.monotonic()
    if not sys.stderr.isatty():
        yield Progress(lambda text, eta: log.info("fit: %s (ETA %s)", text, format_eta(eta)), every_s=2.0)
        return
    from rich.console import Console

    with Console(stderr=True).status("fitting …") as status:
        yield Progress(lambda text, eta: status.update(
            f"{text} — ETA {format_eta(eta)}, {format_eta(time.monotonic() - t0)} so far"))


def _fit_auto(model: RobotModel, cal: Dataset, val: Dataset | None, base, force: str | None,
              link_tolerance: tuple[float, float] | None, n_random: int, n_starts: int, exclusions, output: Path | None,
              model_out: Path | None, report: Path | None, compliance_only: bool = False, noise: dict | None = None) -> None:
    """The default: the data choose the model (``calib.fit.auto_fit``); the table, the fit, and "enter"
    only where earned (``calib.robot.controller.earned_reasons``)."""
    from calib.fit.auto_fit import auto_fit
    from calib.fit.result import write_result

    if force is not None:
        from calib.fit.model_choice import parse_candidate

        try:
            parse_candidate(force, model)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--model") from exc
    try:
        with fit_progress() as progress:
            done = auto_fit(model, cal, val, base, force=force, link_tolerance=link_tolerance, n_random=n_random,
                            n_starts=n_starts, ident_exclusions=exclusions, compliance_only=compliance_only,
                            noise_estimate=noise, progress=progress)
    except ValueError as exc:  # DatasetError, or data a registration cannot use (e.g. collinear points)
        raise typer.BadParameter(str(exc), param_hint="DATA") from exc
    if done.result is None:
        _fit_full(model, cal, val, output, model_out, report, None, done=done)
        return
    if model_out is not None:
        raise typer.BadParameter(f"the chosen model ({done.choice.chosen}) changes only the offsets and the tool: "
                                 "--model-out applies when full identification is chosen", param_hint="--model-out")
    doc = done.doc
    doc["metrics"]["notes"] = metric_notes(done.result) + doc["metrics"].get("notes", [])
    typer.echo(format_summary(doc, done.controller_text, done.choice.format()))
    for part, m in (doc.get("pose_metrics") or {}).items():
        b, a = m["before"], m["after"]
        typer.echo(f"{part} (position and attitude): EACPE {b['EACPE']:.3f} → {a['EACPE']:.3f} mm, EMCPE {b['EMCPE']:.3f} → "
                   f"{a['EMCPE']:.3f} mm" + (f", EACAE {b['EACAE']:.4f} → {a['EACAE']:.4f}°, EMCAE {b['EMCAE']:.4f} → "
                                             f"{a['EMCAE']:.4f}°" if b.get("EACAE") is not None else ""))
    if output is not None:
        write_result(output, doc)
        typer.echo(f"\nwrote {output}")
    if report is not None:
        from calib.report.html import write_report  # the report's modules only when one is asked for

        write_report(report, done.result, cal, doc, done.controller_text)
        typer.echo(f"wrote {report}")
    _verdict_lines(done.refused, done.model_refused, done.choice.chosen)
    if done.refused or not math.isfinite(done.result.pooled_sigma_mm):
        raise typer.Exit(1)


def _estimate_noise(model: RobotModel, cal: Dataset, base) -> tuple[Dataset, dict] | None:
    """The data's noise where they state no spreads (``calib.fit.noise``), printed; None when they do."""
    from calib.fit.noise import estimate_noise, format_estimate

    try:
        found = estimate_noise(model, cal, base)
    except ValueError as exc:  # too little data for the estimate's model: the fit says what it needs
        typer.echo(f"noise: the data state no spreads, and too few to estimate them ({exc}); no held-out check "
                   "against the noise, attitude rows (if any) at a fixed weight\n")
        return None
    if found is not None:
        typer.echo(format_estimate(found[1]) + "\n")
    return found


def _verdict_lines(refused: list[str], model_refused: list[str], model_name: str) -> None:
    """The verdict on the offsets the controller gets (``result.json`` ``entered``), and apart from it the
    guards of the fitted model (what export and compensation would use)."""
    if model_refused:
        typer.echo(f"the fitted model ({model_name}) is not to be used for compensation or export: "
                   + "; ".join(model_refused), err=True)
    if refused:
        typer.echo("DO NOT ENTER these offsets: " + "; ".join(refused), err=True)
