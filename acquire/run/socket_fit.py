"""``acquire fit`` on socket data: the sensorless calibration (``calib.fit.socket``).

Chosen by the file: a CSV whose header ends in ``placement,socket`` (``calib.fit.socket`` format).
Writes result.json (offsets, ball, socket points, identifiability, held-out scores), with
``--model-out`` (or beside ``-o``) the corrected robot model whose tool is the fitted ball, and
with ``--report`` the HTML report (``calib.report.report_socket``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calib.robot.canonical import wrap_deg
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.fit.socket import (
    SocketDataError,
    SocketDataset,
    SocketFit,
    fit_socket,
    held_out_placements,
    socket_scores,
)

#: A fitted play above this (mm) means the data, not the robot, is wrong: do not enter.
MAX_PLAUSIBLE_PLAY_MM = 1.0
#: An offset whose 95 % interval is wider than ± this (degrees) is too weakly determined to
#: enter: the correction could be worse than leaving the axis as it is.
MAX_ENTER_CI95_DEG = 0.1
#: "Enter" needs the chosen model's held-out rms distance within this many times the fitted play
#: (3-D, √3 σ_point): a model that predicts new placements far worse than it fits its own data
#: does not describe the arm.
MAX_HELDOUT_OVER_PLAY = 3.0


def _deg(kind: str) -> bool:
    return kind in ("offset", "alpha", "beta")


def socket_result_dict(model: RobotModel, ds: SocketDataset, fit: SocketFit, folds, method: str,
                       choice=None) -> dict:
    """result.json for a socket fit (mm, degrees); ``choice``: the model choice
    (``calib.fit.socket_choice.SocketChoice``) of ``--method auto``, whose table goes under
    ``model_choice`` and whose rules (``earned_reasons``) "enter" must meet."""
    chain = Chain(model)
    names = chain.param_names
    trusted, why = trust(fit)
    mc = choice.to_dict() if choice is not None else None
    if trusted and mc is not None:
        reasons = earned_socket_reasons(mc, fit)
        if reasons:
            trusted, why = False, "; ".join(reasons)
    offsets = []
    for i, ax in enumerate(model.axis_names):
        name = f"{ax}.offset"
        ok = name in fit.free_names
        half = 1.96 * math.degrees(fit.std[i]) if ok else math.nan
        if not ok:
            status, reason = "undetermined", fit.excluded.get(name, "")
        elif not trusted:
            status, reason = "do not enter", why
        elif half > MAX_ENTER_CI95_DEG:
            status, reason = "do not enter", (f"weakly determined: 95 % interval ±{half:.3f}° (> ±{MAX_ENTER_CI95_DEG}°); "
                                              "add configurations that turn this axis with the ball off its axis")
        else:
            status, reason = "fitted", ""
        offsets.append({
            "joint": ax, "index": i + 1, "identifiable": status == "fitted",
            "value_deg": wrap_deg(math.degrees(fit.params[i])) if ok else None,
            "std_deg": math.degrees(fit.std[i]) if ok else None,
            "ci95_deg": [wrap_deg(math.degrees(fit.params[i])) - half, wrap_deg(math.degrees(fit.params[i])) + half] if ok else None,
            "status": status, "reason": reason,
        })
    params = []
    for name in fit.free_names:
        if name.endswith(".compliance"):
            continue  # reported under "compliance"
        i = names.index(name)
        kind = name.rsplit(".", 1)[1]
        f = math.degrees if _deg(kind) else float
        params.append({"name": name, "nominal": f(chain.nominal[i]) if i < chain.marker_slice().start else None,
                       "value": f(fit.params[i]), "std": f(fit.std[i]), "unit": "deg" if _deg(kind) else "mm"})
    ball, ball_sd = fit.ball(chain)
    doc = {
        "kind": "socket",
        "method": method,
        "fit_model": {"method": method, "model": mc["chosen"] if mc else None, "description": fit.model_description(_prior_words(mc)),
                      "link_prior": None if fit.tolerance is None else {"mm": fit.tolerance[0], "deg": fit.tolerance[1]},
                      "compliance": fit.compliance is not None},
        "robot": {"name": model.name, "source": model.source},
        "data": {"source": ds.source, "n_configurations": int(len(ds.q_rad)),
                 "groups": [{"placement": p, "socket": s, "n": int(np.sum(ds.group == g))} for g, (p, s) in enumerate(ds.groups)],
                 "distances_mm": [{"a": "/".join(ds.groups[a]), "b": "/".join(ds.groups[b]), "mm": d} for a, b, d in ds.distances]},
        "joint_offsets": offsets,
        "parameters": params,
        "ball_mm": {"value": ball.tolist(), "std": ball_sd.tolist(), "frame": "flange"},
        "socket_points_mm": [{"placement": p, "socket": s, "value": fit.points[g].tolist(), "std": fit.points_std[g].tolist(),
                              "frame": "robot base"} for g, (p, s) in enumerate(ds.groups)],
        "compliance": None if fit.compliance is None else [
            {"joint": ax, "unit": "rad/(N·m)", "status": "fitted" if np.isfinite(sd) else "undetermined",
             "value": float(v) if np.isfinite(sd) else None, "std": float(sd) if np.isfinite(sd) else None,
             "reason": "" if np.isfinite(sd) else fit.excluded.get(f"{ax}.compliance", "")}
            for ax, v, sd in zip(model.axis_names, fit.compliance, fit.compliance_std)],
        "sigma_point_mm": fit.sigma_point_mm,
        "rms_mm": fit.rms_mm,
        "identifiability": {"excluded": fit.excluded, "weak": fit.weak, "condition_number": fit.condition_number},
        "scores": {
            "calibration": [s.__dict__ for s in socket_scores(chain, fit.params, ds, fit.compliance)],
            "held_out": [{"placement": h.before.placement, "before": h.before.__dict__, "after": h.after.__dict__,
                          "configurations": [{"config": c, "socket": s, "before_mm": float(b), "after_mm": float(a)}
                                             for c, s, b, a in zip(h.config_ids, h.sockets, h.before_mm, h.after_mm)]}
                         for h in folds],
            "notes": ["spread: RMS distance of the predicted ball centre from its socket's mean; distance error: "
                      "| |m_a − m_b| − distance |; configurations: each held-out configuration's distance from its "
                      "socket's mean prediction (their rms is the spread)", "held_out: fitted on the other placements, scored on this one (no re-fit)",
                      "before: the data-sheet model with the ball from the same training data"],
        },
        "trusted": trusted,
        "do_not_enter_reason": "" if trusted else why,
        "warnings": fit.warnings + fit.weak,
    }
    if mc is not None:
        doc["model_choice"] = mc
    return doc


def _prior_words(mc: dict | None) -> str:
    """How the chosen model's link prior was set, for ``SocketFit.model_description``."""
    scale = (mc or {}).get("link_scale") or {}
    if mc is None or mc["chosen"] not in scale:
        return "a fixed prior"
    return "a given prior" if scale[mc["chosen"]].get("given") else "an empirical-Bayes prior (max evidence)"


