"""Plots as inline SVG, written directly: axes with ticks, grid and labels; scatter, lines, stairs,
markers, arrows and a legend. Enough for the report's figures, and nothing to import but numpy.

A :class:`Figure` is one ``<svg>`` of ``width`` × ``height`` px (its ``viewBox``: it scales down
to a phone's width). :meth:`Figure.axes` places an :class:`Axes` at a pixel box with data
limits; its drawing methods map data to pixels (y upwards; ``logy`` for a log scale). Pixel
coordinates are written to 0.1 px.

The SVG carries its data for a reader or a test: each axes is a ``<g class="axes">`` with
``data-box="x y w h"`` (px) and ``data-xlim`` / ``data-ylim`` (data units; for ``logy`` the
limits themselves, not their logarithms); each series is an element with ``class`` (``scatter``,
``line``, ``marker``, ``stairs``, ``hline``) and, when labelled, ``data-label``; a scatter's
points are ``M x y h0`` dots of its ``<path>`` elements.
"""

from __future__ import annotations

import html
import math
from dataclasses import dataclass, field

import numpy as np

#: matplotlib's default colour cycle ("tab10") and the named colours the report uses.
TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
COLOURS = {"blue": TAB10[0], "orange": TAB10[1], "green": TAB10[2], "red": TAB10[3], "gold": "#ffd700",
           "goldenrod": "#daa520", "grey": "#666666", "black": "#000000"}

#: Dots per ``<path>`` of a scatter. A path's stroke is painted once, so its own dots never
#: darken each other; splitting the dots over many paths lets a translucent cloud show its density.
DOTS_PER_PATH = 100

FONT = "font-family:system-ui,sans-serif"


