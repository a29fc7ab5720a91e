"""``acquire fleet``: every robot of the plant at a glance, an index page and a page per robot.

Rows (one per robot in the archive): serial, site/cell, the cell's state as the station last saw
it (``<archive>/.station/cells.json``: ``up`` / ``down`` / ``error``), the robot's state
(``acquire.station.states``, computed now with the station's policy ``.station/policy.json``),
its reference (the entered calibration), the last run, and archived files the scrub found
damaged and not yet repaired.

Pages (``write_pages``): ``index.html`` — every robot with its state and why; ``<serial>.html`` —
per axis the offsets as Δ from the entered reference (the reference itself at 0 with its ± 2σ,
each later run's Δ ± 2σ and its drift threshold, ± 3 combined σ), the error held out as the robot
ran and with each run's values entered (``acquire.station.accuracy``) over time, and every run
with its verdict. Axes a run left undetermined are said in
words. Plain HTML with inline SVG (``calib.report.svg``), readable on a phone.
"""

from __future__ import annotations

import json
import math
from datetime import datetime
from pathlib import Path

import numpy as np

from acquire.station.drift import expected_deg
from acquire.station.history import load_history, recompute, reference_for, robots
from acquire.station.states import Policy, robot_state
from calib.report.svg import TAB10, Figure, data_limits, esc

_HEAD = ("<!doctype html><html lang='en'><head><meta charset='utf-8'>"
         "<meta name='viewport' content='width=device-width, initial-scale=1'><title>{title}</title><style>"
         "body{{font-family:system-ui,sans-serif;margin:1em;max-width:60em}} svg.fig{{max-width:100%;height:auto}}"
         "table{{border-collapse:collapse;display:block;overflow-x:auto}} td,th{{border:1px solid #ccc;padding:3px 6px;"
         "text-align:left;vertical-align:top}} .state{{font-weight:bold}} .s-drifted,.s-out-of-tolerance{{color:#b00}}"
         ".s-check-due,.s-never-calibrated{{color:#a60}} .s-calibrated{{color:#070}}</style></head><body>")
_STATE_COLOUR = {"calibrated": TAB10[2], "drifted": TAB10[3], "out of tolerance": TAB10[3],
                 "check due": TAB10[1], "never calibrated": TAB10[7]}


def read_cells(archive_root: Path) -> dict[tuple[str, str], dict]:
    """The station's view of the cells, keyed (site, cell); empty when no station wrote one."""
    p = Path(archive_root) / ".station" / "cells.json"
    if not p.exists():
        return {}
    return {(c["site"], c["cell"]): c for c in json.loads(p.read_text())["cells"]}


def read_policy(archive_root: Path) -> Policy:
    """The policy the station wrote (``.station/policy.json``); the defaults without one."""
    p = Path(archive_root) / ".station" / "policy.json"
    return Policy.from_dict(json.loads(p.read_text())) if p.exists() else Policy()


def damaged_runs(archive_root: Path) -> dict[str, list[str]]:
    """Per robot serial, the archived runs the scrub found damaged and not yet repaired."""
    out: dict[str, list[str]] = {}
    for idx in sorted((Path(archive_root) / ".index").glob("*.json")):
        entry = json.loads(idx.read_text())
        if entry.get("damaged"):
            serial, _, run = Path(entry["folder"]).parts[:3]
            out.setdefault(serial, []).append(f"{run}: {', '.join(entry['damaged'])}")
    return out


def fleet_rows(archive_root: Path, policy: Policy | None = None, now: datetime | None = None) -> list[dict]:
    """One row per robot (see the module docstring); plain JSON values."""
    policy = policy or read_policy(archive_root)
    cells = read_cells(archive_root)
    damaged = damaged_runs(archive_root)
    rows = []
    for serial in robots(archive_root):
        hist = load_history(archive_root, serial)
        last = hist[-1]
        cell = cells.get((last["site"], last["cell"]))
        cell_state = "unknown" if cell is None else ("error" if cell.get("last_error") else
                                                      "up" if cell.get("alive") else "down")
        st = robot_state(hist, policy, now)
        ref = next((e for e in hist if e["run_id"] == st["reference"]), None)
        rows.append({
            "robot_serial": serial, "site": last["site"], "cell": last["cell"], "cell_state": cell_state,
            "cell_error": cell.get("last_error") if cell else None,
            "state": st["state"], "reasons": st["reasons"], "axes": st["axes"],
            "reference": None if ref is None else {
                "run_id": ref["run_id"], "finished": ref["finished"], "accuracy_after_mm": ref["accuracy_mm"]["after"]},
            "last_run": {"run_id": last["run_id"], "finished": last["finished"], "kind": last["kind"]},
            "accuracy_mm": st["accuracy_mm"], "accuracy_limit_mm": st["accuracy_limit_mm"], "runs": len(hist),
            "damaged": damaged.get(serial, []),
        })
    return rows


