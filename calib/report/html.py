"""A self-contained ``report.html`` of a fit: one file, its plots inline SVG (``calib.report.svg``).

Sections: a one-screen summary (``calib.report.report_summary``: enter / do not enter, the values,
accuracy before/after, warnings); the values to enter with the controller's sign convention;
zero-offsets; registration and σ; accuracy metrics before/after (Tables III–VIII of the paper);
identifiability (every direction the data leave weak or undetermined, named as the combination
of parameters it mixes — ``calib.plan.identifiability``); sampler diagnostics; and figures
(``calib.report.report_figures``): the paper's TCP cloud (Fig. 5), trace plots and posterior
histograms, and the post-registration error per configuration. The HTML reflows down to a
phone's width: the figures are vector graphics, and panels side by side wrap.
"""

from __future__ import annotations

import math
from pathlib import Path

from calib.measure.dataset import Dataset
from calib.fit.offsets import FitResult
from calib.plan.identifiability import WEAK_NOISE_FACTOR
from calib.report.report_compliance import compliance_section
from calib.report.report_format import CSS, Html, esc, fixed, num, table
from calib.report.report_summary import summary_html

METRIC_TITLES = {
    "relative": "Relative (eq. 17, Table III)",
    "absolute": "Post-registration absolute (eq. 18, Table IV)",
    "theoretical_measured": "Theoretical, offsets + σ, measured configurations (Table V)",
    "theoretical_measured_offsets_only": "Theoretical, offsets alone, measured configurations",
    "theoretical_workspace": "Theoretical, offsets + σ, random workspace configurations (Table VI)",
    "theoretical_workspace_offsets_only": "Theoretical, offsets alone, random workspace configurations (Table VII)",
    "validation_relative": "Validation set, relative (Table VIII)",
    "validation_absolute": "Validation set, absolute with the calibration registration (Table VIII)",
    "validation_absolute_reregistered": "Validation set, absolute re-registered on the validation points (optimistic)",
    "validation_absolute_unseen_markers": "Validation points of markers the calibration never measured (model's "
                                          "marker position; not the headline)",
}

VERDICT_CLASS = {"determined": "good", "weakly determined": "warn", "not determined": "bad"}


def _controller_section(doc: dict, controller_text: str) -> list[str]:
    ctrl = doc.get("controller")
    out = ["<h2 id=controller>Values to enter</h2>"]
    if not ctrl:
        if controller_text:
            out.append(f"<pre class=wrap>{esc(controller_text)}</pre>")
        return out
    out.append(f"<p>controller: <b>{esc(ctrl['controller'])}</b>. {esc(ctrl['convention'])}</p>")
    out.append(f"<p class=warn>{esc(ctrl['sign_convention'])}</p>")
    out.append("<p class=small>The values per axis are in the <a href='#summary'>summary</a> above.</p>")
    return out


def _offsets_section(doc: dict) -> list[str]:
    rows, notes = [], []
    for j in doc["joint_offsets"]:
        ci = j["ci95_deg"]
        status = j["status"]
        rows.append([
            j["joint"],
            Html(fixed(j["value_deg"], 4, sign=True)) if j["value_deg"] is not None else None,
            Html(fixed(j["std_deg"], 4)) if j["std_deg"] is not None else None,
            Html(f"[{fixed(ci[0], 4, sign=True)}, {fixed(ci[1], 4, sign=True)}]") if ci else None,
            Html(num(j.get("sandwich_std_ratio"), 3)),
            Html(f"<span class={'good' if status == 'fitted' else 'warn'}>{esc(status)}</span>"),
        ])
        notes.append(j.get("reason") or None)
    return [
        "<h2>Zero-offsets</h2>",
        table(["joint", "value (°)", "std (°)", "95 % interval (°)", "sandwich ÷ std", "status"], rows, notes=notes),
        "<p class=small>sandwich ÷ std: a model-robust standard deviation (configurations independent, errors of "
        "any shape) over the posterior's; well above 1 means the errors are not isotropic and the interval is too "
        "narrow. Systematic errors shared by all configurations (link lengths) show in neither.</p>",
    ]