def earned_socket_reasons(mc: dict, fit: SocketFit) -> list[str]:
    """Why "enter" is not earned by the model choice ``mc`` (``SocketChoice.to_dict``) and the chosen
    fit: the tracker's rules (``calib.robot.controller.earned_reasons``: every fold fitted, better
    than the data sheet on held-out placements, held-out error below the guard) and a held-out rms
    within ``MAX_HELDOUT_OVER_PLAY`` × the fitted play."""
    from calib.robot.controller import earned_reasons

    reasons = earned_reasons({"model_choice": mc})
    chosen = next((c for c in mc["candidates"] if c["model"] == mc["chosen"]), None)
    play = math.sqrt(3.0) * fit.sigma_point_mm
    if chosen and chosen.get("cv_rms_mm") is not None and chosen["cv_rms_mm"] > MAX_HELDOUT_OVER_PLAY * play:
        reasons.append(f"held-out {mc['grouped_by']}s are predicted to {chosen['cv_rms_mm']:.3f} mm rms, more than "
                       f"{MAX_HELDOUT_OVER_PLAY:g}× the ball's play in the fitted data ({play:.3f} mm): the model does "
                       "not carry over to new placements (see the model-choice table)")
    return reasons


def trust(fit: SocketFit) -> tuple[bool, str]:
    """Whether the offsets may be entered, and if not, why."""
    if fit.sigma_point_mm > MAX_PLAUSIBLE_PLAY_MM:
        return False, (f"the ball scatters by {fit.sigma_point_mm:.2f} mm within a socket (> {MAX_PLAUSIBLE_PLAY_MM} mm): "
                       "the data are inconsistent (mislabelled placement/socket, loose ball)")
    if any("did not converge" in w for w in fit.warnings):
        return False, "the solver did not converge"
    return True, ""


