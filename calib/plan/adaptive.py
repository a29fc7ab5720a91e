"""Sequential design: which configuration to measure next, and when to stop (issue 27).

The fit is linear enough about the nominal robot that its posterior covariance after a set of
configurations is, to first order, the inverse of the information they carry:

    I = P + Σ_c J_cᵀ J_c / σ²,    Σ = I⁻¹

with J_c (r, L) the Jacobian of configuration c's measured coordinates (mm) with respect to the
fit's L free parameters (offsets rad, registration mm/rad, link deviations mm/rad, tool mm,
compliances µrad/(N·m)), P (L, L) the prior precision (the link and tool priors of the fit, and
weak priors on the parameters the fit leaves flat so that Σ exists before the first
configuration) and σ the measurement noise per axis (mm). Σ does not depend on the measured
values, only on where the robot was and on σ — so the design needs no fit beyond σ.

Two quantities a metrologist states a stop rule in (``StopRule``):

* the half-width of every determinable offset's 95 % interval, ``T · sqrt(Σ_kk)`` (degrees;
  T = 2.228, the 97.5 % quantile of the Student t with 10 degrees of freedom that the Laplace
  fit draws from);
* the predicted workspace error, ``sqrt(trace(A Σ))`` (mm): the rms over the plan's
  configurations and markers of the calibrated model's position uncertainty as the sensor sees
  them (A = mean of J_wᵀ J_w over those points, registration included: what only redefines the
  model's base frame is no error). The rule compares it with what the full plan would reach
  (every candidate measured);
* the predicted held-out error, ``sqrt(3σ² + trace(A Σ))`` (mm): what validation on further
  configurations of the same workspace measures — the model's uncertainty and the sensor's
  noise — again against the full plan's. Where the noise dominates, a fraction of the plan
  predicts as well as all of it.

``SequentialDesign.choose`` picks among the remaining candidates the one with the largest
expected relative reduction of the stated quantities (A-optimal: the traces above; a rule with
both sums both relative reductions) per second of motion, settling and measuring from where the
robot stands (``seconds``, computed by the caller). The reduction of candidate c is exact for
the linear model (Woodbury): trace(A Σ) − trace(A Σ') = trace(A M S⁻¹ Mᵀ), M = Σ J_cᵀ,
S = σ² I_r + J_c Σ J_cᵀ.

Pure: numpy only, no I/O. Shapes: N candidates, r rows each, L parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: 97.5 % quantile of Student's t with 10 degrees of freedom (the Laplace fit's draws).
T95 = 2.2281388519649385


@dataclass(frozen=True)
class StopRule:
    """When a sequential run stops (every stated criterion must hold, after ``min_configurations``).

    interval_deg: every determinable offset's 95 % interval half-width ≤ this (deg), or None.
    workspace_within_pct: predicted workspace error ≤ (1 + pct/100) × the full plan's, or None.
    held_out_within_pct: predicted held-out error ≤ (1 + pct/100) × the full plan's, or None.
    min_configurations: never stop before this many measured configurations.
    max_configurations: stop at this many even if the criteria are not met (None: the plan's size).
    """

    interval_deg: float | None = None
    workspace_within_pct: float | None = None
    held_out_within_pct: float | None = None
    min_configurations: int = 1
    max_configurations: int | None = None

    def __post_init__(self) -> None:
        if self.interval_deg is None and self.workspace_within_pct is None and self.held_out_within_pct is None:
            raise ValueError("a stop rule needs interval_deg, workspace_within_pct or held_out_within_pct")
        if self.interval_deg is not None and not self.interval_deg > 0:
            raise ValueError(f"interval_deg must be > 0, given {self.interval_deg}")
        for name in ("workspace_within_pct", "held_out_within_pct"):
            if getattr(self, name) is not None and not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be ≥ 0, given {getattr(self, name)}")
        if self.min_configurations < 1:
            raise ValueError(f"min_configurations must be ≥ 1, given {self.min_configurations}")
        if self.max_configurations is not None and self.max_configurations < self.min_configurations:
            raise ValueError(f"max_configurations ({self.max_configurations}) must be ≥ min_configurations "
                             f"({self.min_configurations})")


@dataclass(frozen=True)
class DesignModel:
    """The linearised fit over the plan's candidates.

    rows: (N, r, L) Jacobian rows per candidate, mm per parameter unit.
    prior: (L, L) prior precision, 1 / unit².
    offsets: (K,) indices into L of the determinable offsets (rad); offset_names: their names.
    workspace: (L, L) A, mm² per unit².
    names: (L,) parameter names.
    """

    rows: np.ndarray
    prior: np.ndarray
    offsets: np.ndarray
    offset_names: tuple[str, ...]
    workspace: np.ndarray
    names: tuple[str, ...] = ()

    @property
    def n_candidates(self) -> int:
        return int(self.rows.shape[0])


@dataclass(frozen=True)
class Status:
    """What the measured configurations predict: half-widths (deg) by offset name, the predicted
    workspace and held-out errors (mm) and the full plan's, and the stop decision with its reason."""

    n_measured: int
    half_width_deg: dict[str, float]
    workspace_mm: float
    full_workspace_mm: float
    stop: bool
    reason: str
    held_out_mm: float = 0.0
    full_held_out_mm: float = 0.0

    @property
    def max_half_width_deg(self) -> float:
        return max(self.half_width_deg.values()) if self.half_width_deg else 0.0

    def to_dict(self) -> dict:
        return {"n_measured": self.n_measured, "max_half_width_deg": round(self.max_half_width_deg, 6),
                "half_width_deg": {k: round(v, 6) for k, v in self.half_width_deg.items()},
                "workspace_mm": round(self.workspace_mm, 6), "full_workspace_mm": round(self.full_workspace_mm, 6),
                "held_out_mm": round(self.held_out_mm, 6), "full_held_out_mm": round(self.full_held_out_mm, 6),
                "stop": self.stop, "reason": self.reason}


@dataclass(frozen=True)
class Choice:
    """The chosen candidate (index into the model's candidates) and why: its expected relative
    reduction of each stated quantity, the seconds to reach and measure it, and the score (gain
    per second); ``runner_up`` the next best index (or None)."""

    index: int
    gain: dict[str, float]
    seconds: float
    score: float
    runner_up: int | None = None
    runner_up_score: float = 0.0

    def to_dict(self) -> dict:
        return {"gain": {k: round(v, 6) for k, v in self.gain.items()}, "seconds": round(self.seconds, 3),
                "score_per_s": round(self.score, 6), "runner_up_score_per_s": round(self.runner_up_score, 6)}


@dataclass
class SequentialDesign:
    """The design's state: which candidates are measured, the information so far.

    sigma_mm: measurement noise per axis (mm); ``set_sigma`` updates it (e.g. from the fast fit).
    """

    model: DesignModel
    rule: StopRule
    sigma_mm: float
    measured: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.sigma_mm > 0:
            raise ValueError(f"sigma_mm must be > 0, given {self.sigma_mm}")
        r = self.model.rows
        self._blocks = np.einsum("nri,nrj->nij", r, r)  # (N, L, L), mm² per unit²
        self._all = self._blocks.sum(axis=0)
        self._full_ws: float | None = None

    # ------------------------------------------------------------------ state
    def set_sigma(self, sigma_mm: float) -> None:
        if not (math.isfinite(sigma_mm) and sigma_mm > 0):
            raise ValueError(f"sigma_mm must be a finite number > 0, given {sigma_mm}")
        self.sigma_mm = float(sigma_mm)
        self._full_ws = None

    def add(self, index: int) -> None:
        """Record candidate ``index`` as measured (once)."""
        if not 0 <= index < self.model.n_candidates:
            raise IndexError(f"candidate {index} out of range 0…{self.model.n_candidates - 1}")
        if index in self.measured:
            raise ValueError(f"candidate {index} is already measured")
        self.measured.append(int(index))

    @property
    def remaining(self) -> np.ndarray:
        left = np.ones(self.model.n_candidates, bool)
        left[self.measured] = False
        return np.flatnonzero(left)

    def covariance(self, indices=None) -> np.ndarray:
        """(L, L) predicted posterior covariance after ``indices`` (default: the measured ones)."""
        idx = self.measured if indices is None else list(indices)
        info = self.model.prior + (self._blocks[idx].sum(axis=0) if idx else 0.0) / self.sigma_mm**2
        return _inv_sym(info)

    def effective_parameters(self) -> float:
        """How many parameters the measured configurations fit, trace(I_data Σ): 1 per parameter
        the data determine, less for one its prior still holds (for σ estimates' degrees of freedom)."""
        idx = self.measured
        if not idx:
            return 0.0
        data = self._blocks[idx].sum(axis=0) / self.sigma_mm**2
        return float(np.sum(data * self.covariance()))

    # ------------------------------------------------------------------ quantities
    def half_widths_deg(self, cov: np.ndarray) -> dict[str, float]:
        k = self.model.offsets
        sd = np.sqrt(np.clip(np.diag(cov)[k], 0.0, None))
        return {name: math.degrees(T95 * s) for name, s in zip(self.model.offset_names, sd)}

    def workspace_mm(self, cov: np.ndarray) -> float:
        return math.sqrt(max(float(np.sum(self.model.workspace * cov)), 0.0))

    def held_out_mm(self, workspace_mm: float) -> float:
        """Predicted rms 3-D error of a held-out measurement: the model's and the sensor's."""
        return math.sqrt(3 * self.sigma_mm**2 + workspace_mm**2)

    def full_workspace_mm(self) -> float:
        """The predicted workspace error with every candidate measured."""
        if self._full_ws is None:
            self._full_ws = self.workspace_mm(_inv_sym(self.model.prior + self._all / self.sigma_mm**2))
        return self._full_ws

    def status(self) -> Status:
        """The measured configurations' predictions and whether the rule says stop."""
        cov = self.covariance()
        hw = self.half_widths_deg(cov)
        ws, full = self.workspace_mm(cov), self.full_workspace_mm()
        held, full_held = self.held_out_mm(ws), self.held_out_mm(full)
        n, rule = len(self.measured), self.rule
        stop, reason = False, ""
        if not len(self.remaining):
            stop, reason = True, f"plan exhausted: all {n} configurations measured"
        elif rule.max_configurations is not None and n >= rule.max_configurations:
            stop, reason = True, f"max_configurations reached ({n})"
        if n >= rule.min_configurations:
            met = []
            ok = True
            if rule.interval_deg is not None:
                worst = max(hw.values()) if hw else 0.0
                ok &= worst <= rule.interval_deg
                met.append(f"every determinable offset's 95 % half-width ≤ {rule.interval_deg:g}° "
                           f"(largest {worst:.4g}°)")
            if rule.workspace_within_pct is not None:
                limit = full * (1 + rule.workspace_within_pct / 100)
                ok &= ws <= limit
                met.append(f"predicted workspace error {ws:.4g} mm within {rule.workspace_within_pct:g} % of the "
                           f"full plan's {full:.4g} mm")
            if rule.held_out_within_pct is not None:
                ok &= held <= full_held * (1 + rule.held_out_within_pct / 100)
                met.append(f"predicted held-out error {held:.4g} mm within {rule.held_out_within_pct:g} % of the "
                           f"full plan's {full_held:.4g} mm")
            if ok:
                stop, reason = True, "stop rule met: " + "; ".join(met)
        return Status(n, hw, ws, full, stop, reason, held, full_held)

    # ------------------------------------------------------------------ the choice
    def gains(self, candidates: np.ndarray) -> dict[str, np.ndarray]:
        """Expected relative reduction of each stated quantity's trace, per candidate (len(candidates),)."""
        cov = self.covariance()
        rows = self.model.rows[candidates]  # (c, r, L)
        m = np.einsum("lk,crk->clr", cov, rows)  # Σ Jᵀ
        s = np.einsum("crl,clq->crq", rows, m) + self.sigma_mm**2 * np.eye(rows.shape[1])
        w = np.linalg.solve(s, np.swapaxes(m, 1, 2))  # S⁻¹ M ᵀ: (c, r, L)
        out = {}
        if self.rule.interval_deg is not None:
            k = self.model.offsets
            now = float(np.trace(cov[np.ix_(k, k)])) or 1.0
            out["interval"] = np.einsum("clr,crl->c", m[:, k, :], w[:, :, k]) / now
        if self.rule.workspace_within_pct is not None or self.rule.held_out_within_pct is not None:
            a = self.model.workspace
            trace = float(np.sum(a * cov))
            drop = np.einsum("lk,ckr,crl->c", a, m, w)
            if self.rule.workspace_within_pct is not None:
                out["workspace"] = drop / (trace or 1.0)
            if self.rule.held_out_within_pct is not None:
                out["held_out"] = drop / (trace + 3 * self.sigma_mm**2)
        return out

    def choose(self, seconds: np.ndarray, exclude=()) -> Choice:
        """The next candidate among the remaining: largest summed relative gain per second.

        seconds: (N,) move + settle + measure time (s) from where the robot stands to each
        candidate (entries of measured or excluded candidates are ignored). exclude: candidate
        indices not to choose (e.g. skipped ones). Raises ValueError when none is left.
        """
        left = np.setdiff1d(self.remaining, np.asarray(list(exclude), dtype=int))
        if not len(left):
            raise ValueError("no candidate left to choose")
        secs = np.asarray(seconds, dtype=float)[left]
        if np.any(~np.isfinite(secs)) or np.any(secs <= 0):
            raise ValueError("seconds must be finite and > 0 for every remaining candidate")
        g = self.gains(left)
        total = sum(g.values())
        score = total / secs
        order = np.argsort(-score, kind="stable")
        best = int(order[0])
        second = int(order[1]) if len(order) > 1 else None
        return Choice(int(left[best]), {k: float(v[best]) for k, v in g.items()}, float(secs[best]),
                      float(score[best]), None if second is None else int(left[second]),
                      0.0 if second is None else float(score[second]))


def _inv_sym(a: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix (Cholesky; pseudo-inverse as a fallback)."""
    try:
        c = np.linalg.cholesky(a)
        ci = np.linalg.solve(c, np.eye(a.shape[0]))
        return ci.T @ ci
    except np.linalg.LinAlgError:
        return np.linalg.pinv(a, hermitian=True)
