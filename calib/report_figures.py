"""The report's figures, as inline PNG ``<img>`` tags; matplotlib is imported only when drawing.

No pyplot: each figure is a ``matplotlib.figure.Figure`` rendered by the Agg canvas, so drawing
needs no display, touches no global state and is safe in the daemon's worker threads.

``tcp_clouds`` computes the paper's Fig. 5 (Sec. V-C): for chosen measured configurations, the
TCP (flange origin, robot base frame, mm) predicted with the nominal offsets ("before", red),
with the applied offsets ("after", green), with posterior draws of the offsets (yellow) and with
those draws plus the isotropic error σ (blue). ``tcp_cloud_figure`` draws it per configuration:
the top row at a scale that shows the move from before to after, the bottom row zoomed on the
after-clouds. X–Y plane of the robot base, as in the paper.
"""

from __future__ import annotations

import base64
import io
import math
from dataclasses import dataclass

import numpy as np

from calib.dataset import Dataset
from calib.fit import FitResult
from calib.kinematics import Chain, offset_kinematics
from calib.metrics import absolute_errors, predicted_base


#: Draws per chain shown in a trace plot: a line of 1000 points at this width is a smear of the
#: same envelope; every ``step``-th draw keeps the mixing visible at a fraction of the cost.
TRACE_POINTS = 250


