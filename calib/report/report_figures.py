"""The report's figures as inline SVG (``calib.report.svg``), drawn from numpy arrays with no plotting library.

``tcp_clouds`` computes the paper's Fig. 5 (Sec. V-C): for chosen measured configurations, the
TCP (flange origin, robot base frame, mm) predicted with the nominal offsets ("before", red),
with the applied offsets ("after", green), with posterior draws of the offsets (yellow) and with
those draws plus the isotropic error σ (blue). ``tcp_cloud_figure`` draws it per configuration:
the top panel at a scale that shows the move from before to after, the bottom one zoomed on the
after-clouds. X–Y plane of the robot base, as in the paper.

A figure of several panels side by side is several ``<svg>`` in a ``<div class="figs">`` that
wraps: on a phone the panels stack instead of shrinking to an unreadable width.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.measure.dataset import Dataset
from calib.fit.offsets import FitResult
from calib.robot.kinematics import Chain, offset_kinematics
from calib.fit.metrics import absolute_errors, predicted_base
from calib.report.svg import COLOURS, TAB10, Figure, data_limits


#: Draws per chain shown in a trace plot: a line of 1000 points at this width is a smear of the
#: same envelope; every ``step``-th draw keeps the mixing visible at a fraction of the size.
TRACE_POINTS = 250


def side_by_side(svgs: list[str]) -> str:
    """Panels in a row that wraps on a narrow screen."""
    return '<div class="figs">' + "".join(svgs) + "</div>"


@dataclass(frozen=True)
class TcpClouds:
    """Fig. 5 data for k configurations (mm, robot base frame; TCP = flange origin).

    rows: (k,) index of a dataset row measured at each configuration; config: (k,) their ids;
    before, after: (k, 3); draws, noisy: (k, m, 3) with posterior offset draws, without and with
    the isotropic error ``sigma_mm``.
    """

    rows: np.ndarray
    config: np.ndarray
    before: np.ndarray
    after: np.ndarray
    draws: np.ndarray
    noisy: np.ndarray
    sigma_mm: float

    @property
    def shift_mm(self) -> np.ndarray:
        """(k,) |TCP after − TCP before|, mm."""
        return np.linalg.norm(self.after - self.before, axis=-1)


def pick_configurations(chain: Chain, data: Dataset, applied_rad: np.ndarray, n: int) -> np.ndarray:
    """Row indices of ``n`` distinct measured configurations spread over the before→after TCP
    shifts: the smallest, the largest and evenly spaced ranks between (fewer if fewer exist)."""
    _, first = np.unique(data.q_rad, axis=0, return_index=True)
    first = np.sort(first)
    fk = offset_kinematics(chain, data.q_rad[first], np.zeros(3))
    shift = np.linalg.norm(fk.positions(applied_rad) - fk.positions(np.zeros(chain.n)), axis=-1)
    order = first[np.argsort(shift, kind="stable")]
    if order.size <= n:
        return order
    return order[np.unique(np.round(np.linspace(0, order.size - 1, n)).astype(int))]


def tcp_clouds(result: FitResult, data: Dataset, *, n_configs: int = 3, n_draws: int = 2000, seed: int = 0) -> TcpClouds:
    """Fig. 5 data at ``n_configs`` measured configurations (``pick_configurations``), with
    ``n_draws`` posterior draws (fewer if the fit has fewer) and σ = ``result.applied_sigma_mm``."""
    chain = Chain(result.model)
    applied = result.applied_offsets_rad
    rows = pick_configurations(chain, data, applied, n_configs)
    q = data.q_rad[rows]
    fk = offset_kinematics(chain, q, np.zeros(3))
    rng = np.random.default_rng(seed)
    samples = result.offset_samples_rad
    draws = samples[rng.choice(samples.shape[0], size=min(n_draws, samples.shape[0]), replace=False)]
    cloud = np.moveaxis(fk.positions(draws), 0, 1)  # (k, m, 3)
    sigma = float(result.applied_sigma_mm)
    noisy = cloud + rng.normal(0.0, sigma, size=cloud.shape)
    return TcpClouds(rows, data.config[rows], fk.positions(np.zeros(chain.n)), fk.positions(applied), cloud, noisy, sigma)


def _limits(points: np.ndarray, pad: float = 0.15) -> tuple[tuple[float, float], tuple[float, float]]:
    """Equal-scale x/y limits around ``points`` (j, 2)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6) * (1 + pad)
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _emptiest_corner(points: np.ndarray, xlim: tuple[float, float], ylim: tuple[float, float]) -> str:
    """The legend corner ("upper left", … as ``calib.report.svg.Axes.legend`` takes) whose region — 45 % ×
    35 % of the axes — holds the fewest of ``points`` (j, 2), data coordinates."""
    u = (points[:, 0] - xlim[0]) / (xlim[1] - xlim[0])
    v = (points[:, 1] - ylim[0]) / (ylim[1] - ylim[0])
    counts = {}
    for name, (right, top) in (("upper left", (False, True)), ("upper right", (True, True)),
                               ("lower left", (False, False)), ("lower right", (True, False))):
        inside_u = u > 0.55 if right else u < 0.45
        inside_v = v > 0.65 if top else v < 0.35
        counts[name] = int(np.sum(inside_u & inside_v))
    return min(counts, key=counts.get)  # ties: the first corner listed


