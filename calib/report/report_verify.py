"""``verify.html``: a verification run's page, from its ``verify.json`` document alone.

A summary box (the verdict; the measured improvement against the predicted one and its interval);
a table of the robot before (the calibration's held-out score, and the robot as found replayed at
the fresh configurations) and after, with the prediction beside; the values the result entered;
a figure of every fresh configuration's held-out error, as found (replayed) and now. The document
is ``calib.fit.verification.verify_entry``'s, with the run's paths added by ``acquire verify``.
"""

from __future__ import annotations

import numpy as np

from calib.fit.verification import summary_lines
from calib.report.report_figures import error_scatter
from calib.report.report_format import CSS, esc, fixed, table

VERDICT_CLASS = {"as predicted": "ok", "better than predicted": "ok", "worse than predicted": "stop",
                 "no prediction": ""}


def _row(name: str, score: dict | None, where: str) -> list:
    if not score:
        return [name, "—", "—", "—", "—", where]
    return [name, fixed(score["mean_mm"], 3), fixed(score["rms_mm"], 3), fixed(score["max_mm"], 3), score["n"], where]


def render_verify_report(doc: dict) -> str:
    """The page (HTML text) of a verification document."""
    verdict = doc["verdict"]
    m = doc["measured"]["improvement_mm"]
    p = doc.get("predicted")
    banner = f"Verification: {verdict}"
    parts = ["<!DOCTYPE html><html lang=en><head><meta charset='utf-8'>",
             "<meta name=viewport content='width=device-width, initial-scale=1'>",
             f"<title>{esc(banner)}</title><style>{CSS}</style></head><body>",
             f"<h1>{esc(banner)}</h1>",
             f"<div class='summary {VERDICT_CLASS.get(verdict, '')}'><div class=banner>{esc(verdict)}</div><ul>",
             f"<li>measured improvement {fixed(m['value'], 3, sign=True)} mm "
             f"(95 % {fixed(m['ci95'][0], 3, sign=True)} … {fixed(m['ci95'][1], 3, sign=True)}), against {esc(m['against'])}</li>"]
    if p is not None:
        pi, iv = p["improvement_mm"], p["interval_for_this_run"]
        parts.append(f"<li>predicted {fixed(pi['value'], 3, sign=True)} mm (95 % {fixed(pi['ci95'][0], 3, sign=True)} … "
                     f"{fixed(pi['ci95'][1], 3, sign=True)}; for {doc['after']['n']} configurations "
                     f"{fixed(iv[0], 3, sign=True)} … {fixed(iv[1], 3, sign=True)})</li>")
    parts += [f"<li class=warn>{esc(n)}</li>" for n in doc.get("notes", [])]
    parts.append("</ul></div>")
    parts.append("<h2>Before and after</h2>")
    rows = [_row("as found, calibration", doc["before"].get("calibration"), "held out, the calibration's configurations"),
            _row("as found, replayed", doc["before"]["replayed"], "these configurations, the entered values taken off"),
            _row("now, after the entry", doc["after"], "these configurations, as the controller runs them")]
    if p is not None and p.get("after"):
        rows.append(_row("predicted after the entry", p["after"], "held out, the calibration's configurations"))
    if p is not None and p.get("full_model"):
        rows.append(_row("predicted, full model (compensation)", p["full_model"],
                         "held out, the calibration's configurations: the rest of the gain"))
    parts.append(table(["robot", "mean (mm)", "rms (mm)", "max (mm)", "configurations", "scored on"], rows, left=1))
    parts.append(f"<p class=small>{esc(doc['scored_on'])}. Errors are per configuration: the rms distance between measured "
                 "and predicted marker positions.</p>")
    parts.append("<h2>Entered on the controller</h2>")
    parts.append(table(["axis", "δ (deg)", "correction (deg)"],
                       [[a, fixed(d, 4, sign=True), fixed(-d, 4, sign=True)] for a, d in doc["entered_deg"].items()], left=1))
    pc = doc["per_configuration"]
    if len(pc["configs"]) >= 2:
        after, before = np.asarray(pc["after_mm"]), np.asarray(pc["before_replayed_mm"])
        order = np.argsort(before)
        parts.append("<h2>Every fresh configuration</h2>")
        parts.append(error_scatter(np.arange(len(order), dtype=float), before[order], after[order],
                                   xlabel="configuration (sorted by the error as found)", ylabel="held-out error (mm)",
                                   labels=("as found (replayed)", "now"), alt="held-out error per configuration"))
    parts.append("<h2>In words</h2><pre class=wrap>" + esc("\n".join(summary_lines(doc))) + "</pre>")
    src = {k: doc[k] for k in ("result", "log", "calibration_log") if doc.get(k)}
    if src:
        parts.append("<p class=small>" + "; ".join(f"{k}: {esc(v)}" for k, v in src.items()) + "</p>")
    parts.append("</body></html>")
    return "\n".join(parts)