def _registration_section(doc: dict) -> list[str]:
    out = ["<h2>Registration corrections and σ</h2>"]
    for s, reg in doc["registration"].items():
        rows = [[k, Html(num(v["value"])), Html(num(v["std"], 2)), "free" if v["free"] else "fixed"] for k, v in reg["corrections"].items()]
        sig = doc["sigma_mm"][s]
        rows.append(["σ (mm)", Html(num(sig["value"])), Html(num(sig["std"], 2)), "free"])
        out += [f"<h3>{esc(s)}</h3>", table(["parameter", "value", "std", ""], rows)]
        out.append("<p class=small>base2sensor (p_sensor = M · p_base; mm):</p><pre>" + "\n".join(
            " ".join(f"{v:12.6f}" if abs(v) < 1e6 else f"{v:12.4e}" for v in row) for row in reg["base2sensor"]) + "</pre>")
    return out


def _tool_section(doc: dict) -> list[str]:
    tool = doc.get("tool") or {}
    out = ["<h2>Tool markers (flange frame, mm)</h2>"]
    if not tool.get("markers"):
        out.append("<p>The model's marker positions were taken as exact (--tool-prior-mm 0).</p>")
        return out
    rows = []
    for t in tool["markers"]:
        for c, axis in enumerate("xyz"):
            lo, hi = t["ci95_mm"][c]
            rows.append([f"{t['marker']}.{axis}", Html(num(t["nominal_mm"][c])), Html(num(t["value_mm"][c])),
                         Html(num(t["std_mm"][c], 2)), Html(f"[{num(lo)}, {num(hi)}]")])
    out.append(table(["coordinate", "model", "fitted", "std", "95 % interval"], rows))
    out.append(f"<p class=small>Fitted under a prior of ±{num(tool['prior_mm'], 3)} mm per coordinate about the "
               "model's values; the corrected model carries the fitted positions.</p>")
    if tool.get("degeneracies"):
        out.append("<p class=small>Decided by the priors, not by the data:</p><ul class=small>"
                   + "".join(f"<li>{esc(d)}</li>" for d in tool["degeneracies"]) + "</ul>")
    return out


def _metrics_section(doc: dict) -> list[str]:
    metrics = doc.get("metrics") or {}
    if not metrics:
        return []
    rows, groups = [], []
    for key, title in METRIC_TITLES.items():
        if isinstance(metrics.get(key), dict) and "before" in metrics[key]:
            for when in ("before", "after"):
                m = metrics[key][when]
                mean = num(m["mean"]) + (f" <span class=small>±{num(m['mc_se'], 1)}</span>" if m.get("mc_se") is not None else "")
                rows.append([when, Html(mean), *(Html(num(m[f])) for f in ("p2_5", "p97_5", "max")), m["count"]])
                groups.append(title if when == "before" else None)
    out = ["<h2 id=accuracy>Accuracy before and after (mm)</h2>",
           table(["", "mean", "2.5 %", "97.5 %", "max", "n"], rows, groups=groups)]
    settings = metrics.get("settings") or {}
    if "draws_workspace" in settings:
        target = settings.get("mc_se_target_mm")
        out.append(
            "<p class=small>The theoretical rows are Monte-Carlo estimates; ±: the standard error of their mean "
            f"(posterior draws; over the workspace also its {settings['n_random_configurations']} random configurations). "
            f"Draws per configuration: {settings['draws_measured']} at the measured configurations, "
            f"{settings['draws_workspace']} over the workspace"
            + (f", added until the draws' share of each standard error was at most {num(target, 1)} mm" if target else "")
            + ". The 2.5 / 97.5 % points vary 2–4 times as much as the means; the max is the largest of n values "
            "and grows with n.</p>")
    share = metrics.get("offsets_share")
    if share:
        out.append(f"<p>Share of the workspace error explained by the offsets alone (Table VII ÷ Table VI): "
                   f"before {num(share['before'], 3)}, after {num(share['after'], 3)}.</p>")
    if metrics.get("notes"):
        out.append("<ul class=small>" + "".join(f"<li>{esc(n)}</li>" for n in metrics["notes"]) + "</ul>")
    return out


