"""Staged, multi-start least squares: solve from several starts, keep the best, say when the
starts disagree.

A Levenberg–Marquardt run finds the minimum nearest its start. A staged solve first frees only
the parameters that are nearly linear and well determined (registration, marker positions,
joint offsets), then all of them from there; random starts probe whether another minimum is
lower. Costs are ½·Σ r² of one fixed objective, so starts compare directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

Residuals = Callable[[np.ndarray], np.ndarray]


@dataclass
class StartOutcome:
    """One start: its label, the solution z (n,), cost ½·Σ r², evaluations, and the Jacobian
    (rows, n) and residuals at the solution."""

    label: str
    z: np.ndarray
    cost: float
    nfev: int
    jac: np.ndarray
    fun: np.ndarray


def lm(fun: Residuals, jac: Callable[[np.ndarray], np.ndarray], z0: np.ndarray, cols: np.ndarray | None = None,
       max_nfev: int = 200) -> tuple[np.ndarray, int]:
    """Levenberg–Marquardt over the columns ``cols`` of z (all if None), the rest held at ``z0``.
    Returns (z (n,), evaluations)."""
    if cols is None or cols.size == z0.size:
        sol = least_squares(fun, z0, jac=jac, method="lm", max_nfev=max_nfev, xtol=1e-12, ftol=1e-12)
        return sol.x, int(sol.nfev)

    def sub(zs):
        z = z0.copy()
        z[cols] = zs
        return z

    sol = least_squares(lambda zs: fun(sub(zs)), z0[cols], jac=lambda zs: jac(sub(zs))[:, cols], method="lm",
                        max_nfev=max_nfev, xtol=1e-12, ftol=1e-12)
    return sub(sol.x), int(sol.nfev)


def solve_from(label: str, fun: Residuals, jac: Callable[[np.ndarray], np.ndarray], z0: np.ndarray,
               stages: list[np.ndarray | None], max_nfev: int = 200) -> StartOutcome:
    """Solve the stages in turn (each an index array of the columns it frees; None: all) from z0."""
    z, nfev = z0.copy(), 0
    for cols in stages:
        z, n = lm(fun, jac, z, cols, max_nfev)
        nfev += n
    r = fun(z)
    return StartOutcome(label, z, 0.5 * float(r @ r), nfev, jac(z), r)


def disagreement(outcomes: list[StartOutcome], rel: float, floor: float = 0.0) -> list[StartOutcome]:
    """The starts whose cost is more than ``rel`` (relative) and more than ``floor`` (absolute, the
    cost's units) above the best's: on noise-free data, rounding-level costs differ by any ratio."""
    best = min(o.cost for o in outcomes)
    return [o for o in outcomes if o.cost - best > max(rel * best, floor)]
