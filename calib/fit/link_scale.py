"""Empirical Bayes for the link prior: one scale for the lengths (d, a; mm) and one for the angles
(α, β; degrees), each the value that maximises the Laplace evidence of the data.

A robot's link errors are not the same size in millimetres and in degrees (a Franka Panda's
published corrections: 0.2–0.9 mm and 0.1–0.66°), so one scale for both — or a fixed ratio —
is too tight for one group or too loose for the other. ``maximise_evidence`` searches the grid
``LENGTHS_MM`` × ``ANGLES_DEG`` by hill-climbing from the grid's middle (the four neighbours of
the current pair, a step to the best of them while that raises the evidence), so a fit costs
about a dozen evidence evaluations instead of the whole grid; the evidence of one scale group is
in practice single-peaked on these grids. The evidence itself is the caller's (``calib.fit.model_choice``
for tracker/mocap data, ``calib.fit.socket_choice`` for socket data).
"""

from __future__ import annotations

import math
from typing import Callable

#: Grid of the length scale (sd of d and a about the data sheet, mm), about half a decade apart.
LENGTHS_MM = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
#: Grid of the angle scale (sd of α and β, degrees).
ANGLES_DEG = (0.003, 0.01, 0.03, 0.1, 0.3, 1.0)


def maximise_evidence(evidence: Callable[[float, float], float], lengths_mm: tuple[float, ...] = LENGTHS_MM,
                      angles_deg: tuple[float, ...] = ANGLES_DEG, *, exhaustive: bool = False) -> dict:
    """The (length mm, angle deg) pair of the grids with the largest ``evidence(mm, deg)`` reached by
    hill-climbing (``exhaustive``: every pair, for a cheap ``evidence``). Returns {"length_mm", "angle_deg", "log_evidence": {"mm/deg": value, …}
    (every pair evaluated), "at_grid_edge": [which scale sits at the end of its grid]}."""
    seen: dict[tuple[float, float], float] = {}

    def ev(mm: float, deg: float) -> float:
        if (mm, deg) not in seen:
            v = evidence(mm, deg)
            seen[(mm, deg)] = v if math.isfinite(v) else -math.inf
        return seen[(mm, deg)]

    i, j = len(lengths_mm) // 2, len(angles_deg) // 2
    if exhaustive:
        i, j = max(((a, b) for a in range(len(lengths_mm)) for b in range(len(angles_deg))),
                   key=lambda ab: ev(lengths_mm[ab[0]], angles_deg[ab[1]]))
    while not exhaustive:
        steps = [(a, b) for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1))
                 if 0 <= a < len(lengths_mm) and 0 <= b < len(angles_deg)]
        best = max(steps, key=lambda ab: ev(lengths_mm[ab[0]], angles_deg[ab[1]]))
        if ev(lengths_mm[best[0]], angles_deg[best[1]]) <= ev(lengths_mm[i], angles_deg[j]):
            break
        i, j = best
    mm, deg = lengths_mm[i], angles_deg[j]
    edge = [name for name, v, grid in (("length", mm, lengths_mm), ("angle", deg, angles_deg))
            if v in (grid[0], grid[-1])]
    return {"length_mm": mm, "angle_deg": deg,
            "log_evidence": {f"{a:g} mm/{b:g}°": v for (a, b), v in seen.items()}, "at_grid_edge": edge}