def tcp_cloud_figure(clouds: TcpClouds) -> str:
    """The paper's Fig. 5, one ``<svg>`` per configuration (``side_by_side``).

    Top: before (red), after (green), draws + σ (blue) and offset draws (yellow) at a scale that
    shows the move, with equal x and y scales. Bottom: zoomed on the offset draws alone (with the
    after point), the part of the error the offsets' uncertainty leaves.
    """
    out = []
    for c in range(len(clouds.rows)):
        origin = clouds.after[c, :2]
        b, a = clouds.before[c, :2] - origin, np.zeros(2)
        d, nz = clouds.draws[c, :, :2] - origin, clouds.noisy[c, :, :2] - origin
        fig = Figure(330, 660)
        top = fig.axes((62, 28, 250, 250), *_limits(np.vstack([nz, [a], [b]])))
        top.scatter(nz[:, 0], nz[:, 1], size=2, color=COLOURS["blue"], opacity=0.35, label="offset draws + σ")
        top.scatter(d[:, 0], d[:, 1], size=2, color=COLOURS["gold"], opacity=0.9, label="offset draws")
        top.arrow(b, a)
        top.marker(*a, color=COLOURS["green"], label="after")
        top.marker(*b, color=COLOURS["red"], label="before")
        labels = {"xlabel": "x − x_after (mm)", "ylabel": "y − y_after (mm)", "grid": True}
        top.frame(title=f"configuration {clouds.config[c]}: before → after {clouds.shift_mm[c]:.3g} mm", **labels)
        lo, hi = np.percentile(d, [0.5, 99.5], axis=0)
        bottom = fig.axes((62, 368, 250, 250), *_limits(np.vstack([lo, hi, a])))
        bottom.scatter(d[:, 0], d[:, 1], size=3, color=COLOURS["goldenrod"], opacity=0.6)
        bottom.marker(*a, color=COLOURS["green"], size=7)
        spread = np.percentile(np.linalg.norm(d, axis=1), 95)
        bottom.frame(title=f"offset draws alone: 95 % within {spread:.2g} mm", **labels)
        if c == 0:
            top.legend(_emptiest_corner(np.vstack([nz, d, [b], [a]]), top.xlim, top.ylim))
        out.append(fig.svg(f"TCP cloud (Fig. 5), configuration {clouds.config[c]}: before, after, posterior draws of the "
                           "offsets with and without σ"))
    return side_by_side(out)


