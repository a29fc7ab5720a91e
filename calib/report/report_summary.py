"""The one-screen summary at the top of ``report.html``, and the warnings it lists.

Everything here reads the ``result.json`` document only (``calib.fit.result``), so a report and the
file agree: the verdict (enter the offsets, or "do not enter" with the reasons of
``calib.robot.controller.do_not_enter_reasons``), the values to enter, the accuracy before and after,
and the warnings (``warnings``).
"""

from __future__ import annotations

from calib.robot.controller import MAX_RHAT, do_not_enter_reasons
from calib.report.report_format import Html, esc, fixed, num, table

#: A sandwich/posterior std ratio above this is worth a warning (the guard refuses above 2).
SANDWICH_WARN = 1.25
#: Fewer effective draws than this: means and stds are unreliable.
MIN_ESS = 100

#: Accuracy rows of the summary: metric key → label (mean and 97.5 % percentile shown).
SUMMARY_METRICS = {
    "absolute": "calibration set, after registration (eq. 18)",
    "validation_absolute": "validation set, with the calibration registration (eq. 18)",
    "validation_relative": "validation set, relative (eq. 17)",
    "theoretical_workspace": "theoretical, workspace (offsets + σ, Table VI)",
}


def refusal_reasons(doc: dict) -> list[str]:
    """Why the offsets must not be entered: the verdict on the offsets fitted for the controller
    (``doc["entered"]``, ``calib.fit.entered``) where the document has one, else the guards' reasons."""
    entered = doc.get("entered")
    if entered:
        return list(entered["reasons"]) if entered["verdict"] != "enter" else []
    return list(doc.get("do_not_enter") or do_not_enter_reasons(doc))


#: Rows of the held-out table: ``entered.heldout`` key → label.
HELDOUT_ROBOTS = {"as_found": "as found (zero offsets; registration and tool fitted)",
                  "entered": "offsets entered on the controller's nominal arm",
                  "full_model": "full model (via compensation)"}


def heldout_table(doc: dict) -> Html | None:
    """The three robots held out side by side (``doc["entered"]["heldout"]``), or None."""
    entered = doc.get("entered")
    if not entered:
        return None
    h = entered["heldout"]
    rows = []
    for key, label in HELDOUT_ROBOTS.items():
        e = h[key]
        name = label if key != "full_model" else f"full model ({entered.get('full_model', 'chosen')}; via compensation)"
        cell = Html(f"<b>{fixed(e['rms_mm'], 4)}</b>") if key == "entered" else Html(fixed(e["rms_mm"], 4))
        rows.append([name, cell, Html(fixed(e["mean_mm"], 4)), Html(fixed(e["max_mm"], 4)), e["n"]])
    imp = h["improvement_mm"]
    note = (f"improvement as found → entered {fixed(imp['value'], 4, sign=True)} mm, 95 % "
            f"[{fixed(imp['ci95'][0], 4, sign=True)}, {fixed(imp['ci95'][1], 4, sign=True)}] ({imp['test']}); "
            f"scored on {h['scored_on']}: {h['how']}")
    return table([f"held out ({h['scored_on']}), mm", "rms", "mean", "max", "n"], rows, notes=[None, None, note])


