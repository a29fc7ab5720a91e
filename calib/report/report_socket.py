"""``report.html`` of a socket (sensorless) fit, from its ``result.json`` document alone.

The document is ``acquire.run.socket_fit.socket_result_dict``'s (``kind: socket``): so the
report and the file always agree. Sections, in the tracker report's style
(``calib.report.report_format``, figures with ``calib.report.svg``): a summary (the verdict —
enter / do not enter with the reasons —, which method and model of the arm ran, the values per
axis, the ball and its play); the model choice (every candidate's held-out error,
``calib.report.report_choice``) with a figure of the candidates' held-out mean ± standard error;
the zero-offsets with their 95 % intervals; the ball on the flange and the socket points; the
fitted link parameters; the joint compliances; what socket data cannot determine; each placement
held out (fitted on the others, scored on it) before → after, and a figure per held-out placement
of every configuration's distance from its socket (mm).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calib.report.report_choice import model_choice_section
from calib.report.report_compliance import compliance_section
from calib.report.report_figures import error_scatter, side_by_side
from calib.report.report_format import CSS, Html, esc, fixed, num, table
from calib.report.svg import COLOURS, Figure, data_limits, log_ticks

STATUS_CLASS = {"fitted": "good", "do not enter": "warn", "undetermined": "warn"}


def verdict(doc: dict) -> tuple[str, list[str]]:
    """("enter", []) when the document marks at least one offset to enter, else ("do not enter",
    the reasons): the document's own reason, or that no offset is determined."""
    entered = [j for j in doc["joint_offsets"] if j["status"] == "fitted"]
    if not doc.get("trusted"):
        return "do not enter", [doc.get("do_not_enter_reason") or "the fit is not trusted"]
    if not entered:
        return "do not enter", ["no offset is determined well enough by these data"]
    return "enter", []


def _method_line(doc: dict) -> str:
    fm = doc.get("fit_model") or {}
    model = f" — model <b>{esc(fm['model'])}</b>" if fm.get("model") else ""
    return (f"<p>method <b>{esc(fm.get('method', doc.get('method')))}</b>{model} — fitted model: "
            f"{esc(fm.get('description', ''))}</p>")


def _offsets_rows(doc: dict, *, with_ci: bool) -> tuple[list[list], list[str | None]]:
    rows, notes = [], []
    for j in doc["joint_offsets"]:
        cls = STATUS_CLASS.get(j["status"], "")
        action = "enter" if j["status"] == "fitted" else ("leave unchanged" if j["status"] == "undetermined" else "do not enter")
        if j["value_deg"] is None:
            row = [j["joint"], "—", "—"] + (["—"] if with_ci else [])
        else:
            ci = j["ci95_deg"]
            row = [j["joint"], Html(fixed(j["value_deg"], 4, sign=True)), Html(fixed(j["std_deg"], 4))]
            if with_ci:
                row.append(Html(f"[{fixed(ci[0], 4, sign=True)}, {fixed(ci[1], 4, sign=True)}]"))
        rows.append(row + [Html(f"<span class={cls}>{esc(action)}</span>")])
        notes.append(j.get("reason") or None)
    return rows, notes


