"""The fitted joint compliances as a ``report.html`` section (fast fit and full identification).

Entries as ``result.json`` has them (``diagnostics.compliance`` of the fast fit, ``compliance``
of ``--method full``): joint, status ``fitted``/``undetermined``, value and std in rad/(N·m),
``ci95`` [lo, hi] where the fit gives one (else ±1.96·std, said so), and the reason an axis is
undetermined. Shown in µrad/(N·m): a joint that turns 10 µrad under 1 N·m of gravity torque.
"""

from __future__ import annotations

from calib.report.report_format import Html, num, table

MICRO = 1e6


def compliance_section(entries: list[dict] | None) -> list[str]:
    """HTML parts of the section; [] when the fit had no compliance model."""
    if not entries:
        return []
    rows, notes, normal = [], [], False
    for c in entries:
        if c.get("status") == "fitted" and c.get("value") is not None:
            ci = c.get("ci95")
            if not ci:
                normal = True
                ci = [c["value"] - 1.96 * c["std"], c["value"] + 1.96 * c["std"]]
            rows.append([c["joint"], Html(num(c["value"] * MICRO, 3)), Html(num(c["std"] * MICRO, 2)),
                         Html(f"[{num(ci[0] * MICRO, 3)}, {num(ci[1] * MICRO, 3)}]"), Html("<span class=good>fitted</span>")])
            notes.append(None)
        else:
            rows.append([c["joint"], None, None, None, Html("<span class=warn>undetermined</span>")])
            notes.append(c.get("reason") or "not determined by these data")
    out = ["<h2 id=compliance>Joint compliances (gravity sag)</h2>",
           table(["joint", "value (µrad/(N·m))", "std", "95 % interval", "status"], rows, notes=notes),
           "<p class=small>Each axis turns by compliance × the gravity torque on it (from the model's link masses); "
           "an undetermined axis is not loaded enough by gravity in these configurations (or not fitted) and says why."
           + (" Intervals: ±1.96 std (normal approximation of the least-squares fit)." if normal else "") + "</p>"]
    return out
