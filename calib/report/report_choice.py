"""The model-choice section of the reports: every candidate model's cross-validated held-out error
(``doc["model_choice"]``: ``calib.fit.model_choice`` for tracker/mocap data, ``calib.fit.socket_choice``
for socket data), the chosen one, the rule, and the link prior scales the evidence chose."""

from __future__ import annotations

from calib.report.report_format import esc
from calib.report.report_summary import link_scale_lines, model_choice_table


def model_choice_section(doc: dict) -> list[str]:
    """HTML of the section, [] when ``doc`` has no model choice (a forced method)."""
    mc = doc.get("model_choice")
    if not mc:
        return []
    out = ["<h2 id=model-choice>Model choice</h2>", model_choice_table(doc),
           f"<p class=small>chosen: <b>{esc(mc['chosen'])}</b>{' (forced by --model)' if mc.get('forced') else ''} — "
           f"{esc(mc['rule'])}. Each model is fitted without the held-out {esc(mc['grouped_by'])}s and scored on them "
           "(never re-fitted on the scored points).</p>"]
    out += [f"<p class=small>{esc(line)}</p>" for line in link_scale_lines(mc)]
    if (doc.get("interval_scale") or {}).get("why"):  # calib.fit.heldout_misfit
        out.append(f"<p class=small>{esc(doc['interval_scale']['why'])}</p>")
    if mc.get("excluded"):
        out.append(f"<p class=small>not compared: {esc(mc['excluded'])}</p>")
    return out