def _summary(doc: dict) -> list[str]:
    what, reasons = verdict(doc)
    if what == "enter":
        n = sum(j["status"] == "fitted" for j in doc["joint_offsets"])
        cls, banner = "ok", (f"<span class=good>Enter the offsets of {n} ax{'is' if n == 1 else 'es'} below</span> "
                             "(the others: leave unchanged).")
    else:
        cls, banner = "stop", "<span class=bad>DO NOT ENTER these offsets.</span>"
    out = [f"<section class='summary {cls}' id=summary><h2>Summary</h2><p class=banner>{banner}</p>"]
    if reasons:
        out.append("<ul class=bad>" + "".join(f"<li>{esc(r)}</li>" for r in reasons) + "</ul>")
    out.append(_method_line(doc))
    out.append("<div class=cols><div>")
    out.append("<p class=small>zero-offsets δ, degrees (true axis angle = reported angle + δ; enter −δ as the "
               "correction in the controller's convention):</p>")
    rows, notes = _offsets_rows(doc, with_ci=False)
    out.append(table(["axis", "δ (°)", "std (°)", "action"], rows, notes=notes))
    out.append("</div><div>")
    b = doc["ball_mm"]
    out.append(table(["", "value"], [
        ["ball on the flange (mm)", Html(", ".join(f"{fixed(v, 3)} <span class='small nw'>± {fixed(s, 3)}</span>"
                                                   for v, s in zip(b["value"], b["std"])))],
        ["ball's play in the sockets σ (mm)", Html(fixed(doc["sigma_point_mm"], 4))],
        ["rms of the fit's residuals (mm)", Html(fixed(doc["rms_mm"], 4))],
        ["configurations", doc["data"]["n_configurations"]],
        ["placement/socket groups", len(doc["data"]["groups"])],
    ]))
    held = doc["scores"]["held_out"]
    if held:
        out.append(table(["held-out placement", "spread before → after (mm)", "distance error before → after (mm)"], [
            [h["placement"], Html(f"{fixed(h['before']['spread_mm'], 3)} → <b>{fixed(h['after']['spread_mm'], 3)}</b>"),
             Html(f"{_mm(h['before']['distance_error_mm'])} → <b>{_mm(h['after']['distance_error_mm'])}</b>")]
            for h in held]))
    out.append("</div></div>")
    warn = doc.get("warnings") or []
    if warn:
        out.append("<p><b>Warnings</b></p><ul class=warn>" + "".join(f"<li>{esc(w)}</li>" for w in warn) + "</ul>")
    else:
        out.append("<p class=good>No warnings.</p>")
    out.append("</section>")
    return out


def _mm(v) -> str:
    return "—" if v is None or not math.isfinite(float(v)) else fixed(v, 3)


def candidates_figure(mc: dict) -> str | None:
    """Held-out mean ± standard error (mm) of the data sheet and every scored candidate, one row each
    (the chosen one green), on a logarithmic error axis (a misfit candidate can be 100× the others);
    None when nothing was scored. Each row is a ``line`` (mean − se … mean + se, log10 mm) with a
    ``marker`` at the mean, in the order of the table."""
    rows = [c for c in [mc["nominal"]] + mc["candidates"] if not c.get("failed") and c.get("cv_mean_mm") is not None]
    if not rows:
        return None
    means = np.array([c["cv_mean_mm"] for c in rows])
    se = np.array([c.get("cv_se_mm") or 0.0 for c in rows])
    lo, hi = np.maximum(means - se, means / 3.0), means + se  # a bar reaching 0 has no end on a log axis
    span = data_limits(np.concatenate([lo, hi]), 0.08, log=True)
    row_h = 26
    fig = Figure(660, 64 + row_h * len(rows))
    box = (270, 12, 370, row_h * len(rows))
    ax = fig.axes(box, (math.log10(span[0]), math.log10(span[1])), (0, len(rows)))
    decades = log_ticks(*span)
    for t in decades:  # the error axis in mm: grid and labels at 1, 2, 5 × 10^k (or decades)
        X = float(ax.px(math.log10(t), 0)[0])
        ax.parts.append(f'<path class="grid" stroke="#ddd" stroke-width="0.6" d="M{X:.1f} {box[1]:.1f}v{box[3]:.1f}"/>')
        fig.text(X, box[1] + box[3] + 16, f"{t:g}", size=10)
    for k, c in enumerate(rows):
        y = len(rows) - k - 0.5
        colour = COLOURS["green"] if c["model"] == mc["chosen"] else (COLOURS["red"] if k == 0 else COLOURS["blue"])
        ax.line(np.log10([lo[k], hi[k]]), [y, y], color=colour, width=2)
        ax.marker(math.log10(means[k]), y, color=colour, size=7)
        name = "data sheet (nominal)" if k == 0 else c["model"]
        fig.text(box[0] - 6, box[1] + row_h * (k + 0.5) + 4, name + (" ←" if c["model"] == mc["chosen"] else ""),
                 anchor="end", size=10)
    ax.frame(xlabel="held-out error, mean ± se (mm, log scale)", xticks=False, yticks=False)
    ax.decor = [d for d in ax.decor if 'class="ticks"' not in d]  # the frame's ticks are at log10 values: labels above
    return fig.svg("held-out error of every candidate model and of the data sheet, mean ± standard error")


