"""What ``acquire run`` prints when a run has ended: counts, the log, the fitted offsets (beside a
simulated cell's truth when the command has it), compliances, a socket fit's placements."""

from __future__ import annotations

from pathlib import Path

from acquire.live.console import display_path


def socket_summary_lines(doc: dict) -> list[str]:
    """What a socket run's summary adds: the ball, its play, every placement's scores (spread of
    the predicted ball centre, socket-distance error) with the placement held out of the fit."""
    b = doc["ball_mm"]
    lines = ["ball on the flange: " + ", ".join(f"{v:.3f} ± {s:.3f}" for v, s in zip(b["value"], b["std"])) + " mm; "
             f"ball's play in the sockets σ = {doc['sigma_point_mm']:.3f} mm"]
    held = doc["scores"]["held_out"]
    if held:
        lines.append("held-out placements (fitted on the others, scored on this one), before → after:")
        for h in held:
            lines.append(f"  {h['placement']:<12} spread {h['before']['spread_mm']:.3f} → {h['after']['spread_mm']:.3f} mm, "
                         f"distance error {h['before']['distance_error_mm']:.3f} → {h['after']['distance_error_mm']:.3f} mm")
        mean = sum(h["after"]["spread_mm"] for h in held) / len(held)
        lines.append(f"  mean held-out spread {mean:.3f} mm")
    else:
        lines.append("held-out placements: none (needs three or more placements)")
    lines += [f"warning: {w}" for w in doc.get("warnings", [])]
    if not doc.get("trusted", True):
        lines.append(f"DO NOT ENTER these offsets: {doc.get('do_not_enter_reason', '')}")
    if doc.get("model_file"):
        lines.append(f"corrected model (tool: the fitted ball): {display_path(Path(doc['model_file']))}")
    return lines