def needs_action(rows: list[dict]) -> bool:
    """Whether any robot is drifted or out of tolerance (``acquire fleet`` then exits 3)."""
    return any(r["state"] in ("drifted", "out of tolerance") for r in rows)


def render_table(rows: list[dict]) -> str:
    """The terminal table."""
    head = ("ROBOT", "SITE/CELL", "CELL", "REFERENCE", "LAST RUN", "STATE")
    lines = [head]
    for r in rows:
        ref = r["reference"]
        lines.append((r["robot_serial"], "/".join(p for p in (r["site"], r["cell"]) if p), r["cell_state"],
                      f"{ref['run_id']} {ref['finished'][:10]}" if ref else "none",
                      f"{r['last_run']['kind']} {r['last_run']['finished'][:10]}",
                      f"{r['state']}: " + "; ".join(r["reasons"])
                      + (f"; archive: {len(r['damaged'])} damaged copy(ies) awaiting the cell" if r["damaged"] else "")))
    widths = [max(len(str(line[i])) for line in lines) for i in range(len(head) - 1)]
    return "\n".join("  ".join(str(v).ljust(w) for v, w in zip(line, widths)) + "  " + str(line[-1])
                     for line in lines)


def _days(entries: list[dict], t0: datetime) -> np.ndarray:
    return np.array([(datetime.fromisoformat(e["finished"]) - t0).total_seconds() / 86400.0 for e in entries])


def deltas(hist: list[dict]) -> list[dict]:
    """Per run and axis: Δ from the entered reference it was measured against (degrees), its σ and the
    drift threshold (3 combined σ); the reference itself at Δ = 0 with its own σ. Runs before the
    first entered calibration have no reference (``reference`` None)."""
    out = []
    for e in hist:
        ref = reference_for(hist, e)
        row = {"run_id": e["run_id"], "reference": None, "axes": {}}
        for j, name in enumerate(e["joints"]):
            v, s = e["offsets_deg"][j], e["std_deg"][j]
            if v is None or s is None:
                row["axes"][name] = None
                continue
            if e.get("entered"):
                row["axes"][name] = {"delta": 0.0, "sigma": s, "threshold": None, "beyond": False}
                row["reference"] = e["run_id"]
            elif ref is not None and ref["offsets_deg"][j] is not None and ref["std_deg"][j] is not None:
                thr = 3.0 * math.hypot(s, ref["std_deg"][j])
                d = v - expected_deg(ref, j)
                row["axes"][name] = {"delta": d, "sigma": s, "threshold": thr, "beyond": abs(d) > thr}
                row["reference"] = ref["run_id"]
            else:
                row["axes"][name] = {"delta": None, "sigma": s, "threshold": None, "beyond": False}
        out.append(row)
    return out