def offset_trace_figure(result: FitResult) -> str | None:
    """Trace plots of the fitted offsets (degrees), each with its posterior histogram beside it on
    the same vertical scale; None when none is fitted."""
    post = result.posterior
    fitted = [i for i, s in enumerate(result.offset_status) if s == "fitted"]
    if not fitted:
        return None
    axes = result.model.axis_names
    full = post.full_vector(result.chains.samples[..., : post.dim])  # (c, d, n + …)
    step = max(1, math.ceil(full.shape[1] / TRACE_POINTS))
    x = np.arange(0, full.shape[1], step)
    row_h, gap, top_margin = 100, 24, 28
    fig = Figure(760, top_margin + len(fitted) * (row_h + gap) - gap + 50)
    xlim = data_limits(x)
    for row, i in enumerate(fitted):
        y0 = top_margin + row * (row_h + gap)
        values = np.degrees(full[..., i])
        ylim = data_limits(values)
        trace = fig.axes((80, y0, 540, row_h), xlim, ylim)
        for c in range(full.shape[0]):
            trace.line(x, values[c, ::step], color=TAB10[c % len(TAB10)], width=0.6)
        last = row == len(fitted) - 1
        trace.frame(ylabel=f"δ{axes[i]} (°)", xticks=last, ynbins=4,
                    xlabel=(f"draw (every {step}th shown)" if step > 1 else "draw") if last else "")
        # The histogram shares its row's vertical scale and draws no axes of its own: the counts
        # say nothing the shape does not.
        counts, edges = np.histogram(values.ravel(), bins=40, range=ylim)
        hist = fig.axes((630, y0, 110, row_h), (0.0, counts.max() * 1.05), ylim)
        hist.stairs_horizontal(counts, edges, color=COLOURS["blue"])
        hist.hline(math.degrees(result.offsets_rad[i]), color="#000")
    fig.text(80 + 270, top_margin - 8, "trace plots (one colour per chain)")
    fig.text(630 + 55, top_margin - 8, "posterior (line: mean)")
    return fig.svg("trace plots and posterior histograms of the fitted offsets")


def error_figure(result: FitResult, data: Dataset) -> str:
    """Post-registration error (eq. 18) per measurement and against the distance from the sensor,
    before (nominal offsets) and after (applied offsets); two ``<svg>`` side by side."""
    chain = Chain(result.model)
    before = absolute_errors(data, predicted_base(chain, data, np.zeros(chain.n)))
    after = absolute_errors(data, predicted_base(chain, data, result.applied_offsets_rad))
    idx = np.arange(len(data), dtype=float)
    dist = np.linalg.norm(data.xyz_mm, axis=1) / 1000.0
    out = []
    for x, xlabel in ((idx, "measurement (row)"), (dist, "distance from the sensor (m)")):
        out.append(error_scatter(x, before, after, xlabel=xlabel, ylabel="error after registration, eq. 18 (mm)",
                                 labels=("before (nominal offsets)", "after (applied offsets)"),
                                 alt=f"post-registration error against {xlabel}, before and after"))
    return side_by_side(out)


def error_scatter(x: np.ndarray, before: np.ndarray, after: np.ndarray, *, xlabel: str, ylabel: str,
                  labels: tuple[str, str], alt: str, width: float = 480, logy: bool = False) -> str:
    """Errors (mm) before (red) and after (green) against ``x`` (k,), one ``<svg>`` ``width`` px
    wide; from 0 up (``logy``: on a log scale around the data)."""
    both = np.concatenate([before, after])
    ylim = data_limits(both, log=True) if logy else (min(0.0, float(both.min())), data_limits(both)[1])
    xlim = data_limits(x)
    fig = Figure(width, 300)
    ax = fig.axes((64, 14, width - 80, 220), xlim, ylim, logy=logy)
    ax.scatter(x, before, size=4, color=COLOURS["red"], label=labels[0])
    ax.scatter(x, after, size=4, color=COLOURS["green"], label=labels[1])
    ax.frame(xlabel=xlabel, ylabel=ylabel)
    y = np.log10(both) if logy else both
    ax.legend(_emptiest_corner(np.column_stack([np.concatenate([x, x]), y]), xlim, tuple(np.log10(ylim)) if logy else ylim))
    return fig.svg(alt)