def warnings(doc: dict) -> list[str]:
    """What an operator should know before entering anything, as sentences (may be empty)."""
    out = []
    d = doc.get("diagnostics", {})
    rhat, ess = d.get("rhat_max"), d.get("ess_min")
    if rhat is not None and rhat > MAX_RHAT:
        out.append(f"R-hat {rhat:.3f} > {MAX_RHAT}: the sampler has not converged.")
    if ess is not None and ess < MIN_ESS:
        out.append(f"ESS {ess:.0f} < {MIN_ESS}: too few effective draws for reliable means and standard deviations.")
    ratios = {j["joint"]: j["sandwich_std_ratio"] for j in doc.get("joint_offsets", []) if j.get("sandwich_std_ratio")}
    if ratios and max(ratios.values()) > SANDWICH_WARN:
        worst = max(ratios, key=ratios.get)
        out.append(f"The errors are not independent and isotropic: the model-robust std of {worst} is "
                   f"{ratios[worst]:.2f}× the posterior's, so its interval is too narrow.")
    for j in doc.get("joint_offsets", []):
        if j.get("status") == "undetermined":
            why = (j.get("reason") or "").split(" (combination")[0]
            out.append(f"{j['joint']}: leave unchanged — {why}.")
    ident = doc.get("identifiability", {}).get("estimate", {})
    for c in ident.get("directions", []):
        if c.get("verdict") in ("weakly determined", "not determined"):
            out.append(f"At the estimate, the combination {c['combination']} is {c['verdict']} ({c.get('why', '')}).")
    for s, c in (doc.get("registration_statistics") or {}).items():
        if c.get("significant") and c.get("r", 0) > 0:
            out.append(f"Sensor {s}: the position error grows with the distance from the sensor (r = {c['r']:.2f}, "
                       f"p = {c['p_value']:.2g}; the registration seed's spatial correlation): a registration or scale "
                       "error, or a sensor less accurate at range — the offsets' intervals assume independent errors.")
    sag = d.get("gravity_sag")
    if sag and sag.get("significant"):
        out.append(f"The residuals follow the joints' gravity torques (p = {sag['p_value']:.1g}): the arm sags; "
                   "fit the compliances too (--compliance).")
    for s, b in (d.get("error_budget") or {}).items():
        share = b.get("unmodelled_share")
        if share is not None and share > 0.5:
            out.append(f"Sensor {s}: {share:.0%} of σ² is robot error the model lacks (link lengths, sag); the offsets "
                       "may be biased beyond their intervals — compare with --method full.")
    return out


def _axes(doc: dict) -> list[dict]:
    ctrl = doc.get("controller")
    if ctrl and ctrl.get("axes"):
        return ctrl["axes"]
    return [{"axis": j["joint"], "delta_deg": j["value_deg"] if j.get("identifiable") else None,
             "std_deg": j.get("std_deg"), "correction_deg": -j["value_deg"] if j.get("identifiable") else None,
             "action": "enter" if j.get("identifiable") else "leave unchanged", "reason": j.get("status", "")}
            for j in doc.get("joint_offsets", [])]


def offsets_table(doc: dict) -> Html:
    """Axis, δ ± std, correction (−δ) and the action, degrees; long reasons under the row."""
    rows, notes = [], []
    for a in _axes(doc):
        if a.get("delta_deg") is None:
            reason = a.get("reason") or ""
            refused = reason == "do not enter"
            rows.append([a["axis"], "—", "—", Html(f"<span class=warn>{esc('do not enter' if refused else a['action'])}</span>")])
            notes.append(None if refused or not reason else f"{a['axis']}: {reason}")
        else:
            rows.append([a["axis"], Html(f"{fixed(a['delta_deg'], 4, sign=True)} <span class='small nw'>± {fixed(a['std_deg'], 4)}</span>"),
                         Html(fixed(a["correction_deg"], 4, sign=True)), a["action"]])
            notes.append(None)
    return table(["axis", "δ ± std", "correction", "action"], rows, notes=notes)


def accuracy_table(doc: dict) -> Html | None:
    metrics = doc.get("metrics") or {}
    rows = []
    for key, label in SUMMARY_METRICS.items():
        m = metrics.get(key)
        if isinstance(m, dict) and isinstance(m.get("before"), dict):
            b, a = m["before"], m["after"]
            rows.append([label, Html(f"{fixed(b['mean'], 3)} [{fixed(b['p97_5'], 3)}]"),
                         Html(f"<b>{fixed(a['mean'], 3)}</b> [{fixed(a['p97_5'], 3)}]")])
    if not rows:
        return None
    return table(["accuracy (mm): mean [97.5 %]", "before", "after"], rows)


def model_choice_table(doc: dict) -> Html | None:
    """The cross-validation table of ``doc["model_choice"]`` (``calib.fit.model_choice``), or None."""
    mc = doc.get("model_choice")
    if not mc:
        return None
    rows = []
    for c in [mc["nominal"]] + mc["candidates"]:
        name = c["model"] + (" ← chosen" + (" (--model)" if mc.get("forced") else "") if c["model"] == mc["chosen"] else "")
        if c.get("failed"):
            rows.append([name, "—" if c["free_parameters"] is None else c["free_parameters"], "—", f"failed: {c['failed']}"])
        else:
            rows.append([Html(f"<b>{esc(name)}</b>") if c["model"] == mc["chosen"] else name, c["free_parameters"],
                         Html(fixed(c["cv_rms_mm"], 4)), Html(f"{fixed(c['cv_mean_mm'], 4)} ± {fixed(c['cv_se_mm'], 4)}")])
    return table([f"model ({mc['folds']}-fold CV by {mc['grouped_by']})", "free", "held-out rms (mm)", "mean ± se (mm)"], rows)