def _model_choice(doc: dict) -> list[str]:
    out = model_choice_section(doc)
    if out:
        fig = candidates_figure(doc["model_choice"])
        if fig:
            out += ["<figure>", fig, "<figcaption>Each candidate's held-out error (mean ± standard error from the "
                    "per-socket means; red: the data sheet with the ball from the training data, green: the chosen "
                    "model). The simplest model within one standard error of the best is chosen.</figcaption></figure>"]
    return out


def _offsets_section(doc: dict) -> list[str]:
    rows, notes = _offsets_rows(doc, with_ci=True)
    return ["<h2 id=offsets>Zero-offsets</h2>", table(["joint", "value (°)", "std (°)", "95 % interval (°)", "action"],
                                                      rows, notes=notes),
            "<p class=small>Values wrapped to (−180°, 180°]. Intervals from the Laplace approximation at the mode "
            "(±1.96 std). An offset is entered only when the chosen model earned it (see the summary's reasons) "
            "and its interval is narrow enough.</p>"]


def _ball_section(doc: dict) -> list[str]:
    b = doc["ball_mm"]
    rows = [[axis, Html(fixed(v, 4)), Html(fixed(s, 4))] for axis, v, s in zip("xyz", b["value"], b["std"])]
    out = ["<h2 id=ball>Ball on the flange and socket points</h2>", table(["ball (flange frame)", "mm", "std (mm)"], rows),
           f"<p>play of the ball in the sockets: σ = <b>{fixed(doc['sigma_point_mm'], 4)} mm</b> per coordinate; "
           f"rms residual {fixed(doc['rms_mm'], 4)} mm.</p>"]
    pts = [[f"{p['placement']}/{p['socket']}", *(Html(fixed(v, 3)) for v in p["value"]),
            Html(", ".join(fixed(s, 3) for s in p["std"]))] for p in doc["socket_points_mm"]]
    n = {f"{g['placement']}/{g['socket']}": g["n"] for g in doc["data"]["groups"]}
    for r in pts:
        r.insert(1, n.get(r[0], "—"))
    out.append(table(["socket", "configurations", "x (mm)", "y (mm)", "z (mm)", "std x, y, z (mm)"], pts))
    dist = doc["data"].get("distances_mm") or []
    out.append("<p class=small>socket points in the robot base frame; "
               + (f"known distances between sockets: {', '.join(sorted({fixed(d['mm'], 3) for d in dist}))} mm.</p>"
                  if dist else "no distance between sockets given: the scale is not determined.</p>"))
    return out


def _parameters_section(doc: dict) -> list[str]:
    params = doc.get("parameters") or []
    links = [p for p in params if p.get("nominal") is not None and not p["name"].endswith(".offset")]
    if not links:
        return []
    rows = [[p["name"], p["unit"], Html(fixed(p["nominal"], 4)), Html(fixed(p["value"], 4)),
             Html(num(p["value"] - p["nominal"], 3, sign=True)), Html(num(p["std"], 2))] for p in links]
    return ["<h2 id=links>Link parameters fitted</h2>",
            table(["parameter", "unit", "data sheet", "fitted", "change", "std"], rows),
            "<p class=small>The corrected model file carries them; entering only the offsets on the controller "
            "corrects the axis zeros.</p>"]


def _identifiability_section(doc: dict) -> list[str]:
    ident = doc.get("identifiability") or {}
    out = ["<h2 id=identifiability>What socket data cannot determine</h2>",
           f"<p>condition number (columns scaled to mm of ball motion): {num(ident.get('condition_number'), 3)}</p>"]
    ex = ident.get("excluded") or {}
    if ex:
        out.append(table(["parameter (kept nominal)", "why"], [[k, v] for k, v in ex.items()], left=2))
    if ident.get("weak"):
        out.append("<p class=small>weakly determined:</p><ul class=small>"
                   + "".join(f"<li>{esc(w)}</li>" for w in ident["weak"]) + "</ul>")
    return out