def _direction_rows(idt: dict, only_weak: bool) -> tuple[list[list], int]:
    """Rows (weakest first) of the directions of one analysis; and how many were left out."""
    dirs = idt.get("directions") or []
    rows, hidden = [], 0
    for k in reversed(range(len(dirs))):
        c = dirs[k]
        verdict = c.get("verdict", "exact null" if c.get("exact") else "")
        if only_weak and verdict == "determined":
            hidden += 1
            continue
        rows.append([
            Html(f"<span class={VERDICT_CLASS.get(verdict, '')}>{esc(verdict)}</span>"),
            c["combination"],
            Html("∞" if c.get("exact") else num(c.get("std_mm"), 3)),
            Html(num(c.get("condition"), 3)),
            Html(num(c["singular_value_mm"], 3)),
        ])
    return rows, hidden


def _condition_text(idt: dict) -> str:
    """"∞ (… exact null directions); …" or the condition number, in words that match the verdicts."""
    dirs = idt.get("directions") or []
    exact = [c for c in dirs if c.get("exact")]
    cond = idt.get("condition_number")
    if not exact:
        return "∞" if cond is None or not math.isfinite(cond) else num(cond, 3)
    rest = [c["singular_value_mm"] for c in dirs if not c.get("exact")]
    text = f"∞ ({len(exact)} exact null direction{'s' if len(exact) > 1 else ''})"
    if len(rest) > 1:
        text += f"; {num(rest[0] / rest[-1], 3)} without {'them' if len(exact) > 1 else 'it'}"
    return text


def _identifiability_section(doc: dict) -> list[str]:
    ident = doc["identifiability"]
    out = ["<h2 id=identifiability>Identifiability</h2>"]
    est = ident.get("estimate", {})
    sigma, limit = est.get("sigma_mm"), est.get("undetermined_limit_mm")
    lever = doc.get("diagnostics", {}).get("lever_arm_mm")
    out.append(
        "<p class=small>Each row is a <i>direction</i> in parameter space: the combination of parameters the data "
        "see together (largest weights of the right singular vector; angles scaled by the lever arm "
        f"L = {num(lever)} mm so every weight is in mm of marker motion). s: its singular value; "
        "s<sub>max</sub>/s: its condition number; std = σ/s: how well the data determine it, in mm "
        f"(σ = {num(sigma, 3)} mm). <b>not determined</b>: an exact null direction (s at rounding level, "
        f"s ≤ s<sub>max</sub>·max(rows, columns)·ε·10) or std above {num(limit, 3)} mm (the fit's "
        f"limit for an offset, times L); <b>weakly determined</b>: std above {WEAK_NOISE_FACTOR:g}·σ.</p>")
    for label in ("start", "estimate"):
        idt = ident.get(label)
        if not idt:
            continue
        n = len(idt["parameters"])
        rows, hidden = _direction_rows(idt, only_weak=True)
        cond_text = _condition_text(idt)
        where = "at the start (nominal model, before anything is fixed)" if label == "start" else "at the estimate (what was sampled)"
        out.append(f"<h3>{where}</h3><p>{n} parameters, numerical rank {idt['rank']}; condition number {cond_text}.</p>")
        if not idt.get("directions"):  # a result.json from before directions were written
            out.append(table(["undetermined combination", "singular value"],
                             [[c["combination"], Html(num(c["singular_value_mm"], 3))] for c in idt["undetermined_combinations"]]))
            continue
        header = ["verdict", "combination (weights)", "std (mm)", "s_max/s", "s"]
        if rows:
            out.append(table(header, rows, left=2))
        if hidden:
            out.append(f"<p>{hidden} {'other ' if rows else ''}direction{'s' if hidden != 1 else ''}: determined.</p>")
        every, _ = _direction_rows(idt, only_weak=False)
        out.append(f"<details class={label}><summary>all {len(every)} directions {where.split(' (')[0]}, weakest first</summary>"
                   f"{table(header, every, left=2)}</details>")
    if ident.get("fixed_parameters"):
        out.append("<h3>fixed before sampling</h3>")
        out.append(table(["parameter", "reason"], [[f["parameter"], f["reason"]] for f in ident["fixed_parameters"]], left=2))
    return out


