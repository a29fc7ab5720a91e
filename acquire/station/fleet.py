"""``acquire fleet``: every robot of the plant at a glance, and a page per robot with its history.

Rows (one per robot in the archive): serial, site/cell, the cell's state as the station last saw
it (``<archive>/.station/cells.json``: ``up`` / ``down`` / ``error``), the last calibration (run,
date, mean absolute error after), the last measurement's drift verdict.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from acquire.station.history import load_history, robots
from calib.report.svg import TAB10, Figure, data_limits, esc, nice_ticks  # noqa: F401


def read_cells(archive_root: Path) -> dict[tuple[str, str], dict]:
    """The station's view of the cells, keyed (site, cell); empty when no station wrote one."""
    p = Path(archive_root) / ".station" / "cells.json"
    if not p.exists():
        return {}
    return {(c["site"], c["cell"]): c for c in json.loads(p.read_text())["cells"]}


def fleet_rows(archive_root: Path) -> list[dict]:
    """One row per robot (see the module docstring); plain JSON values."""
    cells = read_cells(archive_root)
    rows = []
    for serial in robots(archive_root):
        hist = load_history(archive_root, serial)
        last = hist[-1]
        cal = next((e for e in reversed(hist) if e.get("entered")), None)
        cell = cells.get((last["site"], last["cell"]))
        state = "unknown" if cell is None else ("error" if cell.get("last_error") else
                                                 "up" if cell.get("alive") else "down")
        drift = last.get("drift") or {}
        rows.append({
            "robot_serial": serial, "site": last["site"], "cell": last["cell"], "cell_state": state,
            "cell_error": cell.get("last_error") if cell else None,
            "last_calibration": None if cal is None else {
                "run_id": cal["run_id"], "finished": cal["finished"], "accuracy_after_mm": cal["accuracy_mm"]["after"]},
            "last_measurement": {"run_id": last["run_id"], "finished": last["finished"], "kind": last["kind"]},
            "drifted": bool(drift.get("drifted")), "drift_reasons": drift.get("reasons", []),
            "runs": len(hist),
        })
    return rows


def render_table(rows: list[dict]) -> str:
    """The terminal table."""
    head = ("ROBOT", "SITE/CELL", "CELL", "LAST CALIBRATION", "ACC AFTER", "LAST RUN", "DRIFT")
    lines = [head]
    for r in rows:
        cal = r["last_calibration"]
        acc = cal and cal["accuracy_after_mm"]
        lines.append((r["robot_serial"], "/".join(p for p in (r["site"], r["cell"]) if p), r["cell_state"],
                      f"{cal['run_id']} {cal['finished'][:10]}" if cal else "none",
                      f"{acc:.3f} mm" if isinstance(acc, (int, float)) else "-",
                      f"{r['last_measurement']['kind']} {r['last_measurement']['finished'][:10]}",
                      ("DRIFT: " + "; ".join(r["drift_reasons"])) if r["drifted"] else "ok"))
    widths = [max(len(str(line[i])) for line in lines) for i in range(len(head) - 1)]
    return "\n".join("  ".join(str(v).ljust(w) for v, w in zip(line, widths)) + "  " + str(line[-1])
                     for line in lines)


def _days(entries: list[dict]) -> np.ndarray:
    from datetime import datetime

    t = [datetime.fromisoformat(e["finished"]).timestamp() for e in entries]
    return (np.array(t) - t[0]) / 86400.0


def robot_page(archive_root: Path, serial: str) -> str:
    """A static HTML page: the robot's offsets (± 2σ) and accuracy over time, and every run."""
    hist = load_history(archive_root, serial)
    if not hist:
        raise ValueError(f"robot {serial!r} has no history in {archive_root}; robots: {robots(archive_root)}")
    days = _days(hist)
    xlim = (float(days.min()) - 1, float(days.max()) + 1)
    joints = hist[-1]["joints"]
    fig = Figure(760, 130 * len(joints) + 60)
    for j, name in enumerate(joints):
        vals = np.array([e["offsets_deg"][j] if e["offsets_deg"][j] is not None else np.nan for e in hist], float)
        std = np.array([e["std_deg"][j] if e["std_deg"][j] is not None else np.nan for e in hist], float)
        ylim = data_limits(np.concatenate([vals - 2 * std, vals + 2 * std]), 0.1)
        ax = fig.axes((70, 20 + 130 * j, 660, 95), xlim, ylim)
        for k, (x, v, s) in enumerate(zip(days, vals, std)):
            if not np.isfinite(v):
                continue
            colour = "#d62728" if (hist[k].get("drift") or {}).get("drifted") else (
                TAB10[0] if hist[k]["kind"] == "calibration" else TAB10[1])
            ax.line([x, x], [v - 2 * s, v + 2 * s], color=colour)
            ax.marker(x, v, color=colour, size=6, label=None)
        ax.hline(0.0, color="#999999")
        ax.frame(title=f"{name} offset (deg, ± 2σ; blue calibration, orange check, red drifted)",
                 xlabel="days" if j == len(joints) - 1 else "", ylabel="deg")
    acc_b = np.array([e["accuracy_mm"]["before"] or np.nan for e in hist], float)
    acc_a = np.array([e["accuracy_mm"]["after"] or np.nan for e in hist], float)
    afig = Figure(760, 220)
    ax = afig.axes((70, 20, 660, 150), xlim, data_limits(np.concatenate([acc_b, acc_a, [0.0]]), 0.1))
    ax.line(days, acc_b, color=TAB10[3], label="before (as found)")
    ax.line(days, acc_a, color=TAB10[2], label="after (corrected)")
    ax.frame(title="mean absolute error", xlabel="days", ylabel="mm")
    ax.legend()
    rows = "".join(
        f"<tr><td>{esc(e['finished'])}</td><td>{esc(e['run_id'])}</td><td>{esc(e['kind'])}</td>"
        f"<td>{'yes' if e.get('entered') else ''}</td>"
        f"<td>{esc('; '.join((e.get('drift') or {}).get('reasons', [])) or 'ok')}</td></tr>" for e in hist)
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{esc(serial)}</title></head><body>"
            f"<h1>Robot {esc(serial)}</h1><p>{len(hist)} runs; page written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}</p>"
            f"{fig.svg(f'{serial}: joint offsets over time')}{afig.svg(f'{serial}: accuracy over time')}"
            "<table border='1' cellpadding='3'><tr><th>finished</th><th>run</th><th>kind</th><th>entered</th>"
            f"<th>drift</th></tr>{rows}</table></body></html>")


def write_pages(archive_root: Path, out_dir: Path) -> list[Path]:
    """One ``<serial>.html`` per robot in ``out_dir``; returns the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for serial in robots(archive_root):
        p = out_dir / f"{serial}.html"
        p.write_text(robot_page(archive_root, serial), encoding="utf-8")
        paths.append(p)
    return paths
