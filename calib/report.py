"""A self-contained ``report.html`` of a fit: tables and PNG plots embedded as base64.

Sections: values to enter, zero-offsets, registration and σ, accuracy metrics before/after
(Tables III–VIII of the paper), identifiability, sampler diagnostics, and plots — trace plots
and posterior histograms of the offsets, the post-registration error (eq. 18) per
configuration before/after, and that error against the distance from the sensor. Plots use
matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from calib.dataset import Dataset  # noqa: E402
from calib.fit import FitResult  # noqa: E402
from calib.kinematics import Chain  # noqa: E402
from calib.metrics import absolute_errors, predicted_base  # noqa: E402

METRIC_TITLES = {
    "relative": "Relative (eq. 17, Table III)",
    "absolute": "Post-registration absolute (eq. 18, Table IV)",
    "theoretical_measured": "Theoretical, offsets + σ, measured configurations (Table V)",
    "theoretical_measured_offsets_only": "Theoretical, offsets alone, measured configurations",
    "theoretical_workspace": "Theoretical, offsets + σ, random workspace configurations (Table VI)",
    "theoretical_workspace_offsets_only": "Theoretical, offsets alone, random workspace configurations (Table VII)",
    "validation_relative": "Validation set, relative (Table VIII)",
    "validation_absolute": "Validation set, post-registration absolute (Table VIII)",
}

CSS = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:0.5em 0 1.5em}th,td{border:1px solid #bbb;padding:3px 8px;text-align:right}
th{background:#eee}td.l,th.l{text-align:left}.warn{color:#a40}.small{font-size:0.85em;color:#555}
img{max-width:100%;border:1px solid #ddd;margin:0.5em 0}pre{background:#f6f6f6;padding:0.6em;overflow-x:auto}
"""


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return f'<img alt="plot" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode("ascii")}">'


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return "—" if not math.isfinite(v) else f"{v:.{digits}f}"
    return html.escape(str(v))


def _table(header: list[str], rows: list[list], left: int = 1) -> str:
    th = "".join(f'<th class="{"l" if i < left else ""}">{html.escape(h)}</th>' for i, h in enumerate(header))
    body = "".join(
        "<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{_fmt(c)}</td>' for i, c in enumerate(r)) + "</tr>" for r in rows
    )
    return f"<table><tr>{th}</tr>{body}</table>"