def format_socket_summary(doc: dict) -> str:
    lines = [f"robot: {doc['robot']['name']}", f"socket data: {doc['data']['source']} "
             f"({doc['data']['n_configurations']} configurations, {len(doc['data']['groups'])} placement/socket groups)"]
    fm = doc.get("fit_model")
    if fm:
        chosen = f" — model {fm['model']}" if fm.get("model") else ""
        lines.append(f"method: {fm['method']}{chosen} — fitted model: {fm['description']}")
    if doc.get("model_choice"):
        from calib.fit.model_choice import format_table

        lines += [format_table(doc["model_choice"])]
        for name, sc in (doc["model_choice"].get("link_scale") or {}).items():
            how = "given" if sc.get("given") else "empirical Bayes, max evidence"
            lines.append(f"  link prior of {name} ({how}): lengths ±{sc['length_mm']:g} mm, angles ±{sc['angle_deg']:g}°")
    lines.append("")
    lines.append(f"{'joint':<6} {'offset (deg)':>12} {'± std':>8}  status")
    for j in doc["joint_offsets"]:
        if j["value_deg"] is not None:
            lines.append(f"{j['joint']:<6} {j['value_deg']:+12.4f} {j['std_deg']:8.4f}  {j['status']} {j['reason']}".rstrip())
        else:
            lines.append(f"{j['joint']:<6} {'—':>12} {'—':>8}  {j['status']}: {j['reason']}")
    b = doc["ball_mm"]
    lines.append("")
    lines.append("ball in the flange frame: " + ", ".join(f"{v:.3f} ± {s:.3f}" for v, s in zip(b["value"], b["std"])) + " mm")
    lines.append(f"ball's play in the sockets: σ = {doc['sigma_point_mm']:.3f} mm; {len(doc['parameters'])} parameters fitted")
    for c in doc.get("compliance") or []:
        if c["status"] == "fitted":
            lines.append(f"compliance {c['joint']}: {c['value'] * 1e6:.1f} ± {c['std'] * 1e6:.1f} µrad/(N·m)")
    ex = doc["identifiability"]["excluded"]
    if ex:
        lines.append("not determined by socket data (kept nominal):")
        lines += [f"  {k}: {v}" for k, v in ex.items()]
    held = doc["scores"]["held_out"]
    if held:
        lines.append("held-out placements (fit on the others, score this one):")
        for h in held:
            lines.append(f"  {h['placement']}: spread {h['before']['spread_mm']:.3f} → {h['after']['spread_mm']:.3f} mm, "
                         f"distance error {h['before']['distance_error_mm']:.3f} → {h['after']['distance_error_mm']:.3f} mm")
    lines += [f"warning: {w}" for w in doc["warnings"]]
    if not doc["trusted"]:
        lines.append(f"DO NOT ENTER these offsets: {doc['do_not_enter_reason']}")
    else:
        lines.append("the offsets were fitted together with the link parameters: entering only the offsets on the "
                     "controller corrects the axis zeros; the corrected model file carries the rest.")
    return "\n".join(lines)