def _offset_figure(hist: list[dict], rows: list[dict], days: np.ndarray, xlim, joints: list[str],
                   xlabel: str) -> tuple[str, list[str]]:
    """The Δ plots of the axes that have something to plot; the sentences for those that have not."""
    plotted, words = [], []
    for name in joints:
        pts = [(x, r["axes"].get(name), e) for x, r, e in zip(days, rows, hist)]
        vals = [(x, a, e) for x, a, e in pts if a and a["delta"] is not None]
        undetermined = [e["run_id"] for _, a, e in pts if a is None]
        if not vals:
            words.append(f"{name}: no Δ to plot — " + (
                f"undetermined in every run ({', '.join(undetermined)}); the plan's configurations do not "
                "determine this axis" if len(undetermined) == len(pts) else "no run measured it against an entered "
                "reference"))
            continue
        if undetermined:
            words.append(f"{name}: undetermined in run(s) {', '.join(undetermined)} (not plotted)")
        plotted.append((name, vals))
    if not plotted:
        return "", words
    fig = Figure(760, 125 * len(plotted) + 50)
    for k, (name, vals) in enumerate(plotted):
        span = [v for _, a, _ in vals for v in (a["delta"] - 2 * a["sigma"], a["delta"] + 2 * a["sigma"],
                                               a["threshold"] or 0.0, -(a["threshold"] or 0.0))]
        ax = fig.axes((70, 25 + 125 * k, 660, 90), xlim, data_limits(np.array(span), 0.1))
        ax.hline(0.0, color="#999999")
        for x, a, e in vals:
            if a["threshold"]:
                for t in (a["threshold"], -a["threshold"]):
                    ax.line([x - 0.3, x + 0.3], [t, t], color=TAB10[3], width=1.5)
            colour = TAB10[3] if a["beyond"] else (TAB10[2] if e.get("entered") else
                                                   TAB10[0] if e["kind"] == "calibration" else TAB10[1])
            ax.line([x, x], [a["delta"] - 2 * a["sigma"], a["delta"] + 2 * a["sigma"]], color=colour)
            ax.marker(x, a["delta"], color=colour, size=6)
        ax.frame(title=f"{name}: Δ from the entered reference (deg, ± 2σ; red ticks: drift threshold ± 3 combined σ)",
                 xlabel=xlabel if k == len(plotted) - 1 else "", ylabel="Δ deg")
    legend = ("green: the entered reference (Δ 0 by definition); blue: a calibration not entered; orange: a check; "
              "red: beyond the threshold")
    return fig.svg("offsets as Δ from the entered reference over time") + f"<p>{esc(legend)}</p>", words


def robot_page(archive_root: Path, serial: str, policy: Policy | None = None, now: datetime | None = None) -> str:
    """A static HTML page for one robot (see the module docstring)."""
    policy = policy or read_policy(archive_root)
    hist = recompute(load_history(archive_root, serial), policy)
    if not hist:
        raise ValueError(f"robot {serial!r} has no history in {archive_root}; robots: {robots(archive_root)}")
    st = robot_state(hist, policy, now)
    t0 = datetime.fromisoformat(hist[0]["finished"])
    days = _days(hist, t0)
    pad = max(1.0, 0.05 * float(days.max() - days.min()))
    xlim = (float(days.min()) - pad, float(days.max()) + pad)
    rows = deltas(hist)
    since = f"days since {hist[0]['finished'][:10]}"
    offsets_svg, words = _offset_figure(hist, rows, days, xlim, hist[-1]["joints"], since)
    before_ref = [e["run_id"] for e, r in zip(hist, rows) if r["reference"] is None]
    acc_b = np.array([e["accuracy_mm"]["before"] if e["accuracy_mm"]["before"] is not None else np.nan for e in hist])
    acc_a = np.array([e["accuracy_mm"]["after"] if e["accuracy_mm"]["after"] is not None else np.nan for e in hist])
    afig = Figure(760, 230)
    values = np.concatenate([acc_b, acc_a] + ([[st["accuracy_limit_mm"]]] if st["accuracy_limit_mm"] else []))
    top = float(np.nanmax(values)) if np.isfinite(values).any() else 1.0
    ax = afig.axes((70, 25, 660, 150), xlim, (0.0, 1.4 * top))   # headroom: the legend sits above the data
    ax.scatter(days, acc_b, color=TAB10[3], size=6, label="as it ran (the controller's nominal arm)")
    ax.scatter(days, acc_a, color=TAB10[2], size=6, label="with the run's values entered")
    if st["accuracy_limit_mm"]:
        ax.hline(st["accuracy_limit_mm"], color=TAB10[3])
    ax.frame(title="mean error held out" + (f" (line: limit {st['accuracy_limit_mm']:.3f} mm)"
                                            if st["accuracy_limit_mm"] else ""),
             xlabel=since, ylabel="mm")
    ax.legend("upper left")
    joints = hist[-1]["joints"]
    head = "".join(f"<th>Δ {esc(j)} (deg)</th>" for j in joints)
    body = []
    for e, r in zip(hist, rows):
        cells = []
        for j in joints:
            a = r["axes"].get(j)
            if a is None:
                cells.append("<td class='delta'>undetermined</td>")
            elif a["delta"] is None:
                cells.append(f"<td class='delta'>no reference (σ {a['sigma']:.4f})</td>")
            else:
                flag = " BEYOND" if a["beyond"] else ""
                thr = f" / thr {a['threshold']:.4f}" if a["threshold"] else ""
                cells.append(f"<td class='delta'>{a['delta']:+.4f} ± {2 * a['sigma']:.4f}{thr}{flag}</td>")
        verdict = (e.get("drift") or {})
        text = "; ".join(verdict.get("reasons", [])) or ("reference" if e.get("entered") else
                                                           "no reference" if r["reference"] is None else "offsets ok")
        acc = e["accuracy_mm"]
        body.append(f"<tr class='run'><td>{esc(e['finished'][:16])}</td><td>{esc(e['run_id'])}</td>"
                    f"<td>{esc(e['kind'])}</td><td>{'yes' if e.get('entered') else ''}</td>"
                    f"<td>{_mm(acc['before'])}</td><td>{_mm(acc['after'])}</td><td class='verdict'>{esc(text)}</td>"
                    f"{''.join(cells)}</tr>")
    notes = [esc(w) for w in words]
    if before_ref:
        notes.append(esc(f"run(s) {', '.join(before_ref)}: before the first entered calibration, nothing to compare "
                         "with (listed, not plotted)"))
    return (_HEAD.format(title=esc(f"Robot {serial}"))
            + f"<p><a href='index.html'>all robots</a></p><h1>Robot {esc(serial)}</h1>"
            + f"<p class='state s-{st['state'].replace(' ', '-')}' id='state'>{esc(st['state'])}</p>"
            + "<ul id='reasons'>" + "".join(f"<li>{esc(x)}</li>" for x in st["reasons"]) + "</ul>"
            + f"<h2>Offsets</h2>{offsets_svg}"
            + ("<ul id='notes'>" + "".join(f"<li>{n}</li>" for n in notes) + "</ul>" if notes else "")
            + f"<h2>Accuracy</h2>{afig.svg('mean error held out, as it ran and with the values entered')}"
            + "<h2>Runs</h2><table id='runs'><tr><th>finished (UTC)</th><th>run</th><th>kind</th><th>entered</th>"
            + f"<th>as it ran (mm)</th><th>values entered (mm)</th><th>verdict</th>{head}</tr>{''.join(body)}</table>"
            + f"<p>page written {datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')}</p></body></html>")


