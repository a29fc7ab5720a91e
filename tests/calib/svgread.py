"""Read the report's inline SVG figures back into numbers, independently of ``calib.report.svg``.

Each ``<g class="axes">`` states its pixel box and data limits; a scatter's dots are the
``M x y h0`` moves of its paths, a line the points of its polyline. ``points`` maps them back to
data units, so a test can compare a figure with the arrays it was drawn from (to the 0.1 px the
SVG is written with).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

NS = "{http://www.w3.org/2000/svg}"
SVG = re.compile(r"<svg\b.*?</svg>", re.S)


def svgs(page: str) -> list[ET.Element]:
    """Every inline ``<svg>`` of ``page``, parsed as XML (so each must be well-formed)."""
    return [ET.fromstring(s) for s in SVG.findall(page)]


def texts(svg: ET.Element) -> list[str]:
    return ["".join(t.itertext()) for t in svg.iter(f"{NS}text")]


@dataclass
class AxesRead:
    element: ET.Element
    box: tuple[float, float, float, float]
    xlim: tuple[float, float]
    ylim: tuple[float, float]
    logy: bool

    def to_data(self, px: np.ndarray) -> np.ndarray:
        """(k, 2) pixel coordinates → (k, 2) data coordinates."""
        x0, y0, w, h = self.box
        (a, b), (c, d) = self.xlim, self.ylim
        if self.logy:
            c, d = math.log10(c), math.log10(d)
        x = a + (px[:, 0] - x0) / w * (b - a)
        y = c + (y0 + h - px[:, 1]) / h * (d - c)
        return np.column_stack([x, 10**y if self.logy else y])

    def resolution(self) -> tuple[float, float]:
        """Data units per 0.1 px along x and y (linear axes)."""
        return 0.1 * (self.xlim[1] - self.xlim[0]) / self.box[2], 0.1 * (self.ylim[1] - self.ylim[0]) / self.box[3]

    def series(self, cls: str, label: str | None = None) -> list[ET.Element]:
        return [e for e in self.element.iter() if e.get("class") == cls and (label is None or e.get("data-label") == label)]

    def scatter(self, label: str | None = None) -> np.ndarray:
        """The dots of the scatter(s) with ``label`` (all unlabelled ones if None), (k, 2) data units."""
        groups = [g for g in self.series("scatter") if g.get("data-label") == label]
        moves = [m for g in groups for p in g.iter(f"{NS}path") for m in re.findall(r"M([-\d.]+) ([-\d.]+)h0", p.get("d"))]
        return self.to_data(np.array(moves, dtype=float).reshape(-1, 2))

    def lines(self) -> list[np.ndarray]:
        return [self.to_data(np.array(e.get("points").split(), dtype=float).reshape(-1, 2)) for e in self.series("line")]

    def markers(self) -> dict[str | None, np.ndarray]:
        return {e.get("data-label"): self.to_data(np.array([[float(e.get("cx")), float(e.get("cy"))]]))[0]
                for e in self.series("marker")}


def axes(svg: ET.Element) -> list[AxesRead]:
    out = []
    for g in svg.iter(f"{NS}g"):
        if g.get("class") == "axes":
            box = tuple(float(v) for v in g.get("data-box").split())
            xlim = tuple(float(v) for v in g.get("data-xlim").split())
            ylim = tuple(float(v) for v in g.get("data-ylim").split())
            out.append(AxesRead(g, box, xlim, ylim, g.get("data-logy") == "1"))
    return out
