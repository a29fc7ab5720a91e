"""Which parameters (or combinations) a dataset can determine, from the Jacobian's singular values.

Columns are made comparable first: angles are multiplied by a lever arm (mm per rad, the RMS
distance of the measured points from the robot base), so every parameter is in mm of marker
motion ("scaled mm") and every singular value s is in mm of stacked marker motion per scaled mm
(dimensionless). Each right singular vector is a *combination* of parameters; the data determine
it to a standard deviation of σ / s scaled mm (σ: the per-axis measurement error, mm).

Two different questions, two different thresholds:

* **exact** null direction: s at or below what rounding leaves of a zero singular value,
  ``s ≤ s_max · max(rows, columns) · ε · EXACT_FACTOR`` (ε: float64 machine precision). Only
  a structural degeneracy gets there (e.g. the first joint's offset against a rotation of the
  sensor registration about the base z axis: s/s_max ≈ 1e-16).
* **numerical** null direction: s ≤ ``rel_tol`` · s_max but above rounding (condition number
  above 1/rel_tol, e.g. 5.7e9). The fit treats it like an exact one (fixes a parameter), but it
  is called "not determined at condition number …", never "exact".

``verdicts`` then grades every direction against the measurement noise (``Verdict``):
"not determined" (exact, or σ/s above the fit's useful limit), "weakly determined" (σ/s above
``WEAK_NOISE_FACTOR`` × σ) or "determined".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Rounding headroom over ``max(rows, columns) · ε`` (numpy's matrix_rank default has none).
EXACT_FACTOR = 10.0
#: A direction known worse than this many times the measurement noise σ is "weakly determined".
WEAK_NOISE_FACTOR = 10.0


def exact_tolerance(s_max: float, shape: tuple[int, int]) -> float:
    """Largest singular value that rounding alone can leave of an exact null direction."""
    return float(s_max) * max(shape) * np.finfo(float).eps * EXACT_FACTOR


def top_loadings(loadings: dict[str, float], *, share: float = 0.95, most: int = 4) -> list[tuple[str, float]]:
    """The largest components of a unit vector, by |weight|, until they hold ``share`` of its
    squared length (at most ``most``): [(parameter, weight)]."""
    items = sorted(loadings.items(), key=lambda kv: -abs(kv[1]))
    out, acc = [], 0.0
    for name, w in items:
        out.append((name, w))
        acc += w * w
        if acc >= share or len(out) >= most:
            break
    return out


def describe_loadings(loadings: dict[str, float], **kw) -> str:
    """``+0.88·mocap.x −0.33·A1.offset …`` (largest components, see ``top_loadings``)."""
    top = top_loadings(loadings, **kw)
    text = " ".join(f"{w:+.2f}·{k}" for k, w in top)
    rest = len([w for w in loadings.values() if w != 0.0]) - len(top)
    return text + (f" (+{rest} smaller)" if rest > 0 else "")


@dataclass(frozen=True)
class Combination:
    """A direction in parameter space: parameter name → loading (unit vector in scaled units).

    singular_value: s (mm per scaled mm); relative: s / s_max; exact: s is at rounding level.
    """

    loadings: dict[str, float]
    singular_value: float
    relative: float = 0.0
    exact: bool = True

    def describe(self) -> str:
        return describe_loadings(self.loadings)

    def explain(self) -> str:
        """Why this combination is not determined, in words an operator can act on."""
        if self.exact:
            return "an exact null direction (singular value at rounding level: no data of this kind can separate it)"
        cond = 1.0 / self.relative if self.relative > 0 else math.inf
        return (f"not determined at condition number {cond:.2g} (a weak direction above rounding level: "
                "configurations that move these parameters differently would separate them)")


@dataclass(frozen=True)
class Identifiability:
    """SVD summary. vectors: (p, p) right singular vectors as rows (scaled units), same order
    as ``singular_values`` (largest first); shape: the scaled Jacobian's (rows, p)."""

    names: list[str]
    singular_values: np.ndarray
    condition_number: float
    rank: int
    null_space: list[Combination] = field(default_factory=list)
    vectors: np.ndarray | None = None
    shape: tuple[int, int] = (0, 0)

    @property
    def deficient(self) -> bool:
        return self.rank < len(self.names)

    def directions(self, min_loading: float = 0.05) -> list[Combination]:
        """Every direction (largest singular value first) with its loadings ≥ ``min_loading``."""
        if self.vectors is None:
            return []
        s = np.asarray(self.singular_values, dtype=float)
        smax = float(s[0]) if s.size else 0.0
        tol = exact_tolerance(smax, self.shape)
        out = []
        for k, v in enumerate(self.vectors):
            v = v * np.sign(v[np.argmax(np.abs(v))])
            load = {self.names[i]: float(v[i]) for i in np.flatnonzero(np.abs(v) >= min_loading)}
            out.append(Combination(load, float(s[k]), float(s[k] / smax) if smax > 0 else 0.0, bool(s[k] <= tol)))
        return out

    def to_dict(self) -> dict:
        return {
            "parameters": list(self.names),
            "singular_values_mm": [float(s) for s in self.singular_values],
            "condition_number": self.condition_number,
            "rank": self.rank,
            "jacobian_shape": list(self.shape),
            "undetermined_combinations": [_combination_dict(c) for c in self.null_space],
            "directions": [_combination_dict(c) for c in self.directions()],
        }


