"""``report.html`` of a full identification (``acquire fit --method full --report``).

Built from the ``result.json`` document of ``calib.fit.identification.ident_result_dict`` with the
fast report's building blocks (``calib.report.report_format``, ``calib.report.report_figures``): the outcome and
its warnings (starts that disagree, conditioning), the model choice when the default chose full
identification (``calib.report.report_choice``: every candidate's held-out error), every start of the solve, the identified
parameters with their change and std, the tool markers, what was kept nominal and why, the
accuracy before and after (validation scored with the calibration registration, the
re-registered figure beside it and named as such), and the error per measurement.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.measure.dataset import Dataset
from calib.fit.identification import IdentResult, pose_errors
from calib.report.report_choice import model_choice_section
from calib.report.report_compliance import compliance_section
from calib.report.report_format import CSS, Html, esc, num, table
from calib.report.report_summary import entered_section


def _outcome(doc: dict) -> list[str]:
    warn = doc.get("warnings") or []
    stop = doc.get("do_not_use") or []
    cls = "summary stop" if warn or stop else "summary ok"
    out = [f"<div class='{cls}'><h2 id=summary>Outcome</h2>",
           *(f"<p class='banner bad'>Do not use this model: {esc(r)}</p>" for r in stop),
           f"<p class=banner>{sum(p['identified'] for p in doc['parameters'])} parameters identified; rms residual "
           f"{num(doc['rms_mm'])} mm; scaled condition number {num(doc['condition_number'], 3)}</p>"]
    out += [f"<p class=small>{esc(c)}</p>" for c in doc.get("canonical") or []]
    if warn:
        out.append("<ul>" + "".join(f"<li class=warn>{esc(w)}</li>" for w in warn) + "</ul>")
    else:
        out.append("<p class=good>No warnings: every start of the solve ended in the same minimum.</p>")
    out.append("</div>")
    return out


def _starts(doc: dict) -> list[str]:
    starts = doc.get("starts") or []
    if not starts:
        return []
    best = starts[0]["cost"]
    rows = [[s["label"], Html(num(s["cost"])), Html(num(s["cost"] / best if best > 0 else 1.0, 4)), Html(num(s["rms_mm"])),
             s["evaluations"], "yes" if s["same_minimum"] else Html("<span class=warn>no</span>")] for s in starts]
    return ["<h2>Starts of the solve</h2>",
            table(["start", "cost (mm²)", "÷ best", "rms (mm)", "evaluations", "best minimum"], rows),
            "<p class=small>staged: registration, marker positions and joint offsets first, then every identifiable "
            "parameter; plain: every parameter at once from the nominal model; random: staged from a start drawn about "
            "nominal (seeded); \"J<i> zero +180°\": nominal with that joint's zero turned half a turn and the registration "
            "re-fitted, solved only when its first stage beat nominal's. Cost: ½·Σ r² over the residuals and the tool "
            "prior's rows.</p>"]


def _parameters(doc: dict) -> list[str]:
    rows = [[p["name"], p["unit"], Html(num(p["nominal"])), Html(num(p["value"])), Html(num(p["change"], 3, sign=True)),
             Html(num(p["std"], 2))] for p in doc["parameters"] if p["identified"]]
    kept = [[name, reason] for name, reason in doc["excluded"].items()]
    return ["<h2>Identified parameters</h2>", table(["parameter", "unit", "nominal", "identified", "change", "std"], rows),
            f"<h2>Kept nominal ({len(kept)})</h2>", table(["parameter", "why"], kept, left=2)]


def _accuracy(doc: dict) -> list[str]:
    rows, groups = [], []
    titles = {"calibration": "Calibration set", "validation": "Validation set, with the calibration registration",
              "validation_unseen_markers": "Validation points of markers the calibration never measured (placement "
                                           "estimated, not the headline), with the calibration registration"}
    for part, m in doc["metrics"].items():
        blocks = [(titles.get(part, part), m)]
        if "reregistered" in m:
            blocks.append((f"{titles.get(part, part).split(',')[0]}, re-registered on its own points (optimistic)", m["reregistered"]))
        if m.get("placement"):
            groups_note = "; ".join(f"{k}: ±{num(v['uncertainty_mm'], 2)} mm" for k, v in m["placement"].items()
                                    if v.get("uncertainty_mm") is not None)
            if groups_note:
                blocks[0] = (f"{blocks[0][0]} — estimated placement uncertainty {groups_note}", m)
        for title, b in blocks:
            for when in ("before", "after"):
                att = [Html(num(b[when].get(k), 4)) if b[when].get(k) is not None else "—" for k in ("EACAE", "EMCAE")]
                rows.append([when, Html(num(b[when]["EACPE"])), Html(num(b[when]["EMCPE"])), *att])
                groups.append(title if when == "before" else None)
    heads = ["", "EACPE (mean, mm)", "EMCPE (max, mm)", "EACAE (mean, °)", "EMCAE (max, °)"]
    if not any(r[3] != "—" for r in rows):  # positions only: no attitude columns
        rows, heads = [r[:3] for r in rows], heads[:3]
    out = ["<h2 id=accuracy>Accuracy before and after</h2>", table(heads, rows, groups=groups)]
    notes = doc.get("metric_notes") or []
    if notes:
        out.append("<ul class=small>" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>")
    return out


def _error_figure(result: IdentResult, cal: Dataset) -> list[str]:
    from calib.robot.kinematics import Chain
    from calib.fit.metrics import registrations
    from calib.report.report_figures import error_scatter

    chain = Chain(result.model)
    idx = np.array([chain.marker_names.index(m) for m in cal.marker])
    nominal = chain.marker_positions(cal.q_rad)[np.arange(len(cal)), idx]
    before = pose_errors(result.model, chain.nominal, cal, registrations(cal, nominal))
    after = pose_errors(result.model, result.params, cal, result.base2sensor)
    figure = error_scatter(np.arange(len(cal), dtype=float), before, after, xlabel="measurement (row)",
                           ylabel="position error (mm)", width=760, logy=True,
                           labels=("before (nominal, least-squares registration)", "after (identified, its registration)"),
                           alt="position error per calibration measurement, before and after")
    return ["<h2>Error per measurement</h2>", figure]


def render_ident_report(result: IdentResult, cal: Dataset, doc: dict) -> str:
    """The report as one HTML string; ``doc`` is ``ident_result_dict(result, cal, val)``."""
    name = esc(doc["robot"])
    parts = ["<!DOCTYPE html><html lang=en><head><meta charset='utf-8'>",
             "<meta name=viewport content='width=device-width, initial-scale=1'>",
             f"<title>remaster identification — {name}</title><style>{CSS}</style></head><body>",
             f"<h1>Full identification: {name}</h1>",
             f"<p class=small>{len(cal)} calibration measurements; tool prior ±{num(doc['tool_prior_mm'], 3)} mm per "
             f"coordinate; {doc['evaluations']} evaluations</p>"]
    parts += _outcome(doc) + entered_section(doc) + model_choice_section(doc) + _starts(doc) + _parameters(doc) + compliance_section(doc.get("compliance"))
    parts += _accuracy(doc) + _error_figure(result, cal)
    parts.append("</body></html>")
    return "\n".join(parts)


def write_ident_report(path: str | Path, result: IdentResult, cal: Dataset, doc: dict) -> Path:
    path = Path(path)
    path.write_text(render_ident_report(result, cal, doc), encoding="utf-8")
    return path