def _diagnostics_section(doc: dict) -> list[str]:
    d = doc["diagnostics"]
    out = ["<h2>Sampler diagnostics</h2>", (
        f"<p>sampler {esc(d.get('sampler'))}, {d.get('n_chains')} chain(s) × {d.get('n_draws')} draws, "
        f"acceptance {', '.join(num(a, 2) for a in d.get('acceptance', []))}, "
        f"R-hat max {num(d.get('rhat_max'), 4)}, ESS min {num(d.get('ess_min'), 3)}, "
        f"time {num(d.get('seconds_total'), 3)} s</p>")]
    if "rhat" in d or "ess" in d:
        names = list((d.get("rhat") or d.get("ess")).keys())
        out.append(f"<details><summary>R-hat and ESS of each of the {len(names)} sampled parameters</summary>")
        out.append(table(["parameter", "R-hat", "ESS"],
                         [[n, Html(num((d.get("rhat") or {}).get(n), 4)), Html(num((d.get("ess") or {}).get(n), 3))] for n in names]))
        out.append("</details>")
    return out


def _figures_section(result: FitResult, data: Dataset) -> list[str]:
    from calib.report.report_figures import error_figure, offset_trace_figure, tcp_cloud_figure, tcp_clouds

    clouds = tcp_clouds(result, data)
    out = [
        "<h2 id=tcp>TCP cloud (the paper's Fig. 5)</h2><figure>", tcp_cloud_figure(clouds),
        f"<figcaption>TCP (flange origin, robot base x–y, relative to the TCP after) at {len(clouds.rows)} measured "
        f"configurations — the smallest, middle and largest before→after move: with the nominal offsets (red, "
        f"before), the applied offsets (green, after), {clouds.draws.shape[1]} posterior draws of the offsets "
        f"(yellow) and those draws plus the isotropic error σ = {num(clouds.sigma_mm, 3)} mm of the corrected robot "
        "(blue; the σ of the theoretical metrics). Top: at the scale of the move; bottom: the offset draws alone, "
        "zoomed. A yellow cloud much smaller than the blue one means the offsets are no longer the main error."
        "</figcaption></figure>",
        "<h2>Plots</h2>",
    ]
    trace = offset_trace_figure(result)
    if trace:
        out.append(trace)
    out.append(error_figure(result, data))
    return out


def render_report(result: FitResult, data: Dataset, doc: dict, controller_text: str = "") -> str:
    """The report as one HTML string. ``doc`` is the ``result.json`` document (``calib.fit.result``);
    ``controller_text`` is shown only when ``doc`` has no ``controller`` entry."""
    name = esc(doc["robot"]["name"])
    parts = [
        "<!DOCTYPE html><html lang=en><head><meta charset='utf-8'>",
        "<meta name=viewport content='width=device-width, initial-scale=1'>",
        f"<title>remaster fit — {name}</title><style>{CSS}</style></head><body>",
        f"<h1>Remastering fit: {name}</h1>",
        f"<p class=small>data: <code class=wrap>{esc(doc['data']['source'] or '(in memory)')}</code> — {doc['data']['n_measurements']} "
        f"measurements, {doc['data']['n_configurations']} configurations, sensors {esc(', '.join(doc['data']['sensors']))}; "
        f"method {esc(doc['diagnostics'].get('method'))}</p>",
        summary_html(doc),
    ]
    parts += _controller_section(doc, controller_text)
    parts += _offsets_section(doc)
    parts += _tool_section(doc)
    parts += _registration_section(doc)
    parts += _metrics_section(doc)
    parts += compliance_section(doc.get("diagnostics", {}).get("compliance"))
    parts += _identifiability_section(doc)
    parts += _diagnostics_section(doc)
    parts += _figures_section(result, data)
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(path: str | Path, result: FitResult, data: Dataset, doc: dict, controller_text: str = "") -> Path:
    """Write the self-contained HTML report; returns the path."""
    path = Path(path)
    path.write_text(render_report(result, data, doc, controller_text), encoding="utf-8")
    return path