def _combination_dict(c: Combination) -> dict:
    return {"combination": c.describe(), "singular_value_mm": c.singular_value, "relative": c.relative,
            "exact": c.exact, "loadings": c.loadings}


def analyse(jacobian: np.ndarray, names: list[str], scale: np.ndarray, *, rel_tol: float = 1e-7, min_loading: float = 0.05) -> Identifiability:
    """SVD of ``jacobian`` (m, p) with columns divided by ``scale`` (p,) (mm per unit).

    Directions with s ≤ ``rel_tol`` · s_max form ``null_space`` (the fit fixes a parameter for
    each); each says whether it is exact (``exact_tolerance``) or only numerically null.
    """
    j = np.asarray(jacobian, dtype=float) / np.asarray(scale, dtype=float)
    _, s, vt = np.linalg.svd(j, full_matrices=False)
    smax = s[0] if s.size else 0.0
    tol = rel_tol * smax
    exact = exact_tolerance(smax, j.shape)
    rank = int(np.sum(s > tol))
    null = []
    for k in range(rank, len(s)):
        v = vt[k]
        v = v * np.sign(v[np.argmax(np.abs(v))])
        null.append(Combination({names[i]: float(v[i]) for i in np.flatnonzero(np.abs(v) >= min_loading)}, float(s[k]),
                                float(s[k] / smax) if smax > 0 else 0.0, bool(s[k] <= exact)))
    cond = float(smax / s[-1]) if s.size and s[-1] > 0 else float("inf")
    return Identifiability(list(names), s, cond, rank, null, vt, tuple(j.shape))


@dataclass(frozen=True)
class Verdict:
    """One direction graded against the noise: std_mm = σ / s (scaled mm; an angle × lever arm)."""

    verdict: str  # "determined" | "weakly determined" | "not determined"
    why: str
    std_mm: float
    condition: float  # s_max / s


