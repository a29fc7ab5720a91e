"""The default fit (``acquire fit``, and the run's end-of-run fit): the data choose the model
(``calib.fit.model_choice``), the chosen model is fitted with uncertainty, and "enter" is earned
(``calib.robot.controller.earned_reasons``) — for the model; the offsets the controller gets are fitted
for its nominal arm and earn "enter" held out against the robot as found (``calib.fit.entered``).

``auto_fit`` returns the ``result.json`` document with the cross-validation table under
``model_choice``. A chosen ``offsets…`` model is fitted by ``calib.fit.offsets.fit_offsets`` with the
Laplace + PSIS posterior (``method="laplace"``); a chosen ``full`` model by
``calib.fit.identification.identify`` (its document is the identification's, with the guards'
reasons in ``do_not_use``). An offsets model's intervals are widened by its held-out misfit where
that is above 1 (``calib.fit.heldout_misfit``; ``interval_scale`` in the document, and a line under
the model-choice table); the stored draws stay the posterior's.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calib.robot.controller import apply_guards, earned_reasons
from calib.measure.dataset import Dataset
from calib.fit.offsets import FitOptions, FitResult, fit_offsets
from calib.robot.model import RobotModel
from calib.fit.model_choice import ENTERED, ModelChoice, choose_model, interval_factor, options_for, parse_candidate
from calib.fit.heldout_misfit import scale_offset_intervals
from calib.fit.entered import as_found_markers, attach, fitted_arm, for_controller, identified_arm, refused_document


#: Where the controller's offsets (``ENTERED``: offsets+tool) start: that candidate's mode on all the
#: data, else the nearest candidate's (by name, ``fit_mode``: their common terms, the rest at nominal).
ENTERED_STARTS = ("offsets+tool", "offsets+tool+compliance", "offsets", "offsets+compliance")


def ident_joint_offsets(doc: dict, model: RobotModel) -> list[dict]:
    """The zero-offsets of a full identification's document (``ident_result_dict``) as the offsets
    fits' ``joint_offsets`` entries (degrees, wrapped to (−180°, 180°], 95 % interval), so that the
    run summary and the values to enter read them alike: "do not enter" with the reasons of
    ``doc["do_not_use"]``, "undetermined" for an offset the data did not identify. The rest of the
    identified model (link parameters, tool) is in the corrected model file, not on the controller."""
    from calib.robot.canonical import wrap_deg

    params = {p["name"]: p for p in doc["parameters"]}
    refused = "; ".join(doc.get("do_not_use") or [])
    out = []
    for i, ax in enumerate(model.axis_names):
        p = params.get(f"{ax}.offset")
        ok = bool(p and p["identified"] and p["std"] is not None)
        value = wrap_deg(p["value"]) if ok else None
        half = 1.96 * p["std"] if ok else None
        status = "undetermined" if not ok else ("do not enter" if refused else "fitted")
        reason = (p or {}).get("reason", "not identified by this data") if not ok else refused
        out.append({"joint": ax, "index": i + 1, "identifiable": status == "fitted", "value_deg": value,
                    "std_deg": p["std"] if ok else None, "ci95_deg": [value - half, value + half] if ok else None,
                    "status": status, "reason": reason})
    return out


@dataclass
class AutoFit:
    """``doc``: the result document; ``refused``: why not to enter the offsets fitted for the
    controller (``doc["entered"]``, ``calib.fit.entered``), [] if earned; ``model_refused``: why not to
    use the chosen model itself (its guards: for export and compensation); ``result`` (offsets models)
    or ``ident`` (full) is the fit itself; ``controller_text``: the three robots held out and the
    values to enter (from ``doc["entered"]``)."""

    choice: ModelChoice
    doc: dict
    refused: list[str]
    result: FitResult | None = None
    ident: object | None = None
    controller_text: str | None = None
    model_refused: list[str] = field(default_factory=list)


def auto_fit(model: RobotModel, cal: Dataset, val: Dataset | None, base: FitOptions = FitOptions(), *,
             force: str | None = None, link_tolerance: tuple[float, float] | None = None, n_random: int = 1000,
             n_starts: int = 6, ident_exclusions: tuple[tuple[str, str], ...] = (), k: int = 5,
             include_full: bool = True, compliance_only: bool = False, noise_estimate: dict | None = None,
             progress=None) -> AutoFit:
    """Choose the model by cross-validation (``force``: a candidate's name, ``--model``), fit it on
    all of ``cal``, score ``val`` and apply the guards. ``base``: the user's options (joints,
    registration, error model, tool prior, seed, draws); ``link_tolerance``: a fixed link scale
    instead of the empirical Bayes one; ``include_full``: False leaves full identification out of
    the candidates (the run's end-of-run fit, whose summary is the offsets'); ``noise_estimate``: how the
    rows' spreads were estimated where the data state none (``calib.fit.noise``), for the document;
    ``progress``: a ``calib.fit.progress.Progress`` told what the fit is doing."""
    from calib.robot.kinematics import Chain
    from calib.fit.metrics import accuracy_metrics
    from calib.fit.result import registration_statistics, result_dict

    base = replace(base, method="laplace", compliance=False)
    choice = choose_model(model, cal, base, force=force, k=k, link_tolerance=link_tolerance,
                          include_full=include_full, compliance_only=compliance_only, progress=progress)
    candidate = parse_candidate(choice.chosen, model)
    if candidate.kind == "full":
        from calib.fit.identification import IdentOptions, ident_result_dict, identify

        ident = identify(model, cal, IdentOptions(tool_prior_mm=base.tool_prior_mm, seed=base.seed, n_starts=n_starts,
                                                  exclude_reasons=ident_exclusions))
        doc = ident_result_dict(ident, cal, val)
        doc["model_choice"] = choice.to_dict()
        if noise_estimate:
            doc["noise_estimate"] = noise_estimate
        refused = [r for r in earned_reasons(doc) if r not in ident.do_not_use]
        refused += [f"tool: {w}" for w in ident.warnings if w.startswith("markers fitted far outside their prior")]
        ident.do_not_use.extend(refused)
        doc["do_not_use"] = list(ident.do_not_use)
        doc["joint_offsets"] = ident_joint_offsets(doc, model)
        refused, text = _enter_for_controller(model, cal, val, base, choice, doc, identified_arm(ident), k, progress)
        return AutoFit(choice, doc, refused, ident=ident, controller_text=text, model_refused=list(ident.do_not_use))
    scale = choice.link_scale
    tolerance = (scale["length_mm"], scale["angle_deg"]) if scale else None
    options = options_for(candidate, base, tolerance)
    if progress is not None:
        progress.begin(f"posterior of {choice.chosen}")
    result = fit_offsets(model, cal, options, start=choice.starts.get(choice.chosen), progress=progress)
    metrics = accuracy_metrics(Chain(model), cal, result.applied_offsets_rad, result.offset_samples_rad,
                               result.applied_sigma_mm, validation=val, n_random=n_random, seed=base.seed,
                               markers_mm=result.fitted_markers_mm, before_markers_mm=as_found_markers(model, cal))
    doc = result_dict(result, cal, metrics=metrics)
    # the registration seed's spatial correlation (scipy.stats; the default path has scipy loaded)
    doc["registration_statistics"] = registration_statistics(result)
    if noise_estimate:
        doc["noise_estimate"] = noise_estimate
    if result.posterior.attitude is not None:  # 6-DoF rows: the paper's position and attitude metrics
        from calib.fit.pose_scoring import pose_metrics

        post = result.posterior
        doc["pose_metrics"] = pose_metrics(post, result.mode[: post.dim], result.base2sensor0, cal, val)
        doc["attitude_weight"] = post.attitude.weight_info
    doc["model_choice"] = choice.to_dict()
    factor = interval_factor(choice.score(choice.chosen).misfit)
    if factor > 1.0:  # the intervals as wide as the held-out configurations say (calib.fit.heldout_misfit)
        scale_offset_intervals(doc, factor)
    refused, text = _enter_for_controller(model, cal, val, base, choice, doc, fitted_arm(result.posterior, result.mode[: result.posterior.dim]), k,
                                          progress, result if choice.chosen == ENTERED.name else None)
    return AutoFit(choice, doc, refused, result=result, controller_text=text, model_refused=apply_guards(doc))


def _enter_for_controller(model: RobotModel, cal: Dataset, val: Dataset | None, base: FitOptions, choice: ModelChoice,
                          doc: dict, full_arm, k: int, progress=None,
                          chosen_fit: FitResult | None = None) -> tuple[list[str], str]:
    """``doc["entered"]`` (``calib.fit.entered``: the offsets fitted for the controller's nominal arm and the
    three robots held out) and ``doc["controller"]`` from it; returns (why not to enter, the values' text).

    Nothing the model choice fitted is fitted again: the controller's offsets start from its fit of
    offsets+tool on all the data (or, where that was no candidate, of the nearest one: the same mode,
    fewer steps), are that fit's posterior itself where offsets+tool was chosen (``chosen_fit``), and
    its folds' offsets are the model choice's where the same axes are fitted."""
    chosen = choice.score(choice.chosen)
    names = {s.name for s in choice.scores}
    misfit = choice.score("offsets+tool").misfit if "offsets+tool" in names else None
    full_cv = None if chosen.failed else dict(zip(chosen.configs.tolist(), chosen.errors_mm.tolist()))
    start = next((choice.starts[n] for n in ENTERED_STARTS if n in choice.starts), None)
    if progress is not None:
        progress.begin("the controller's offsets (links at nominal) and their held-out check")
    try:
        entered, _ = for_controller(model, cal, val, base, full_arm=full_arm, full_folds=full_cv,
                                    fitted_model=choice.chosen, std_factor=interval_factor(misfit), k=k,
                                    start=start, reuse=chosen_fit, fold_offsets=choice.entered_folds)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:  # e.g. too few configurations for offsets+tool
        entered = refused_document(model, str(exc), "validation" if val is not None else "cross-validation")
    if full_cv is None and val is None:
        entered["reasons"].append(f"the chosen model ({choice.chosen}) could not be scored held out")
        entered["verdict"] = "do not enter"
        for o in entered["offsets"]:
            o["enter"], o["reason"] = False, o["reason"] or "do not enter: " + entered["reasons"][-1]
    return attach(model, doc, entered)