def _mm(v) -> str:
    return f"{v:.3f}" if isinstance(v, (int, float)) and math.isfinite(v) else "-"


def index_page(archive_root: Path, policy: Policy | None = None, now: datetime | None = None) -> str:
    """Every robot with its state and why, linking to its page."""
    rows = fleet_rows(archive_root, policy, now)
    order = {"drifted": 0, "out of tolerance": 1, "check due": 2, "never calibrated": 3, "calibrated": 4}
    body = "".join(
        f"<tr class='robot'><td><a href='{esc(r['robot_serial'])}.html'>{esc(r['robot_serial'])}</a></td>"
        f"<td>{esc('/'.join(p for p in (r['site'], r['cell']) if p))}</td>"
        f"<td class='state s-{r['state'].replace(' ', '-')}'>{esc(r['state'])}</td>"
        f"<td>{esc('; '.join(r['reasons']))}</td><td>{esc(r['reference']['run_id'] if r['reference'] else 'none')}</td>"
        f"<td>{esc(r['last_run']['run_id'])} ({esc(r['last_run']['finished'][:10])})</td>"
        f"<td>{esc(r['cell_state'])}</td>"
        f"<td class='archive'>{esc('; '.join(r['damaged']) + ' (awaiting a copy from the cell)' if r['damaged'] else 'ok')}"
        "</td></tr>"
        for r in sorted(rows, key=lambda r: (order.get(r["state"], 9), r["robot_serial"])))
    counts = {s: sum(r["state"] == s for r in rows) for s in order}
    summary = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    return (_HEAD.format(title="remaster fleet") + f"<h1>Robots ({len(rows)})</h1><p id='summary'>{esc(summary)}</p>"
            "<table id='robots'><tr><th>robot</th><th>site/cell</th><th>state</th><th>why</th><th>reference</th>"
            f"<th>last run</th><th>cell</th><th>archive</th></tr>{body}</table></body></html>")


def write_pages(archive_root: Path, out_dir: Path, policy: Policy | None = None) -> list[Path]:
    """``index.html`` and one ``<serial>.html`` per robot in ``out_dir``; returns the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "index.html"]
    paths[0].write_text(index_page(archive_root, policy), encoding="utf-8")
    for serial in robots(archive_root):
        p = out_dir / f"{serial}.html"
        p.write_text(robot_page(archive_root, serial, policy), encoding="utf-8")
        paths.append(p)
    return paths