def verdicts(singular_values, shape: tuple[int, int], sigma_mm: float, undetermined_mm: float,
             weak_factor: float = WEAK_NOISE_FACTOR) -> list[Verdict]:
    """Grade each singular value (largest first) of a scaled Jacobian of ``shape`` (rows, p).

    sigma_mm: the measurement error per axis (mm); undetermined_mm: the std (scaled mm) beyond
    which a direction is of no use (the fit's per-offset limit × lever arm). Exact null
    directions (``exact_tolerance``) are "not determined" whatever the noise.
    """
    s = np.asarray(singular_values, dtype=float)
    if s.size == 0:
        return []
    smax = float(s[0])
    tol = exact_tolerance(smax, shape)
    out = []
    for sk in s:
        cond = smax / sk if sk > 0 else math.inf
        std = sigma_mm / sk if sk > 0 else math.inf
        if sk <= tol:
            out.append(Verdict("not determined", "exact null direction (singular value at rounding level)", math.inf, cond))
        elif std > undetermined_mm:
            out.append(Verdict("not determined", f"known only to ±{std:.3g} mm (limit {undetermined_mm:.3g} mm)", std, cond))
        elif std > weak_factor * sigma_mm:
            out.append(Verdict("weakly determined", f"known only to ±{std:.3g} mm, over {weak_factor:g} × σ", std, cond))
        else:
            out.append(Verdict("determined", f"±{std:.3g} mm", std, cond))
    return out


def undetermined(ident: Identifiability, min_loading: float = 0.05) -> dict[str, float]:
    """Parameters that take part in a null direction: name → the length of their loading in the
    null space (0…1; 1: the parameter alone is a null direction). Below ``min_loading``: left out."""
    if ident.vectors is None or not ident.deficient:
        return {}
    null = np.asarray(ident.vectors)[ident.rank:]  # (p − rank, p) orthonormal rows
    share = np.sqrt(np.sum(null ** 2, axis=0))
    return {n: float(v) for n, v in zip(ident.names, share) if v >= min_loading}


@dataclass(frozen=True)
class OrientationGain:
    """What measured orientations add to positions (same configurations, same parameters).

    newly_determined: parameters in a null direction of the position rows but not of the
    position + attitude rows; still_undetermined: in a null direction of both (e.g. the first
    joint's offset against the registration); std_ratio: for parameters determined both ways, the
    standard deviation with orientation over that without (scaled, same σ per scaled row; < 1:
    orientation sharpens it)."""

    newly_determined: list[str]
    still_undetermined: list[str]
    std_ratio: dict[str, float]
    positions: Identifiability
    poses: Identifiability

    def describe(self) -> str:
        new = ", ".join(self.newly_determined) or "nothing"
        still = ", ".join(self.still_undetermined) or "nothing"
        return (f"orientation makes determined what positions alone leave undetermined: {new}; undetermined either way: "
                f"{still}")

    def to_dict(self) -> dict:
        return {"newly_determined": self.newly_determined, "still_undetermined": self.still_undetermined,
                "std_ratio": self.std_ratio, "rank_positions": self.positions.rank, "rank_poses": self.poses.rank,
                "parameters": list(self.poses.names)}


def orientation_gain(j_positions: np.ndarray, j_poses: np.ndarray, names: list[str], scale: np.ndarray, *,
                     rel_tol: float = 1e-7, min_loading: float = 0.05) -> OrientationGain:
    """Compare the scaled Jacobian of the position rows (m, p) with that of position + attitude
    rows (m', p) over the same ``names`` (attitude rows already weighted into mm-equivalents)."""
    pos = analyse(j_positions, names, scale, rel_tol=rel_tol, min_loading=min_loading)
    both = analyse(j_poses, names, scale, rel_tol=rel_tol, min_loading=min_loading)
    u_pos, u_both = undetermined(pos, min_loading), undetermined(both, min_loading)
    ratio = {}
    determined = [i for i, n in enumerate(names) if n not in u_pos and n not in u_both]
    if determined:
        def stds(j):
            js = np.asarray(j, dtype=float) / np.asarray(scale, dtype=float)
            return np.sqrt(np.clip(np.diag(np.linalg.pinv(js.T @ js, rcond=rel_tol ** 2 * 1e2)), 0.0, None))
        sp, sb = stds(j_positions), stds(j_poses)
        ratio = {names[i]: float(sb[i] / sp[i]) for i in determined if sp[i] > 0}
    return OrientationGain([n for n in names if n in u_pos and n not in u_both], [n for n in names if n in u_both],
                           ratio, pos, both)