def read_socket_run(path: Path, n_joints: int, *, distance_mm: float | None = None) -> SocketDataset | None:
    """The socket dataset of an ``acquire run`` log (MCAP) whose samples are socket records:
    measured joint angles with their placement and socket; the distance between sockets from
    ``distance_mm`` or else the run's plan (``socket.distance_mm``). None for any other log."""
    from acquire.record.recorder import read_run
    from calib.fit.socket import with_distance
    from calib.io.yamlfile import ConfigError, parse_yaml_text

    rc = read_run(path)
    recs = [r for r in rc.samples if isinstance(r.get("socket"), dict)]
    if not recs:
        return None
    if len(recs) != len(rc.samples):
        raise SocketDataError(f"{path}: {len(rc.samples) - len(recs)} sample(s) are not socket records")
    q, keys, ids = [], [], []
    for rec in recs:
        qm = rec.get("q_measured_deg")
        if not isinstance(qm, list) or len(qm) != n_joints:
            raise SocketDataError(f"{path}: configuration {rec.get('config_id')!r}: q_measured_deg must hold "
                                  f"{n_joints} numbers, given {qm!r}")
        q.append(qm)
        keys.append((str(rec["socket"]["placement"]), str(rec["socket"]["socket"])))
        ids.append(str(rec["config_id"]))
    if distance_mm is None:
        try:
            plan = parse_yaml_text(rc.plan_text or "", f"{path} (recorded plan)")[0]
        except ConfigError:
            plan = None
        socket = plan.get("socket") if isinstance(plan, dict) else None
        distance_mm = socket.get("distance_mm") if isinstance(socket, dict) else None
    groups = sorted(set(keys))
    gidx = np.array([groups.index(k) for k in keys], dtype=int)
    return SocketDataset(np.radians(np.array(q, dtype=float)), gidx, groups, with_distance(groups, distance_mm), ids, str(path))


def write_socket_model(model: RobotModel, fit: SocketFit, path: Path) -> Path:
    """The corrected robot model whose tool is the fitted ball (marker ``ball``), as YAML."""
    from calib.fit.identification import corrected_model, write_model_yaml

    chain = Chain(model)
    ms = chain.marker_slice()
    tool_model = model.model_copy(update={"tool": model.tool.model_copy(update={
        "markers": [model.tool.markers[0].model_copy(update={"name": "ball", "xyz": (0.0, 0.0, 0.0)})]})})
    params = np.concatenate([fit.params[: ms.start], fit.params[ms.start:ms.start + 3]])
    write_model_yaml(corrected_model(tool_model, params), path)
    return path


def run_socket_fit(model: RobotModel, ds: SocketDataset, *, method: str, link_tolerance: tuple[float, float] | None,
                   compliance: bool = False, force: str | None = None) -> tuple[dict, SocketFit]:
    """The socket fit of ``method``: auto (the data choose the model, ``calib.fit.socket_choice``;
    ``force``: ``--model``; ``link_tolerance`` given: that link prior instead of the empirical
    Bayes one; ``compliance``: only the compliance candidates), fast (the link prior
    ``link_tolerance``) or full (no link prior). Returns (result document, fit)."""
    choice = None
    if method == "auto":
        from calib.fit.socket_choice import choose_socket_model, chosen_options

        choice = choose_socket_model(model, ds, force=force, link_tolerance=link_tolerance,
                                     compliance_only=compliance and model.has_dynamics)
        options = chosen_options(model, choice)
    else:
        options = {"tolerance": None if method == "full" else link_tolerance, "compliance": compliance}
    fit = fit_socket(model, ds, **options)
    folds = held_out_placements(model, ds, **options) if len(ds.placements) >= 3 else []
    return socket_result_dict(model, ds, fit, folds, method, choice), fit