def summary_html(doc: dict) -> str:
    """The summary box: verdict, offsets to enter, accuracy before/after, warnings."""
    refused = refusal_reasons(doc)
    entered = [a for a in _axes(doc) if a.get("delta_deg") is not None]
    if refused:
        cls, banner = "stop", "<span class=bad>DO NOT ENTER these offsets.</span>"
    elif entered:
        cls, banner = "ok", f"<span class=good>Enter the offsets of {len(entered)} axes below</span> (the others: leave unchanged)."
    else:
        cls, banner = "stop", "<span class=bad>Nothing to enter:</span> no offset is determined by this data."
    parts = [f"<section class='summary {cls}' id=summary><h2>Summary</h2><p class=banner>{banner}</p>"]
    if refused:
        parts.append("<ul class=bad>" + "".join(f"<li>{esc(r)}</li>" for r in refused) + "</ul>")
    ctrl = doc.get("controller") or {}
    parts.append("<div class=cols><div>")
    parts.append(f"<p class=small>values for the {esc(ctrl.get('controller', doc['robot'].get('controller', '?')))} "
                 f"controller, degrees; δ: true axis angle = reported angle + δ; correction = −δ.</p>")
    parts.append(offsets_table(doc))
    if ctrl.get("lines") and not refused:
        parts.append("<p class=small>to type on the controller (sign UNVERIFIED — see the convention below):</p>")
        parts.append("<pre class=wrap>" + "\n".join(esc(line) for line in ctrl["lines"]) + "</pre>")
    parts.append("</div><div>")
    held = heldout_table(doc)
    if held:
        parts.append(held)
    acc = accuracy_table(doc)
    if acc:
        parts.append(acc)
        if held:
            parts.append("<p class=small>before: the robot as found (zero offsets, its tool fitted); after: the fitted "
                         "model's own offsets on the nominal arm — not what is entered (the held-out table above is).</p>")
    choice = model_choice_table(doc)
    if choice:
        parts.append(choice)
        parts.append(f"<p class=small>model: {esc(doc['model_choice']['chosen'])} — {esc(doc['model_choice']['rule'])}; each "
                     "model fitted on the other folds, held-out configurations scored with that fit's registration.</p>")
        from calib.report.report_choice import link_scale_lines  # that module builds on this one's table

        parts += [f"<p class=small>{esc(line)}</p>" for line in link_scale_lines(doc["model_choice"])]
    sig = ", ".join(f"{esc(s)} σ = {num(v['value'], 3)} mm" for s, v in doc.get("sigma_mm", {}).items())
    if sig:
        parts.append(f"<p class=small>fit: {sig}; {doc['data']['n_measurements']} measurements at "
                     f"{doc['data']['n_configurations']} configurations.</p>")
    parts.append("</div></div>")
    warn = warnings(doc)
    if warn:
        parts.append("<p><b>Warnings</b></p><ul class=warn>" + "".join(f"<li>{esc(w)}</li>" for w in warn) + "</ul>")
    else:
        parts.append("<p class=good>No warnings.</p>")
    parts.append("<p class=small>Details: <a href='#controller'>values to enter and sign convention</a> · "
                 "<a href='#accuracy'>accuracy</a> · <a href='#identifiability'>identifiability</a> · "
                 "<a href='#tcp'>TCP cloud</a></p></section>")
    return "\n".join(parts)


def entered_section(doc: dict) -> list[str]:
    """What the controller gets, on its own (the identification's report): the verdict on the offsets
    fitted for its nominal arm, the three robots held out, and the values (``doc["entered"]``)."""
    entered = doc.get("entered")
    if not entered:
        return []
    refused = refusal_reasons(doc)
    cls = "summary stop" if refused else "summary ok"
    banner = ("<span class=bad>DO NOT ENTER offsets on the controller.</span>" if refused else
              "<span class=good>Enter the offsets below on the controller</span> (the others: leave unchanged).")
    out = [f"<div class='{cls}'><h2 id=controller>What the controller gets</h2><p class=banner>{banner}</p>"]
    if refused:
        out.append("<ul class=bad>" + "".join(f"<li>{esc(r)}</li>" for r in refused) + "</ul>")
    out += [offsets_table(doc), heldout_table(doc), "</div>"]
    return out