def esc(text: str) -> str:
    return html.escape(str(text), quote=True)


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """At most ``n + 1`` round values (1, 2, 2.5, 5 × 10^k apart) within [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if math.isfinite(lo) else np.zeros(0)
    raw = (hi - lo) / max(n, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    ticks = np.arange(first, math.floor(hi / step + 1e-9) + 1) * step
    return np.round(ticks / step) * step


def tick_labels(ticks: np.ndarray) -> list[str]:
    """The ticks with the decimals their spacing needs, a true minus sign, no "−0.00"."""
    t = np.asarray(ticks, dtype=float)
    if t.size < 2:
        return [f"{v:.4g}".replace("-", "−") for v in t]
    step = float(np.min(np.diff(t)))
    decimals = 0
    while decimals < 12 and abs(step * 10**decimals - round(step * 10**decimals)) > 1e-6 * step * 10**decimals:
        decimals += 1
    out = []
    for v in t:
        text = f"{v:.{decimals}f}"
        out.append(text.lstrip("-") if float(text) == 0 else text.replace("-", "−"))
    return out


def log_ticks(lo: float, hi: float) -> np.ndarray:
    """Powers of ten within [lo, hi] (lo > 0); with 1, 2, 5 × 10^k when fewer than two decades fit."""
    k0, k1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    decades = [10.0**k for k in range(k0, k1 + 1) if lo <= 10.0**k <= hi]
    if len(decades) >= 2:
        return np.array(decades)
    return np.array([m * 10.0**k for k in range(k0, k1 + 1) for m in (1, 2, 5) if lo <= m * 10.0**k <= hi])


def _coords(x: np.ndarray, y: np.ndarray) -> list[str]:
    return [f"{a:.1f} {b:.1f}" for a, b in zip(x.tolist(), y.tolist())]


@dataclass
class Axes:
    """A plotting box: ``box`` (x, y, w, h) px from the figure's top left; ``xlim``/``ylim`` data."""

    box: tuple[float, float, float, float]
    xlim: tuple[float, float]
    ylim: tuple[float, float]
    logy: bool = False
    parts: list[str] = field(default_factory=list)
    legend_entries: list[tuple[str, str]] = field(default_factory=list)  # (label, symbol markup)
    grid: str = ""
    decor: list[str] = field(default_factory=list)

    def _ty(self, y: np.ndarray) -> np.ndarray:
        return np.log10(y) if self.logy else y

    def px(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Data (x, y) → pixel (X, Y) of the figure."""
        x0, y0, w, h = self.box
        (a, b), (c, d) = self.xlim, self._ty(np.asarray(self.ylim, dtype=float))
        X = x0 + (np.asarray(x, dtype=float) - a) / (b - a) * w
        Y = y0 + h - (self._ty(np.asarray(y, dtype=float)) - c) / (d - c) * h
        return X, Y

    def inside(self, x, y) -> np.ndarray:
        """Mask of the points within the limits (what a scatter draws)."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        (a, b), (c, d) = self.xlim, self.ylim
        return (x >= a) & (x <= b) & (y >= c) & (y <= d)

    def _attrs(self, cls: str, label: str | None) -> str:
        return f'class="{cls}"' + (f' data-label="{esc(label)}"' if label else "")

    def scatter(self, x, y, *, color: str, size: float = 2.0, opacity: float = 1.0, label: str | None = None) -> int:
        """Round dots of diameter ``size`` px at the points within the limits; returns how many."""
        keep = self.inside(x, y)
        X, Y = self.px(np.asarray(x, dtype=float)[keep], np.asarray(y, dtype=float)[keep])
        dots = [f"M{c}h0" for c in _coords(X, Y)]
        paint = f'fill="none" stroke="{color}" stroke-width="{size:g}" stroke-linecap="round" stroke-opacity="{opacity:g}"'
        paths = "".join(f'<path d="{"".join(dots[i:i + DOTS_PER_PATH])}"/>' for i in range(0, len(dots), DOTS_PER_PATH))
        self.parts.append(f'<g {self._attrs("scatter", label)} data-n="{len(dots)}" {paint}>{paths}</g>')
        if label:
            self.legend_entries.append((label, f'<circle r="{max(size, 4) / 2:g}" fill="{color}"/>'))
        return len(dots)

    def line(self, x, y, *, color: str, width: float = 1.0, label: str | None = None) -> None:
        X, Y = self.px(x, y)
        self.parts.append(f'<polyline {self._attrs("line", label)} fill="none" stroke="{color}" stroke-width="{width:g}" '
                          f'stroke-linejoin="round" points="{" ".join(_coords(X, Y))}"/>')
        if label:
            self.legend_entries.append((label, f'<path d="M-8 0h16" stroke="{color}" stroke-width="{max(width, 1.5):g}"/>'))

    def marker(self, x: float, y: float, *, color: str, size: float = 8.0, label: str | None = None) -> None:
        """One filled circle with a black rim, ``size`` px across."""
        X, Y = self.px(x, y)
        self.parts.append(f'<circle {self._attrs("marker", label)} cx="{float(X):.1f}" cy="{float(Y):.1f}" '
                          f'r="{size / 2:g}" fill="{color}" stroke="#000" stroke-width="0.6"/>')
        if label:
            self.legend_entries.append((label, f'<circle r="{size / 2:g}" fill="{color}" stroke="#000" stroke-width="0.6"/>'))

    def arrow(self, start: tuple[float, float], end: tuple[float, float], *, color: str = "#666666") -> None:
        """A thin line from ``start`` to ``end`` with an open head at ``end`` (data units)."""
        (x0, x1), (y0, y1) = self.px([start[0], end[0]], [start[1], end[1]])
        dx, dy = x1 - x0, y1 - y0
        length = math.hypot(dx, dy)
        if length < 1e-9:
            return
        ux, uy = dx / length, dy / length
        head = [(x1 - 7 * ux + 3.5 * s * uy, y1 - 7 * uy - 3.5 * s * ux) for s in (1, -1)]
        self.parts.append(f'<path class="arrow" fill="none" stroke="{color}" stroke-width="1" d="M{x0:.1f} {y0:.1f}L{x1:.1f} {y1:.1f}'
                          f'M{head[0][0]:.1f} {head[0][1]:.1f}L{x1:.1f} {y1:.1f}L{head[1][0]:.1f} {head[1][1]:.1f}"/>')

    def hline(self, y: float, *, color: str = "#000", width: float = 1.0) -> None:
        x0, _, w, _ = self.box
        _, Y = self.px(self.xlim[0], y)
        self.parts.append(f'<path class="hline" data-y="{y:.6g}" stroke="{color}" stroke-width="{width:g}" d="M{x0:.1f} {float(Y):.1f}h{w:.1f}"/>')

    def stairs_horizontal(self, counts: np.ndarray, edges: np.ndarray, *, color: str, opacity: float = 0.8) -> None:
        """A histogram lying on its side: bin ``edges`` (k + 1,) along y, ``counts`` (k,) along x
        from the left edge; one filled path."""
        xs = np.repeat(np.asarray(counts, dtype=float), 2)
        ys = np.repeat(np.asarray(edges, dtype=float), 2)[1:-1]
        X, Y = self.px(np.concatenate([[0.0], xs, [0.0]]), np.concatenate([[edges[0]], ys, [edges[-1]]]))
        self.parts.append(f'<path class="stairs" data-bins="{len(counts)}" data-total="{int(np.sum(counts))}" fill="{color}" '
                          f'fill-opacity="{opacity:g}" d="M{"L".join(_coords(X, Y))}Z"/>')

    def frame(self, *, title: str = "", xlabel: str = "", ylabel: str = "", xticks: bool = True, yticks: bool = True,
              grid: bool = False, font: float = 10.0, nbins: int = 5, ynbins: int | None = None) -> None:
        """Spines, ticks with labels (``xticks``/``yticks`` False: ticks without labels), grid, title
        and axis labels."""
        x0, y0, w, h = self.box
        out = []
        xt = nice_ticks(*self.xlim, nbins)
        yt = log_ticks(*self.ylim) if self.logy else nice_ticks(*self.ylim, ynbins or nbins)
        X, _ = self.px(xt, np.full(xt.shape, self.ylim[0]))
        _, Y = self.px(np.full(yt.shape, self.xlim[0]), yt)
        ticks = "".join(f"M{x:.1f} {y0 + h:.1f}v4" for x in X) + "".join(f"M{x0:.1f} {y:.1f}h-4" for y in Y)
        if grid:  # drawn under the data (``svg``)
            self.grid = ('<path class="grid" stroke="#ddd" stroke-width="0.6" d="' + "".join(f"M{x:.1f} {y0:.1f}v{h:.1f}" for x in X)
                         + "".join(f"M{x0:.1f} {y:.1f}h{w:.1f}" for y in Y) + '"/>')
        out.append(f'<path class="ticks" stroke="#000" stroke-width="0.8" d="{ticks}"/>')
        if xticks:
            out += [f'<text x="{x:.1f}" y="{y0 + h + 6 + font:.1f}" text-anchor="middle">{esc(t)}</text>'
                    for x, t in zip(X, tick_labels(xt))]
        if yticks:
            labels = [_pow10(v) for v in yt] if self.logy else tick_labels(yt)
            out += [f'<text x="{x0 - 6:.1f}" y="{y + font * 0.35:.1f}" text-anchor="end">{esc(t)}</text>' for y, t in zip(Y, labels)]
        if title:
            out.append(f'<text x="{x0 + w / 2:.1f}" y="{y0 - 6:.1f}" text-anchor="middle" font-size="{font * 1.1:g}">{esc(title)}</text>')
        if xlabel:
            out.append(f'<text class="xlabel" x="{x0 + w / 2:.1f}" y="{y0 + h + 2 * font + 12:.1f}" text-anchor="middle">{esc(xlabel)}</text>')
        if ylabel:
            yx, yy = x0 - 4.2 * font, y0 + h / 2
            out.append(f'<text class="ylabel" x="{yx:.1f}" y="{yy:.1f}" text-anchor="middle" transform="rotate(-90 {yx:.1f} {yy:.1f})">'
                       f"{esc(ylabel)}</text>")
        out.append(f'<rect fill="none" stroke="#000" stroke-width="0.8" x="{x0:.1f}" y="{y0:.1f}" width="{w:.1f}" height="{h:.1f}"/>')
        self.decor = out

    def legend(self, corner: str = "upper right", *, font: float = 9.0) -> None:
        """The labelled series in a box at ``corner`` ("upper left", "lower right", …)."""
        if not self.legend_entries:
            return
        x0, y0, w, h = self.box
        row = font * 1.5
        width = 30 + 0.56 * font * max(len(label) for label, _ in self.legend_entries)
        height = row * len(self.legend_entries) + 6
        lx = x0 + 6 if "left" in corner else x0 + w - 6 - width
        ly = y0 + 6 if "upper" in corner else y0 + h - 6 - height
        out = [f'<g class="legend" transform="translate({lx:.1f} {ly:.1f})">',
               f'<rect width="{width:.1f}" height="{height:.1f}" rx="3" fill="#fff" fill-opacity="0.85" stroke="#ccc"/>']
        for k, (label, symbol) in enumerate(self.legend_entries):
            y = 3 + row * (k + 0.5)
            out.append(f'<g transform="translate(14 {y:.1f})">{symbol}</g>'
                       f'<text x="28" y="{y + font * 0.35:.1f}" font-size="{font:g}">{esc(label)}</text>')
        out.append("</g>")
        self.decor += out

    def svg(self) -> str:
        x0, y0, w, h = self.box
        ylim = " ".join(f"{v:.6g}" for v in self.ylim)
        return (f'<g class="axes" data-box="{x0:.1f} {y0:.1f} {w:.1f} {h:.1f}" data-xlim="{self.xlim[0]:.6g} {self.xlim[1]:.6g}" '
                f'data-ylim="{ylim}"' + (' data-logy="1"' if self.logy else "") + ">"
                + self.grid + "".join(self.parts) + "".join(self.decor) + "</g>")


def _pow10(v: float) -> str:
    """A log-axis label: 0.01, 0.1, 1, 10, 100 plainly; 10ⁿ beyond."""
    k = math.log10(v)
    if abs(k - round(k)) < 1e-9 and not -2 <= round(k) <= 3:
        return "10" + str(int(round(k))).translate(str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹"))
    return f"{v:g}"


@dataclass
class Figure:
    """One ``<svg>``: ``width`` × ``height`` px, font ``font`` px."""

    width: float
    height: float
    font: float = 10.0
    axes_list: list[Axes] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)

    def axes(self, box: tuple[float, float, float, float], xlim: tuple[float, float], ylim: tuple[float, float], *,
             logy: bool = False) -> Axes:
        if not (xlim[1] > xlim[0] and ylim[1] > ylim[0]) or (logy and ylim[0] <= 0):
            raise ValueError(f"axis limits must be increasing (and positive on a log scale), given x {xlim}, y {ylim}")
        ax = Axes(tuple(float(v) for v in box), tuple(float(v) for v in xlim), tuple(float(v) for v in ylim), logy=logy)
        self.axes_list.append(ax)
        return ax

    def text(self, x: float, y: float, text: str, *, size: float | None = None, anchor: str = "middle") -> None:
        self.texts.append(f'<text x="{x:.1f}" y="{y:.1f}" text-anchor="{anchor}" font-size="{size or self.font * 1.1:g}">{esc(text)}</text>')

    def svg(self, alt: str) -> str:
        """The figure as an inline ``<svg>`` with ``alt`` as its accessible name."""
        body = "".join(ax.svg() for ax in self.axes_list) + "".join(self.texts)
        return (f'<svg class="fig" xmlns="http://www.w3.org/2000/svg" role="img" aria-label="{esc(alt)}" '
                f'width="{self.width:g}" height="{self.height:g}" viewBox="0 0 {self.width:g} {self.height:g}" '
                f'style="{FONT}" font-size="{self.font:g}"><title>{esc(alt)}</title>{body}</svg>')


def data_limits(values: np.ndarray, pad: float = 0.05, *, log: bool = False) -> tuple[float, float]:
    """Limits around ``values`` with ``pad`` of their range on each side (a fraction of a decade
    on a log scale); a small range around a single value."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v) & (v > 0)] if log else v[np.isfinite(v)]
    if v.size == 0:
        return (0.1, 10.0) if log else (0.0, 1.0)
    if log:
        lo, hi = math.log10(v.min()), math.log10(v.max())
        span = max(hi - lo, 0.1)
        return 10 ** (lo - pad * span), 10 ** (hi + pad * span)
    lo, hi = float(v.min()), float(v.max())
    span = hi - lo if hi > lo else max(abs(lo), 1.0) * 0.1
    return lo - pad * span, hi + pad * span