def adaptive_summary_lines(ad: dict, cell_seconds: float | None = None) -> list[str]:
    """An adaptive run: why it stopped, the predicted intervals against the number of
    configurations (a few rows), and the estimated cell time against the full plan's — and
    against the cell time the run measured (``cell_seconds``, the cell's clock) when given and
    the run was not resumed (a segment's clock does not cover the earlier segments)."""
    lines = [f"adaptive: stopped after {ad['measured']} of {ad['candidates']} configurations — {ad['reason']}"]
    if ad.get("generated_candidates"):  # a pool beyond the plan (adaptive.candidates)
        lines.append(f"  {ad.get('generated_measured', 0)} of them generated (a pool of {ad['generated_candidates']} "
                     "beyond the plan's; the full plan compared with is the plan's)")
    hist = ad.get("history") or []
    if hist:
        step = max(1, len(hist) // 8)
        rows = hist[::step] + ([hist[-1]] if (len(hist) - 1) % step else [])
        lines.append("  configurations  largest 95 % half-width (deg)  predicted workspace / held-out error (mm)")
        for h in rows:
            lines.append(f"  {h['n']:>14}  {h['max_half_width_deg']:>29.4f}  {h['workspace_mm']:>18.4f} / "
                         f"{h.get('held_out_mm', float('nan')):.4f}")
        lines.append(f"  (the full plan would reach {hist[-1]['full_workspace_mm']:.4f} / "
                     f"{hist[-1].get('full_held_out_mm', float('nan')):.4f} mm; σ used {ad['sigma_mm']:.4f} mm)")
    lines += decision_lines(ad)
    saved = ad.get("saved_seconds")
    if saved is not None:
        comp = ad.get("compute_seconds")
        lines.append(f"  estimated cell time {ad['estimated_seconds']:.0f} s"
                     + (f" (with {comp:.1f} s choosing and refitting)" if comp else "")
                     + f" against {ad['full_plan_seconds']:.0f} s for the full plan: {saved:.0f} s "
                     f"({ad.get('saved_pct') or 0:.0f} %) saved")
        hist = ad.get("history") or [{}]
        if cell_seconds and hist[0].get("n", 0) == 0 and ad.get("estimated_seconds"):
            over = cell_seconds / ad["estimated_seconds"] - 1
            lines.append(f"  measured cell time {cell_seconds:.0f} s ({over:+.0%} against the estimate)")
            if over > 0.1:
                lines.append("  (moves, settling or measuring took longer than estimated: a simulated cell at "
                             "fake.time_scale > 1 falls behind its clock on a busy host — time a plan at "
                             "time_scale 1; on a real cell, check the speed override and the settle window)")
    return lines


def _num(v, fmt: str = ".4f", unit: str = "") -> str:
    return "–" if v is None else f"{v:{fmt}}{unit}"


def decision_lines(ad: dict) -> list[str]:
    """What backs the stop: each criterion (limit, predicted), the noise it was judged with, the
    predicted errors against the full plan's, and what the fit found after the fact."""
    dec = ad.get("decision")
    if not dec:
        return []
    unit = {"interval_deg": "°", "region_error_mm": " mm", "joint_space_error_mm": " mm"}
    lines = ["  the stop decision: " + "; ".join(
        f"{c['criterion']} {'≤' if c['met'] else '>'} {c['limit']:g}{unit.get(c['criterion'], ' %')} "
        f"(predicted {c['predicted']:.4g}{unit.get(c['criterion'], ' %')})" for c in dec["checks"])]
    n = dec["noise"]
    lines.append(f"  noise: plan {n['plan_per_reading_mm']:g} mm per reading / √{n['samples']} = "
                 f"{_num(n['plan_per_configuration_mm'])} mm per configuration; measured spread "
                 f"{_num(n['spread_mm'])} mm, fit's σ {_num(n['fitted_mm'])} mm, misfit {_num(n['misfit_mm'])} mm; "
                 f"σ used {_num(n['used_mm'])} mm")
    p = dec["predicted"]
    lines.append(f"  predicted at the stop (full plan): largest half-width {_num(p['max_half_width_deg'])}° "
                 f"({_num(p['full_max_half_width_deg'])}°), model error {_num(p['region_mm'])} mm "
                 f"({_num(p['full_region_mm'])}) in the plan's region, {_num(p['joint_space_mm'])} mm "
                 f"({_num(p['full_joint_space_mm'])}) over the working joint space, held-out {_num(p['held_out_mm'])} mm "
                 f"({_num(p['full_held_out_mm'])})")
    f = ad.get("found")
    if f:
        lines.append(f"  found by the fit: largest half-width {_num(f['max_half_width_deg'])}° (predicted "
                     f"{_num(f['predicted_max_half_width_deg'])}°; {f['determined']} of {f['of']} offsets determined), "
                     f"σ {_num(f['sigma_mm'])} mm (predicted {_num(f['predicted_sigma_mm'])}), misfit "
                     f"{_num(f['misfit_mm'])} mm (predicted {_num(f['predicted_misfit_mm'])})")
    return lines


def _attitude_metrics(node, label: str = "", depth: int = 0) -> list[tuple[str, dict, dict]]:
    """Every (label, before, after) in a result document whose before/after carry EACAE (degrees)."""
    out: list[tuple[str, dict, dict]] = []
    if not isinstance(node, dict) or depth > 4:
        return out
    b, a = node.get("before"), node.get("after")
    if isinstance(b, dict) and isinstance(a, dict) and b.get("EACAE") is not None and a.get("EACAE") is not None:
        return [(label, b, a)]
    for key, value in node.items():
        if key not in ("before", "after"):
            out += _attitude_metrics(value, f"{label}.{key}" if label else str(key), depth + 1)
    return out


def _oriented_configurations(log_path) -> int:
    """How many measured configurations of the run log carry a 6-DoF target's orientation."""
    try:
        from acquire.record.recorder import read_run

        samples = read_run(Path(log_path)).samples
    except Exception:  # noqa: BLE001 - a summary line must never fail the summary
        return 0
    return sum(any(isinstance(m.get("quat_wxyz"), list) for m in rec.get("markers") or []) for rec in samples)


def attitude_summary_lines(fit: dict, log_path=None) -> list[str]:
    """Attitude accuracy as the pose-selection paper reports it (EACAE / EMCAE, mean / max
    attitude error, degrees, before → after) wherever the result has it; otherwise, when the run
    measured orientations, how many and that this fit scored positions only."""
    found = [(label, b, a) for label, b, a in _attitude_metrics(fit.get("metrics") or {}, "")]
    found += [(label, b, a) for label, b, a in _attitude_metrics({k: v for k, v in fit.items() if k != "metrics"}, "")]
    lines = []
    for label, b, a in found:
        lines.append(f"attitude accuracy{' (' + label + ')' if label else ''}: EACAE {b['EACAE']:.4f} → {a['EACAE']:.4f}°, "
                     f"EMCAE {b['EMCAE']:.4f} → {a['EMCAE']:.4f}° (mean / max attitude error, before → after)")
    if not found and log_path is not None:
        n = _oriented_configurations(log_path)
        if n:
            lines.append(f"attitude: {n} configurations measured with the target's orientation (in the log and the "
                         "dataset); this fit scored positions only — `acquire fit LOG --method full` fits and scores "
                         "position and attitude (EACAE / EMCAE)")
    return lines


def format_run_summary(summary, lp, truth: list | None = None, sag: list | None = None) -> str:
    """The summary a person reads. ``truth`` / ``sag``: a simulated cell's hidden zero-offsets
    and mean gravity sag per joint (deg), shown beside the fit when given."""
    lines = [
        f"run {summary.run_id}: {summary.state}" + (f" ({summary.reason})" if summary.reason else ""),
        f"configurations: {summary.total} total, {summary.measured} measured, {summary.skipped} skipped, "
        f"{summary.failed} failed; {summary.wall_seconds:.1f} s wall, {summary.cell_seconds:.1f} s cell time",
        f"log: {display_path(summary.log_path)}",
    ]
    for cid, reason in list(summary.skipped_reasons.items())[:20]:
        lines.append(f"  not measured {cid}: {reason}")
    if getattr(summary, "adaptive", None):
        lines += adaptive_summary_lines(summary.adaptive, summary.cell_seconds)
    if summary.fit is not None:
        names = lp.model.axis_names
        head = f"{'joint':<6} {'fitted (deg)':>13} {'± std':>8}"
        if truth is not None:
            head += f" {'truth (deg)':>12} {'error':>8}"
        if sag is not None:
            head += f" {'mean sag':>9}"
        lines += ["", head]
        for i, j in enumerate(summary.fit["joint_offsets"]):
            v, sd = j.get("value_deg"), j.get("std_deg")
            row = f"{names[i]:<6} " + (f"{v:+13.4f}" if v is not None else f"{'—':>13}") + " " + (
                f"{sd:8.4f}" if sd is not None else f"{'—':>8}")
            if truth is not None:
                row += f" {truth[i]:+12.4f}" + (f" {v - truth[i]:+8.4f}" if v is not None else f" {'—':>8}")
            if sag is not None:
                row += f" {sag[i]:+9.4f}"
            if not j.get("identifiable", True):
                row += f"  {j.get('status', '')}"
            lines.append(row)
        choice = summary.fit.get("model_choice")
        if choice:
            from calib.fit.model_choice import format_table

            lines.append(format_table(choice))
            if summary.fit.get("model_file"):
                lines.append(f"corrected model (full identification): {display_path(Path(summary.fit['model_file']))}")
        entered = summary.fit.get("entered")
        if entered:  # what the controller gets: offsets for its nominal arm, judged held out (calib.fit.entered)
            from calib.fit.entered import format_heldout

            lines.append(format_heldout(entered))
            lines += [f"  enter {o['joint']}: δ = {o['value_deg']:+.4f}° ± {o['std_deg']:.4f}°"
                      for o in entered["offsets"] if o["enter"]]
        for reason in summary.fit.get("do_not_enter") or []:
            lines.append(f"DO NOT ENTER: {reason}" if not entered else f"the fitted model, not for compensation: {reason}")
        diag = summary.fit.get("diagnostics", {})
        fitted_compliance = diag.get("compliance") or summary.fit.get("compliance") or []
        for c in fitted_compliance:
            if c["status"] == "fitted":
                lines.append(f"compliance {c['joint']}: {c['value'] * 1e6:.2f} ± {c['std'] * 1e6:.2f} µrad/(N·m)")
            else:
                lines.append(f"compliance {c['joint']}: undetermined — {c['reason']}")
        if sag is not None:
            lines.append("mean sag: the simulated cell's gravity deflection of each joint, averaged over the plan —")
            if fitted_compliance:
                lines.append("the fit models it (joint compliances), so 'error' should stay within about 2 std")
            else:
                lines.append("a zero-offset fit cannot tell it from an offset, so expect 'error' to carry part of it")
        gsag = diag.get("gravity_sag")
        if gsag and gsag.get("significant"):
            lines.append(f"warning: the residuals follow the joints' gravity torques (p = {gsag['p_value']:.1g}): "
                         "the arm sags and the fit does not model it — set fit.compliance: true in the plan")
        lines += attitude_summary_lines(summary.fit, getattr(summary, "log_path", None))
        if summary.fit.get("kind") == "socket":
            lines += socket_summary_lines(summary.fit)
        lines.append("")
        lines.append(f"result: {display_path(summary.result_path)}")
        if summary.report_path is not None:
            lines.append(f"report: {display_path(summary.report_path)}")
    return "\n".join(lines)