def _plots(result: FitResult, data: Dataset) -> list[str]:
    out = []
    post = result.posterior
    fitted = [i for i, s in enumerate(result.offset_status) if s == "fitted"]
    axes = result.model.axis_names
    samples = result.chains.samples  # (c, d, dim + S)
    full = post.full_vector(samples[..., : post.dim])  # (c, d, n + 6S)
    if fitted:
        fig, ax = plt.subplots(len(fitted), 2, figsize=(10, 1.8 * len(fitted)), squeeze=False)
        for row, i in enumerate(fitted):
            for c in range(full.shape[0]):
                ax[row, 0].plot(np.degrees(full[c, :, i]), lw=0.5)
            ax[row, 0].set_ylabel(f"δ{axes[i]} (°)")
            ax[row, 1].hist(np.degrees(full[..., i].ravel()), bins=40, color="tab:blue", alpha=0.8)
            ax[row, 1].axvline(math.degrees(result.offsets_rad[i]), color="k", lw=1)
        ax[0, 0].set_title("trace plots (one colour per chain)")
        ax[0, 1].set_title("posterior histograms (line: mean)")
        ax[-1, 0].set_xlabel("draw")
        ax[-1, 1].set_xlabel("degrees")
        fig.tight_layout()
        out.append(_png(fig))
    chain = Chain(result.model)
    before = absolute_errors(data, predicted_base(chain, data, np.zeros(chain.n)))
    after = absolute_errors(data, predicted_base(chain, data, result.applied_offsets_rad))
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
    idx = np.arange(len(data))
    ax[0].plot(idx, before, ".", color="tab:red", label="before (nominal offsets)")
    ax[0].plot(idx, after, ".", color="tab:green", label="after (fitted offsets)")
    ax[0].set_xlabel("measurement (row)")
    ax[0].set_ylabel("error after registration, eq. 18 (mm)")
    ax[0].legend(fontsize=8)
    dist = np.linalg.norm(data.xyz_mm, axis=1) / 1000.0
    ax[1].plot(dist, before, ".", color="tab:red", label="before")
    ax[1].plot(dist, after, ".", color="tab:green", label="after")
    ax[1].set_xlabel("distance from the sensor (m)")
    ax[1].set_ylabel("error (mm)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    out.append(_png(fig))
    return out


def render_report(result: FitResult, data: Dataset, doc: dict, controller_text: str = "") -> str:
    """The report as one HTML string. ``doc`` is the ``result.json`` document."""
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>remaster fit — {html.escape(doc['robot']['name'])}</title><style>{CSS}</style></head><body>",
        f"<h1>Remastering fit: {html.escape(doc['robot']['name'])}</h1>",
        f"<p class='small'>data: {html.escape(str(doc['data']['source']))} — {doc['data']['n_measurements']} measurements, "
        f"{doc['data']['n_configurations']} configurations, sensors {html.escape(', '.join(doc['data']['sensors']))}; "
        f"method {html.escape(str(doc['diagnostics'].get('method')))}</p>",
    ]
    if controller_text:
        parts += ["<h2>Values to enter</h2>", f"<pre>{html.escape(controller_text)}</pre>"]
    parts.append("<h2>Zero-offsets</h2>")
    parts.append(
        _table(
            ["joint", "value (°)", "std (°)", "95 % interval (°)", "sandwich ÷ std", "status", "reason"],
            [
                [
                    j["joint"],
                    j["value_deg"],
                    j["std_deg"],
                    "—" if j["ci95_deg"] is None else f"[{j['ci95_deg'][0]:.4f}, {j['ci95_deg'][1]:.4f}]",
                    j.get("sandwich_std_ratio"),
                    j["status"],
                    j["reason"],
                ]
                for j in doc["joint_offsets"]
            ],
        ).replace("<td class=\"\">undetermined", "<td class=\"warn\">undetermined")
    )
    parts.append(
        "<p class='small'>sandwich ÷ std: a model-robust standard deviation (configurations independent, errors of "
        "any shape) over the posterior's; well above 1 means the errors are not isotropic and the interval is too "
        "narrow. Systematic errors shared by all configurations (link lengths) show in neither.</p>"
    )
    parts.append("<h2>Registration corrections and σ</h2>")
    for s, reg in doc["registration"].items():
        rows = [[k, v["value"], v["std"], "free" if v["free"] else "fixed"] for k, v in reg["corrections"].items()]
        sig = doc["sigma_mm"][s]
        rows.append(["σ (mm)", sig["value"], sig["std"], "free"])
        parts += [f"<h3>{html.escape(s)}</h3>", _table(["parameter", "value", "std", ""], rows)]
        parts.append("<p class='small'>base2sensor (mm):</p><pre>" + "\n".join(
            " ".join(f"{v:12.6f}" for v in row) for row in reg["base2sensor"]) + "</pre>")
    metrics = doc.get("metrics", {})
    if metrics:
        parts.append("<h2>Accuracy before and after (mm)</h2>")
        rows = []
        for key, title in METRIC_TITLES.items():
            if key in metrics:
                for when in ("before", "after"):
                    m = metrics[key][when]
                    rows.append([title if when == "before" else "", when, m["mean"], m["p2_5"], m["p97_5"], m["max"], m["count"]])
        parts.append(_table(["metric", "", "mean", "2.5 %", "97.5 %", "max", "n"], rows, left=2))
        share = metrics.get("offsets_share")
        if share:
            parts.append(
                f"<p>Share of the workspace error explained by the offsets alone (Table VII ÷ Table VI): "
                f"before {_fmt(share['before'], 3)}, after {_fmt(share['after'], 3)}.</p>"
            )
        if metrics.get("notes"):
            parts.append("<ul class='small'>" + "".join(f"<li>{html.escape(n)}</li>" for n in metrics["notes"]) + "</ul>")
    ident = doc["identifiability"]
    parts.append("<h2>Identifiability</h2>")
    for label in ("start", "estimate"):
        idt = ident[label]
        parts.append(
            f"<h3>at the {label}</h3><p>rank {idt['rank']} of {len(idt['parameters'])}, "
            f"condition number {_fmt(idt['condition_number'], 1)}</p>"
        )
        parts.append(_table(["parameter", "singular value (mm)"], list(zip(idt["parameters"], idt["singular_values_mm"]))))
        for c in idt["undetermined_combinations"]:
            parts.append(f"<p class='warn'>undetermined combination: {html.escape(c['combination'])}</p>")
    if ident["fixed_parameters"]:
        parts.append(_table(["fixed parameter", "reason"], [[f["parameter"], f["reason"]] for f in ident["fixed_parameters"]], left=2))
    d = doc["diagnostics"]
    parts.append("<h2>Sampler diagnostics</h2>")
    parts.append(
        f"<p>sampler {html.escape(str(d.get('sampler')))}, {d.get('n_chains')} chain(s) × {d.get('n_draws')} draws, "
        f"acceptance {', '.join(f'{a:.2f}' for a in d.get('acceptance', []))}, "
        f"R-hat max {_fmt(d.get('rhat_max'), 3)}, ESS min {_fmt(d.get('ess_min'), 0)}, "
        f"time {_fmt(d.get('seconds_total'), 2)} s</p>"
    )
    if "rhat" in d or "ess" in d:
        names = list((d.get("rhat") or d.get("ess")).keys())
        parts.append(_table(["parameter", "R-hat", "ESS"], [[n, (d.get("rhat") or {}).get(n), (d.get("ess") or {}).get(n)] for n in names]))
    parts.append("<h2>Plots</h2>")
    parts += _plots(result, data)
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(path: str | Path, result: FitResult, data: Dataset, doc: dict, controller_text: str = "") -> Path:
    """Write the self-contained HTML report; returns the path."""
    path = Path(path)
    path.write_text(render_report(result, data, doc, controller_text), encoding="utf-8")
    return path