def _figure(width_in: float, height_in: float, *, left: float = 0.7, right: float = 0.15, bottom: float = 0.5,
            top: float = 0.3, wspace: float = 0.35, hspace: float = 0.45):
    """A bare Agg figure with fixed margins in inches (no layout engine: constrained layout
    measured every tick label and cost more than drawing the report's plots)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: keeps matplotlib out of the CLI's start-up
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=left / width_in, right=1 - right / width_in, bottom=bottom / height_in,
                        top=1 - top / height_in, wspace=wspace, hspace=hspace)
    return fig


def png(fig, alt: str, dpi: int = 100) -> str:
    """``fig`` as an inline ``<img>`` (PNG, base64), drawn by the Agg canvas."""
    buf = io.BytesIO()
    # zlib level 1: a few per cent larger than the default 6 and about half its encoding time
    fig.savefig(buf, format="png", dpi=dpi, pil_kwargs={"compress_level": 1})
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img alt="{alt}" src="data:image/png;base64,{data}">'


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
    """The legend location (matplotlib's corner names) whose corner — 45 % × 35 % of the axes —
    holds the fewest of ``points`` (j, 2), data coordinates. matplotlib's ``loc="best"`` finds
    the same by testing every vertex of every artist in Python, and cost a third of the figure."""
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
    """The paper's Fig. 5, one column per configuration; returns an ``<img>`` tag.

    Top row: before (red), after (green), draws + σ (blue) and offset draws (yellow) at a scale
    that shows the move. Bottom row: zoomed on the offset draws alone (with the after point), the
    part of the error the offsets' uncertainty leaves.
    """
    k = len(clouds.rows)
    fig = _figure(3.4 * k + 0.4, 6.8, left=0.6, wspace=0.45, hspace=0.35)
    ax = fig.subplots(2, k, squeeze=False)
    for c in range(k):
        origin = clouds.after[c, :2]
        b, a = clouds.before[c, :2] - origin, np.zeros(2)
        d, nz = clouds.draws[c, :, :2] - origin, clouds.noisy[c, :, :2] - origin
        top, bottom = ax[0, c], ax[1, c]
        top.scatter(nz[:, 0], nz[:, 1], s=2, color="tab:blue", alpha=0.35, lw=0, label="offset draws + σ", rasterized=True)
        top.scatter(d[:, 0], d[:, 1], s=2, color="gold", alpha=0.9, lw=0, label="offset draws", rasterized=True)
        top.annotate("", xy=a, xytext=b, arrowprops={"arrowstyle": "->", "color": "0.4", "lw": 0.8})
        top.plot(*a, "o", color="tab:green", ms=6, mec="k", mew=0.5, label="after")
        top.plot(*b, "o", color="tab:red", ms=6, mec="k", mew=0.5, label="before")
        top.set_title(f"configuration {clouds.config[c]}: before → after {clouds.shift_mm[c]:.3g} mm", fontsize=8)
        lims = [_limits(np.vstack([nz, [a], [b]]))]
        bottom.scatter(d[:, 0], d[:, 1], s=3, color="goldenrod", alpha=0.6, lw=0, rasterized=True)
        bottom.plot(*a, "o", color="tab:green", ms=5, mec="k", mew=0.5)
        spread = np.percentile(np.linalg.norm(d, axis=1), 95)
        bottom.set_title(f"offset draws alone: 95 % within {spread:.2g} mm", fontsize=8)
        lo, hi = np.percentile(d, [0.5, 99.5], axis=0)
        lims.append(_limits(np.vstack([lo, hi, a])))
        for axc, (xl, yl) in zip((top, bottom), lims):
            axc.set_xlim(*xl)
            axc.set_ylim(*yl)
            axc.set_aspect("equal", adjustable="box")
            axc.tick_params(labelsize=7)
            axc.locator_params(nbins=5)
            axc.grid(True, lw=0.3)
            axc.set_xlabel("x − x_after (mm)", fontsize=7)
            axc.set_ylabel("y − y_after (mm)", fontsize=7)
    first = ax[0, 0]
    d0, nz0 = clouds.draws[0, :, :2] - clouds.after[0, :2], clouds.noisy[0, :, :2] - clouds.after[0, :2]
    corner = _emptiest_corner(np.vstack([nz0, d0, clouds.before[0, :2] - clouds.after[0, :2], [0.0, 0.0]]),
                              first.get_xlim(), first.get_ylim())
    leg = first.legend(fontsize=7, loc=corner, framealpha=0.8)
    for h in leg.legend_handles[:2]:
        h.set_sizes([16])
        h.set_alpha(1.0)
    return png(fig, "TCP cloud (Fig. 5): before, after, posterior draws of the offsets with and without σ")


def offset_trace_figure(result: FitResult) -> str | None:
    """Trace plots of the fitted offsets (degrees), each with its posterior histogram beside it on
    the same vertical scale; None when none is fitted."""
    post = result.posterior
    fitted = [i for i, s in enumerate(result.offset_status) if s == "fitted"]
    if not fitted:
        return None
    axes = result.model.axis_names
    full = post.full_vector(result.chains.samples[..., : post.dim])  # (c, d, n + …)
    fig = _figure(10, 1.5 * len(fitted) + 0.6, left=0.85, wspace=0.05, hspace=0.3, bottom=0.45)
    # The histogram shares its row's vertical axis and draws no axes of its own: tick labels are
    # most of a figure's drawing cost, and the counts say nothing the shape does not.
    ax = fig.subplots(len(fitted), 2, squeeze=False, gridspec_kw={"width_ratios": [4, 1]})
    step = max(1, math.ceil(full.shape[1] / TRACE_POINTS))
    x = np.arange(0, full.shape[1], step)
    for row, i in enumerate(fitted):
        trace, hist = ax[row]
        for c in range(full.shape[0]):
            trace.plot(x, np.degrees(full[c, ::step, i]), lw=0.5)
        trace.set_ylabel(f"δ{axes[i]} (°)", fontsize=8)
        trace.tick_params(labelsize=7)
        trace.locator_params(axis="y", nbins=4)
        counts, edges = np.histogram(np.degrees(full[..., i].ravel()), bins=40)
        hist.stairs(counts, edges, fill=True, color="tab:blue", alpha=0.8, orientation="horizontal")  # one artist
        hist.axhline(math.degrees(result.offsets_rad[i]), color="k", lw=1)
        hist.sharey(trace)
        hist.set_axis_off()
        if row < len(fitted) - 1:  # the draw axis is common: label it once, at the bottom
            trace.sharex(ax[-1, 0])
            trace.tick_params(labelbottom=False)
    ax[0, 0].set_title("trace plots (one colour per chain)", fontsize=9)
    ax[0, 1].set_title("posterior (line: mean)", fontsize=9)
    ax[-1, 0].set_xlabel(f"draw (every {step}th shown)" if step > 1 else "draw", fontsize=8)
    return png(fig, "trace plots and posterior histograms of the fitted offsets", dpi=90)


def error_figure(result: FitResult, data: Dataset) -> str:
    """Post-registration error (eq. 18) per measurement and against the distance from the sensor,
    before (nominal offsets) and after (applied offsets)."""
    chain = Chain(result.model)
    before = absolute_errors(data, predicted_base(chain, data, np.zeros(chain.n)))
    after = absolute_errors(data, predicted_base(chain, data, result.applied_offsets_rad))
    fig = _figure(10, 3.4, wspace=0.25)
    ax = fig.subplots(1, 2)
    idx = np.arange(len(data))
    dist = np.linalg.norm(data.xyz_mm, axis=1) / 1000.0
    for a, x, xlabel in ((ax[0], idx, "measurement (row)"), (ax[1], dist, "distance from the sensor (m)")):
        a.plot(x, before, ".", color="tab:red", label="before (nominal offsets)")
        a.plot(x, after, ".", color="tab:green", label="after (applied offsets)")
        a.set_xlabel(xlabel, fontsize=8)
        a.set_ylabel("error after registration, eq. 18 (mm)", fontsize=8)
        a.tick_params(labelsize=7)
        a.legend(fontsize=7)
    return png(fig, "post-registration error per measurement, before and after", dpi=90)
