"""Which parameters (or combinations) a dataset can determine, from the Jacobian's singular values.

Columns are made comparable first: angles are multiplied by a lever arm (mm per rad, the RMS
distance of the measured points from the robot base), so every singular value is in mm of marker
motion per unit of scaled parameter. A singular value below ``rel_tol`` × the largest marks an
exactly undetermined combination (a structural null space, e.g. the first joint's offset and a
rotation of the sensor registration about the base z axis); the right singular vector says which
parameters take part.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Combination:
    """An undetermined direction: parameter name → loading (unit vector in scaled units)."""

    loadings: dict[str, float]
    singular_value: float

    def describe(self) -> str:
        parts = sorted(self.loadings.items(), key=lambda kv: -abs(kv[1]))
        return " ".join(f"{v:+.2f}·{k}" for k, v in parts)


@dataclass(frozen=True)
class Identifiability:
    names: list[str]
    singular_values: np.ndarray
    condition_number: float
    rank: int
    null_space: list[Combination] = field(default_factory=list)

    @property
    def deficient(self) -> bool:
        return self.rank < len(self.names)

    def to_dict(self) -> dict:
        return {
            "parameters": list(self.names),
            "singular_values_mm": [float(s) for s in self.singular_values],
            "condition_number": self.condition_number,
            "rank": self.rank,
            "undetermined_combinations": [
                {"combination": c.describe(), "singular_value_mm": c.singular_value, "loadings": c.loadings}
                for c in self.null_space
            ],
        }


def analyse(jacobian: np.ndarray, names: list[str], scale: np.ndarray, *, rel_tol: float = 1e-7, min_loading: float = 0.05) -> Identifiability:
    """SVD of ``jacobian`` (m, p) with columns multiplied by ``scale`` (p,)."""
    j = np.asarray(jacobian, dtype=float) / np.asarray(scale, dtype=float)
    _, s, vt = np.linalg.svd(j, full_matrices=False)
    smax = s[0] if s.size else 0.0
    tol = rel_tol * smax
    rank = int(np.sum(s > tol))
    null = []
    for k in range(rank, len(s)):
        v = vt[k]
        v = v * np.sign(v[np.argmax(np.abs(v))])
        null.append(Combination({names[i]: float(v[i]) for i in np.flatnonzero(np.abs(v) >= min_loading)}, float(s[k])))
    cond = float(smax / s[-1]) if s.size and s[-1] > 0 else float("inf")
    return Identifiability(list(names), s, cond, rank, null)
