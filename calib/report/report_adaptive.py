"""The report's "Adaptive run" section (issue 27): why the run stopped, the predicted intervals
and errors against the number of configurations measured, and the cell time against the full
plan's. Input: ``result.json``'s ``adaptive`` entry (``acquire.run.adaptive.AdaptiveRun.summary``)."""

from __future__ import annotations

from calib.report.report_format import esc, fixed, table


def adaptive_section(ad: dict | None) -> list[str]:
    """HTML lines of the section; empty without an adaptive run."""
    if not ad:
        return []
    out = ["<h2 id=adaptive>Adaptive run</h2>",
           f"<p>Measured <b>{ad['measured']}</b> of the plan's {ad['candidates']} configurations, each chosen by "
           f"its expected gain per second of motion. Stopped: {esc(ad['reason'])}.</p>"]
    if ad.get("saved_seconds") is not None:
        out.append(f"<p>Estimated cell time {ad['estimated_seconds']:.0f} s against {ad['full_plan_seconds']:.0f} s for "
                   f"the full plan in its minimum-time order: <b>{ad['saved_seconds']:.0f} s "
                   f"({ad.get('saved_pct') or 0:.0f} %) saved</b>.</p>")
    hist = ad.get("history") or []
    if hist:
        rows = [[h["n"], fixed(h["max_half_width_deg"], 4), fixed(h["workspace_mm"], 4),
                 fixed(h.get("held_out_mm"), 4), fixed(h["sigma_mm"], 4)] for h in hist]
        out.append(table(["configurations", "largest 95 % half-width (°)", "predicted workspace error (mm)",
                          "predicted held-out error (mm)", "σ used (mm)"], rows, left=0))
        last = hist[-1]
        out.append(f"<p class=small>Predicted by the fit's model linearised at the nominal robot, with σ the larger "
                   f"of the plan's noise and the fitted one. The full plan would reach "
                   f"{fixed(last['full_workspace_mm'], 4)} mm (workspace) and {fixed(last.get('full_held_out_mm'), 4)} mm "
                   "(held-out).</p>")
    return out
