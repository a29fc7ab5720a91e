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
        out.append(f"<p class=small>Predicted by the fit's model linearised at the nominal robot, with σ as measured "
                   f"(the readings' spread, then the fit's σ). The full plan would reach "
                   f"{fixed(last['full_workspace_mm'], 4)} mm (workspace) and {fixed(last.get('full_held_out_mm'), 4)} mm "
                   "(held-out).</p>")
    out += decision_section(ad)
    return out


#: A criterion's unit in the tables.
UNIT = {"interval_deg": "°", "region_error_mm": "mm", "joint_space_error_mm": "mm"}


def decision_section(ad: dict) -> list[str]:
    """The stop decision and what backs it: each criterion (limit, predicted at the stop), the
    noise it was judged with, predicted against the full plan's, and what the fit found."""
    dec = ad.get("decision")
    if not dec:
        return []
    out = ["<h3>The stop decision</h3>",
           table(["criterion", "limit", "predicted at the stop", "met"],
                 [[esc(c["criterion"]), f"{c['limit']:g} {UNIT.get(c['criterion'], '%')}",
                   f"{fixed(c['predicted'], 4)} {UNIT.get(c['criterion'], '%')}", "yes" if c["met"] else "no"]
                  for c in dec["checks"]], left=1)]
    n, p, f = dec["noise"], dec["predicted"], ad.get("found") or {}
    rows = [["largest 95 % half-width (°)", fixed(p["max_half_width_deg"], 4), fixed(p["full_max_half_width_deg"], 4),
             fixed(f.get("max_half_width_deg"), 4)],
            ["model error, plan's region (mm)", fixed(p["region_mm"], 4), fixed(p["full_region_mm"], 4), ""],
            ["model error, working joint space (mm)", fixed(p["joint_space_mm"], 4), fixed(p["full_joint_space_mm"], 4), ""],
            ["held-out error (mm)", fixed(p["held_out_mm"], 4), fixed(p["full_held_out_mm"], 4), ""],
            ["σ per configuration (mm)", fixed(n["used_mm"], 4), "", fixed(f.get("sigma_mm"), 4)],
            ["misfit (mm)", fixed(n["misfit_mm"], 4), "", fixed(f.get("misfit_mm"), 4)]]
    out.append(table(["", "predicted at the stop", "the full plan (predicted)", "found by the fit"], rows, left=1))
    out.append(f"<p class=small>Noise: the plan's {n['plan_per_reading_mm']:g} mm per reading over √{n['samples']} "
               f"readings = {fixed(n['plan_per_configuration_mm'], 4)} mm per configuration; the readings' spread "
               f"{fixed(n['spread_mm'], 4)} mm, the fit's σ {fixed(n['fitted_mm'], 4)} mm. The misfit is what the fit's "
               "σ has beyond the spread: error the model does not explain, counted in the model errors.</p>")
    return out