def held_out_figure(held: list[dict]) -> str | None:
    """Per held-out placement, every configuration's distance from its socket's mean prediction (mm)
    before (data sheet) and after (the fit on the other placements), log scale; None without them."""
    panels = []
    for h in held:
        cfg = h.get("configurations") or []
        if not cfg:
            continue
        before = np.array([c["before_mm"] for c in cfg])
        after = np.array([c["after_mm"] for c in cfg])
        panels.append(error_scatter(np.arange(1, len(cfg) + 1, dtype=float), before, after,
                                    xlabel=f"held-out configuration of {h['placement']}",
                                    ylabel="distance from its socket (mm)",
                                    labels=("before (data sheet)", "after (fit on the others)"),
                                    alt=f"held-out placement {h['placement']}: distance of each configuration's "
                                        "predicted ball from its socket, before and after", width=360, logy=True))
    return side_by_side(panels) if panels else None


def _held_out_section(doc: dict) -> list[str]:
    held = doc["scores"]["held_out"]
    out = ["<h2 id=held-out>Held-out placements</h2>"]
    if not held:
        out.append("<p>Fewer than three placements: no placement is held out here (the model choice above scores "
                   "held-out data).</p>")
        return out
    rows = []
    for h in held:
        rows.append([h["placement"], len(h.get("configurations") or []) or "—",
                     Html(fixed(h["before"]["spread_mm"], 4)), Html(f"<b>{fixed(h['after']['spread_mm'], 4)}</b>"),
                     Html(_mm(h["before"]["distance_error_mm"])), Html(f"<b>{_mm(h['after']['distance_error_mm'])}</b>")])
    out.append(table(["placement", "configurations", "spread before (mm)", "spread after (mm)",
                      "distance error before (mm)", "after (mm)"], rows))
    out += [f"<p class=small>{esc(n)}</p>" for n in doc["scores"].get("notes", [])]
    fig = held_out_figure(held)
    if fig:
        out += ["<figure>", fig, "<figcaption>Each held-out configuration's predicted ball centre from its socket (the "
                "mean of that socket's predictions), with the data sheet (red) and with the model fitted on the other "
                "placements (green). The rms of each colour is the spread in the table.</figcaption></figure>"]
    return out


def render_socket_report(doc: dict) -> str:
    """The report as one HTML string; ``doc``: a socket fit's ``result.json`` document."""
    if doc.get("kind") != "socket":
        raise ValueError(f"not a socket fit's result (kind {doc.get('kind')!r}): use calib.report.html for sensor data")
    name = esc(doc["robot"]["name"])
    data = doc["data"]
    parts = [
        "<!DOCTYPE html><html lang=en><head><meta charset='utf-8'>",
        "<meta name=viewport content='width=device-width, initial-scale=1'>",
        f"<title>remaster socket fit — {name}</title><style>{CSS}</style></head><body>",
        f"<h1>Socket calibration: {name}</h1>",
        f"<p class=small>data: <code class=wrap>{esc(data['source'] or '(in memory)')}</code> — {data['n_configurations']} "
        f"configurations in {len(data['groups'])} placement/socket groups; method {esc(doc.get('method'))}</p>",
    ]
    parts += _summary(doc)
    parts += _model_choice(doc)
    parts += _offsets_section(doc)
    parts += _ball_section(doc)
    parts += _parameters_section(doc)
    parts += compliance_section(doc.get("compliance"))
    parts += _identifiability_section(doc)
    parts += _held_out_section(doc)
    parts.append("</body></html>")
    return "\n".join(parts)


def write_socket_report(path: str | Path, doc: dict) -> Path:
    """Write the self-contained socket report; returns the path."""
    path = Path(path)
    path.write_text(render_socket_report(doc), encoding="utf-8")
    return path
