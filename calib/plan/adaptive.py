"""Sequential design: which configuration to measure next, and when to stop (issues 27, 35).

The fit is linear enough about the nominal robot that its posterior covariance after a set of
configurations is, to first order, the inverse of the information they carry:

    I = P + Σ_c J_cᵀ J_c / σ²,    Σ = I⁻¹

with J_c (r, L) the Jacobian of configuration c's measured coordinates (mm) with respect to the
fit's L free parameters (offsets rad, registration mm/rad, link deviations mm/rad, tool mm,
compliances µrad/(N·m)), P (L, L) the prior precision (the link and tool priors of the fit, and
weak priors on the parameters the fit leaves flat so that Σ exists before the first
configuration) and σ the measurement noise per axis (mm). Σ does not depend on the measured
values, only on where the robot was and on σ — so the design needs no fit beyond σ.

The quantities a stop rule is stated in (``StopRule``; ``CRITERIA``) — absolute, in the operator's
terms: the offsets' half-widths, the model error at new poses of the plan's region and over the
robot's working joint space (``DesignModel.joint_space``), each model error with the misfit the
fit's σ shows beyond the sensor's spread (``SequentialDesign.misfit_mm``: error no configuration
reduces); relative, against what the full plan would reach:

* the half-width of every determinable offset's 95 % interval, ``T · sqrt(Σ_kk)`` (degrees;
  T = 2.228, the 97.5 % quantile of the Student t with 10 degrees of freedom that the Laplace
  fit draws from);
* the predicted workspace error, ``sqrt(trace(A Σ))`` (mm): the rms over the plan's
  configurations and markers of the calibrated model's position uncertainty as the sensor sees
  them (A = mean of J_wᵀ J_w over those points, registration included: what only redefines the
  model's base frame is no error). The rule compares it with what the full plan would reach
  (every candidate measured). Scored on the candidates themselves this is optimistic for the
  configurations that were measured — the fit has seen them, a new pose beside one it has not —
  and most so for the full plan, which has measured them all; when A is the candidates' own
  (``DesignModel.workspace_from_candidates``) each measured candidate's term is therefore taken
  leave-one-out (``new_pose_workspace_mm``): the error at new poses of the same workspace;
* the predicted held-out error, ``sqrt(3σ² + w²)`` (mm), w the workspace error above: what
  validation on further configurations of the same workspace measures — the model's
  uncertainty and the sensor's noise — again against the full plan's. Where the noise
  dominates, a fraction of the plan predicts as well as all of it.

``SequentialDesign.choose_route`` plans the rest of the run — a batch that the linear model
predicts meets the stop rule, toured from where the robot stands (``plan_route``) — and goes to
its first stop; ``choose`` is the one-step rule it improves on: among the remaining candidates
the one with the largest expected relative reduction of the stated quantities (A-optimal: the traces above; a rule with
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

    In the operator's terms (absolute):
    interval_deg: every determinable offset's 95 % interval half-width ≤ this (deg), or None.
    region_error_mm: the predicted model error (rms, 3-D, mm; the model's uncertainty and its
    misfit, no sensor noise) at new poses of the plan's region ≤ this, or None.
    joint_space_error_mm: the same over the robot's working joint space as the plan declares it
    (``DesignModel.joint_space``), or None.

    Against the full plan (relative):
    workspace_within_pct: predicted workspace error ≤ (1 + pct/100) × the full plan's, or None.
    held_out_within_pct: predicted held-out error ≤ (1 + pct/100) × the full plan's, or None.
    joint_space_within_pct: predicted joint-space error ≤ (1 + pct/100) × the full plan's, or None.

    min_configurations: never stop before this many measured configurations.
    max_configurations: stop at this many even if the criteria are not met (None: the plan's size).
    """

    interval_deg: float | None = None
    workspace_within_pct: float | None = None
    held_out_within_pct: float | None = None
    min_configurations: int = 1
    max_configurations: int | None = None
    region_error_mm: float | None = None
    joint_space_error_mm: float | None = None
    joint_space_within_pct: float | None = None

    def __post_init__(self) -> None:
        if not self.criteria:
            raise ValueError("a stop rule needs one of " + ", ".join(CRITERIA))
        for name in ("interval_deg", "region_error_mm", "joint_space_error_mm"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, given {getattr(self, name)}")
        for name in ("workspace_within_pct", "held_out_within_pct", "joint_space_within_pct"):
            if getattr(self, name) is not None and not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be ≥ 0, given {getattr(self, name)}")
        if self.min_configurations < 1:
            raise ValueError(f"min_configurations must be ≥ 1, given {self.min_configurations}")
        if self.max_configurations is not None and self.max_configurations < self.min_configurations:
            raise ValueError(f"max_configurations ({self.max_configurations}) must be ≥ min_configurations "
                             f"({self.min_configurations})")

    @property
    def criteria(self) -> dict[str, float]:
        """The stated criteria, name → limit (the names of ``CRITERIA``)."""
        return {k: float(getattr(self, k)) for k in CRITERIA if getattr(self, k) is not None}

    @property
    def needs_joint_space(self) -> bool:
        return self.joint_space_error_mm is not None or self.joint_space_within_pct is not None


#: The stop rule's criteria, in the order they are reported.
CRITERIA = ("interval_deg", "region_error_mm", "joint_space_error_mm", "workspace_within_pct",
            "held_out_within_pct", "joint_space_within_pct")


@dataclass(frozen=True)
class DesignModel:
    """The linearised fit over the plan's candidates.

    rows: (N, r, L) Jacobian rows per candidate, mm per parameter unit.
    prior: (L, L) prior precision, 1 / unit².
    offsets: (K,) indices into L of the determinable offsets (rad); offset_names: their names.
    workspace: (L, L) A, mm² per unit² (over the plan's configurations).
    names: (L,) parameter names.
    plan_size: the first this many candidates are the plan's configurations — "the full plan"
    the rule compares with — and the rest a generated pool (None: every candidate is the plan's).
    workspace_from_candidates: A is the mean of the plan's candidates' own JᵀJ per 3 rows (as
    ``calib.fit.design`` builds it): the predicted errors are then those at new configurations
    like the plan's (``SequentialDesign.new_pose_workspace_mm``), not at the measured ones.
    joint_space: (L, L) the same matrix over configurations drawn from the robot's working joint
    space as the plan declares it (none of them a candidate: no leave-one-out), or None.
    """

    rows: np.ndarray
    prior: np.ndarray
    offsets: np.ndarray
    offset_names: tuple[str, ...]
    workspace: np.ndarray
    names: tuple[str, ...] = ()
    plan_size: int | None = None
    workspace_from_candidates: bool = False
    joint_space: np.ndarray | None = None

    @property
    def n_candidates(self) -> int:
        return int(self.rows.shape[0])

    @property
    def n_plan(self) -> int:
        """How many of the candidates are the plan's own configurations (the first ones)."""
        return self.n_candidates if self.plan_size is None else int(self.plan_size)


@dataclass(frozen=True)
class Check:
    """One criterion of the stop rule as judged: its name (``CRITERIA``), the limit stated, the
    value predicted (deg, mm, or % over the full plan's) and whether it holds."""

    name: str
    limit: float
    predicted: float
    met: bool

    def to_dict(self) -> dict:
        return {"criterion": self.name, "limit": self.limit, "predicted": round(self.predicted, 6), "met": self.met}


@dataclass(frozen=True)
class Status:
    """What the measured configurations predict: half-widths (deg) by offset name, the predicted
    workspace and held-out errors (mm) and the full plan's, the model error at new poses of the
    plan's region and over the working joint space (mm, misfit included; the latter None without
    a joint space), each stated criterion as judged (``checks``; ``unmet`` their names where the
    prediction falls short), and the stop decision with its reason."""

    n_measured: int
    half_width_deg: dict[str, float]
    workspace_mm: float
    full_workspace_mm: float
    stop: bool
    reason: str
    held_out_mm: float = 0.0
    full_held_out_mm: float = 0.0
    region_mm: float = 0.0
    full_region_mm: float = 0.0
    joint_space_mm: float | None = None
    full_joint_space_mm: float | None = None
    checks: tuple[Check, ...] = ()

    @property
    def max_half_width_deg(self) -> float:
        return max(self.half_width_deg.values()) if self.half_width_deg else 0.0

    @property
    def unmet(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.checks if not c.met)

    def to_dict(self) -> dict:
        r6 = lambda v: None if v is None else round(v, 6)  # noqa: E731
        return {"n_measured": self.n_measured, "max_half_width_deg": round(self.max_half_width_deg, 6),
                "half_width_deg": {k: round(v, 6) for k, v in self.half_width_deg.items()},
                "workspace_mm": round(self.workspace_mm, 6), "full_workspace_mm": round(self.full_workspace_mm, 6),
                "held_out_mm": round(self.held_out_mm, 6), "full_held_out_mm": round(self.full_held_out_mm, 6),
                "region_mm": round(self.region_mm, 6), "full_region_mm": round(self.full_region_mm, 6),
                "joint_space_mm": r6(self.joint_space_mm), "full_joint_space_mm": r6(self.full_joint_space_mm),
                "checks": [c.to_dict() for c in self.checks], "stop": self.stop, "reason": self.reason}


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
    planned: tuple[int, ...] = ()
    planned_seconds: float | None = None
    planned_by: str = ""

    def to_dict(self) -> dict:
        out = {"gain": {k: round(v, 6) for k, v in self.gain.items()}, "seconds": round(self.seconds, 3),
               "score_per_s": round(self.score, 6), "runner_up_score_per_s": round(self.runner_up_score, 6)}
        if self.planned:
            out.update(planned_configurations=len(self.planned), planned_seconds=round(self.planned_seconds, 1),
                       planned_by=self.planned_by)
        return out


@dataclass(frozen=True)
class Route:
    """A plan for the rest of the run: candidate indices in visiting order, the seconds of the
    whole tour from where the robot stands (moves + per-configuration settle and measure), the
    status the linear model predicts at its end, and how the batch was chosen."""

    order: tuple[int, ...]
    seconds: float
    status: Status
    by: str


@dataclass
class SequentialDesign:
    """The design's state: which candidates are measured, the information so far.

    sigma_mm: σ of a configuration's measured coordinates, per axis (mm): the noise of the
    averaged readings and, once a fit tells, what the model leaves unexplained (the fit's σ);
    misfit_mm: the part of σ the sensor's spread does not explain, per axis (mm): the model's
    systematic error, which more configurations do not reduce — counted in the model errors the
    rule predicts at new poses. ``set_noise`` updates both (``acquire.run.adaptive``).
    """

    model: DesignModel
    rule: StopRule
    sigma_mm: float
    measured: list[int] = field(default_factory=list)
    misfit_mm: float = 0.0

    def __post_init__(self) -> None:
        if not self.sigma_mm > 0:
            raise ValueError(f"sigma_mm must be > 0, given {self.sigma_mm}")
        r = self.model.rows
        self._blocks = np.einsum("nri,nrj->nij", r, r)  # (N, L, L), mm² per unit²
        self._all = self._blocks[: self.model.n_plan].sum(axis=0)  # the full plan: the plan's own
        self._full_ws: float | None = None
        self._full_js: float | None = None

    # ------------------------------------------------------------------ state
    def set_sigma(self, sigma_mm: float) -> None:
        self.set_noise(sigma_mm, self.misfit_mm)

    def set_noise(self, sigma_mm: float, misfit_mm: float = 0.0) -> None:
        """σ and the misfit (mm per axis) the design predicts with (see the class docstring)."""
        if not (math.isfinite(sigma_mm) and sigma_mm > 0):
            raise ValueError(f"sigma_mm must be a finite number > 0, given {sigma_mm}")
        if not (math.isfinite(misfit_mm) and misfit_mm >= 0):
            raise ValueError(f"misfit_mm must be a finite number ≥ 0, given {misfit_mm}")
        self.sigma_mm, self.misfit_mm = float(sigma_mm), float(misfit_mm)
        self._full_ws = self._full_js = None

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

    def effective_parameters(self, indices=None, sigma_mm: float | None = None) -> float:
        """How many parameters the configurations ``indices`` (default: the measured ones) fit at
        noise ``sigma_mm`` (default: the design's), trace(I_data Σ): 1 per parameter the data
        determine, less for one its prior still holds (for σ estimates' degrees of freedom)."""
        idx = self.measured if indices is None else [int(i) for i in indices]
        if not idx:
            return 0.0
        s2 = (self.sigma_mm if sigma_mm is None else float(sigma_mm)) ** 2
        data = self._blocks[idx].sum(axis=0) / s2
        return float(np.sum(data * _inv_sym(self.model.prior + data)))

    # ------------------------------------------------------------------ quantities
    def half_widths_deg(self, cov: np.ndarray) -> dict[str, float]:
        k = self.model.offsets
        sd = np.sqrt(np.clip(np.diag(cov)[k], 0.0, None))
        return {name: math.degrees(T95 * s) for name, s in zip(self.model.offset_names, sd)}

    def workspace_mm(self, cov: np.ndarray) -> float:
        return math.sqrt(max(float(np.sum(self.model.workspace * cov)), 0.0))

    def new_pose_workspace_mm(self, indices, cov: np.ndarray | None = None) -> float:
        """The predicted workspace error at configurations like the plan's that were not measured
        (mm): the mean over the plan's candidates (the first ``n_plan``; a generated pool is not
        the workspace the rule averages over) of the model's position variance, trace(J_c Σ J_cᵀ),
        where a measured candidate's own information is taken out (leave-one-out, Woodbury:
        trace(σ² B (σ² I − B)⁻¹), B = J_c Σ J_cᵀ). ``workspace_mm`` scores the candidates
        themselves, and a measured one is predicted better than a new pose beside it would be —
        more so the more of them are measured: the full plan's in-sample error is its most
        optimistic. indices: the measured candidates (plan's and pool's); cov: their covariance
        when the caller has it."""
        n_plan = self.model.n_plan
        measured = [int(i) for i in indices]
        cov = self.covariance(measured) if cov is None else cov
        idx = [i for i in measured if i < n_plan]  # measured pool candidates are not averaged over
        rows = self.model.rows[:n_plan]  # (N_plan, r, L)
        n, r, L = rows.shape
        flat = rows.reshape(n * r, L)
        var = np.sum((flat @ cov) * flat, axis=1).reshape(n, r).sum(axis=1)  # trace(J_c Σ J_cᵀ), (N,)
        if idx:
            j = rows[idx]
            b = (j.reshape(-1, L) @ cov).reshape(len(idx), r, L) @ np.swapaxes(j, 1, 2)  # (k, r, r)
            s2 = self.sigma_mm**2
            eye = np.eye(b.shape[1])
            var[idx] = s2 * np.trace(np.linalg.solve(s2 * eye - b, b), axis1=1, axis2=2)
        return math.sqrt(max(float(var.mean()) / r * 3, 0.0))

    def held_out_mm(self, workspace_mm: float) -> float:
        """Predicted rms 3-D error of a held-out measurement: the model's and the sensor's (σ, the
        fit's once it tells, holds the misfit too)."""
        return math.sqrt(3 * self.sigma_mm**2 + workspace_mm**2)

    def model_error_mm(self, uncertainty_mm: float) -> float:
        """Predicted rms 3-D model error at new poses (no sensor noise): the calibrated model's
        uncertainty there (mm) and its misfit (per axis, in each of the three)."""
        return math.sqrt(uncertainty_mm**2 + 3 * self.misfit_mm**2)

    def joint_space_uncertainty_mm(self, cov: np.ndarray) -> float | None:
        """sqrt(trace(A_js Σ)) over the working joint space (mm), None without one."""
        a = self.model.joint_space
        return None if a is None else math.sqrt(max(float(np.sum(a * cov)), 0.0))

    def full_joint_space_mm(self) -> float | None:
        """The joint-space uncertainty with every configuration of the plan measured (mm)."""
        if self.model.joint_space is None:
            return None
        if self._full_js is None:
            self._full_js = self.joint_space_uncertainty_mm(_inv_sym(self.model.prior + self._all / self.sigma_mm**2))
        return self._full_js

    def predicted_workspace_mm(self, indices, cov: np.ndarray) -> float:
        """The workspace error the stop rule and the reports use after measuring ``indices``:
        at new configurations like the candidates when the model's workspace is theirs
        (``new_pose_workspace_mm``), else sqrt(trace(A Σ))."""
        if self.model.workspace_from_candidates:
            return self.new_pose_workspace_mm(indices, cov)
        return self.workspace_mm(cov)

    def full_workspace_mm(self) -> float:
        """The predicted workspace error with every configuration of the plan measured (a
        generated pool beyond the plan is not part of "the full plan")."""
        if self._full_ws is None:
            cov = _inv_sym(self.model.prior + self._all / self.sigma_mm**2)
            self._full_ws = self.predicted_workspace_mm(range(self.model.n_plan), cov)
        return self._full_ws

    def status(self) -> Status:
        """The measured configurations' predictions and whether the rule says stop."""
        return self.status_of(self.measured)

    def status_of(self, indices, cov: np.ndarray | None = None) -> Status:
        """What measuring ``indices`` (candidate indices) would predict, and whether the rule
        would say stop then (for plans ahead: ``plan_route``); ``cov``: their covariance when
        the caller has it."""
        idx = list(indices)
        cov = self.covariance(idx) if cov is None else cov
        hw = self.half_widths_deg(cov)
        ws, full = self.predicted_workspace_mm(idx, cov), self.full_workspace_mm()
        held, full_held = self.held_out_mm(ws), self.held_out_mm(full)
        region, full_region = self.model_error_mm(ws), self.model_error_mm(full)
        js_w, full_js_w = self.joint_space_uncertainty_mm(cov), self.full_joint_space_mm()
        js = None if js_w is None else self.model_error_mm(js_w)
        full_js = None if full_js_w is None else self.model_error_mm(full_js_w)
        pct = lambda a, b: 100.0 * (a / b - 1.0) if b > 0 else 0.0  # noqa: E731 - % over the full plan's
        predicted = {"interval_deg": max(hw.values()) if hw else 0.0, "region_error_mm": region,
                     "joint_space_error_mm": js, "workspace_within_pct": pct(ws, full),
                     "held_out_within_pct": pct(held, full_held),
                     "joint_space_within_pct": None if js is None else pct(js, full_js)}
        checks = []
        for name, limit in self.rule.criteria.items():
            value = predicted[name]
            if value is None:
                raise ValueError(f"the stop rule's {name} needs the working joint space in the design model")
            checks.append(Check(name, limit, float(value), bool(value <= limit)))
        n, rule = len(idx), self.rule
        stop, reason = False, ""
        if n >= self.model.n_candidates:
            stop, reason = True, f"plan exhausted: all {n} configurations measured"
        elif rule.max_configurations is not None and n >= rule.max_configurations:
            stop, reason = True, f"max_configurations reached ({n})"
        if n >= rule.min_configurations and all(c.met for c in checks):
            stop, reason = True, "stop rule met: " + "; ".join(describe(c) for c in checks)
        return Status(n, hw, ws, full, stop, reason, held, full_held, region, full_region, js, full_js, tuple(checks))

    # ------------------------------------------------------------------ the choice
    def gains(self, candidates: np.ndarray, planned=(), cov: np.ndarray | None = None,
              criteria=None) -> dict[str, np.ndarray]:
        """Expected relative reduction of each stated quantity, per candidate (len(candidates),),
        after the measured configurations and ``planned`` ones (candidate indices); ``cov``: their
        covariance when the caller has it; ``criteria``: the names (``CRITERIA``) to weigh [the
        rule's]. The model errors' reductions are relative to the error with the misfit, which no
        configuration reduces: a cell whose model leaves more unexplained gains less per
        configuration there and measures more for an absolute limit."""
        if cov is None:
            cov = self.covariance(list(self.measured) + [int(i) for i in planned])
        rows = self.model.rows[candidates]  # (c, r, L)
        mt = rows @ cov  # (Σ Jᵀ)ᵀ: (c, r, L)
        s = mt @ np.swapaxes(rows, 1, 2) + self.sigma_mm**2 * np.eye(rows.shape[1])  # (c, r, r)
        w = np.linalg.inv(s) @ mt  # S⁻¹ J Σ: (c, r, L); S is r × r and well conditioned (σ² I + …), and a
        # batched inverse then a product is ~3× faster than a batched solve (pools of hundreds of candidates)
        stated = self.rule.criteria if criteria is None else criteria
        kinds = {GAIN_OF[name] for name in stated}
        out = {}
        if "interval" in kinds:
            k = self.model.offsets
            now = float(np.trace(cov[np.ix_(k, k)])) or 1.0
            out["interval"] = np.sum(mt[:, :, k] * w[:, :, k], axis=(1, 2)) / now
        if kinds & {"workspace", "held_out", "region"}:
            a = self.model.workspace
            trace = float(np.sum(a * cov))
            drop = np.sum((mt @ a) * w, axis=(1, 2))  # trace(A Σ Jᵀ S⁻¹ J Σ), A symmetric
            for kind, rest in (("workspace", 0.0), ("region", 3 * self.misfit_mm**2),
                               ("held_out", 3 * self.sigma_mm**2)):
                if kind in kinds:
                    out[kind] = drop / ((trace + rest) or 1.0)
        if "joint_space" in kinds:
            a = self.model.joint_space
            trace = float(np.sum(a * cov))
            out["joint_space"] = np.sum((mt @ a) * w, axis=(1, 2)) / ((trace + 3 * self.misfit_mm**2) or 1.0)
        return out

    def plan_route(self, here_s: np.ndarray, between_s: np.ndarray, per_config_s: float, exclude=()) -> Route:
        """The configurations still to measure and their order: a batch the linear model predicts
        meets the stop rule (or, failing that, all that may be chosen), in a short tour from where
        the robot stands. Two batches are built and the faster tour kept:

        * "gain per second of tour": repeatedly the candidate with the largest summed relative gain
          (given the measured and the batch so far) per second it adds to the tour at its cheapest
          insertion (move seconds + ``per_config_s``), then the tour shortened by 2-opt;
        * "gain": repeatedly the candidate with the largest gain, toured by nearest neighbour + 2-opt.

        Choosing one configuration at a time by gain per second from where the robot stands (``choose``)
        is myopic: it takes what is near now and pays for far-away information later; a batch that
        meets the rule, toured, reaches the same predicted error in less cell time.

        here_s: (N,) move seconds from where the robot stands to each candidate; between_s: (N, N)
        move seconds between candidates; per_config_s: settle + measure seconds per configuration;
        exclude: candidate indices not to choose. Raises ValueError when none is left.
        """
        from calib.plan.route import insertion_costs, nearest_neighbour, path_seconds, two_opt

        left0 = np.setdiff1d(self.remaining, np.asarray(list(exclude), dtype=int))
        if not len(left0):
            raise ValueError("no candidate left to choose")
        n = self.model.n_candidates
        here = np.asarray(here_s, dtype=float).reshape(n)
        cost = np.zeros((n + 1, n + 1))
        cost[0, 1:] = cost[1:, 0] = here
        cost[1:, 1:] = np.asarray(between_s, dtype=float).reshape(n, n)
        if not np.all(np.isfinite(cost[np.ix_(np.r_[0, left0 + 1], np.r_[0, left0 + 1])])):
            raise ValueError("move seconds must be finite for every remaining candidate")
        per = float(per_config_s)

        info0 = self.model.prior + (self._blocks[self.measured].sum(axis=0) if self.measured else 0.0) / self.sigma_mm**2

        def grow(timed: bool) -> list[int]:
            path, batch, left, info = [0], [], list(left0), info0.copy()
            while left:
                cov = _inv_sym(info)
                st = self.status_of(self.measured + batch, cov)
                if st.stop and batch:  # (a first one even when the rule holds: the caller goes on, e.g.
                    break  # until the fit's σ is determined)
                g = sum(self.gains(np.array(left), cov=cov, criteria=st.unmet or None).values())
                if timed:
                    extra, pos = insertion_costs(path, cost, np.array(left) + 1)
                    k = int(np.argmax(g / (extra + per)))
                    path.insert(int(pos[k]) + 1, left[k] + 1)
                else:
                    k = int(np.argmax(g))
                info = info + self._blocks[left[k]] / self.sigma_mm**2
                batch.append(left.pop(k))
            path = path if timed else nearest_neighbour(cost, np.array(batch) + 1)
            return two_opt(path, cost)

        best = None
        for timed, by in ((True, "gain per second of tour"), (False, "gain")):
            path = grow(timed)
            secs = path_seconds(path, cost) + per * (len(path) - 1)
            if best is None or secs < best[1] - 1e-9:
                best = (path, secs, by)
        path, secs, by = best
        order = tuple(int(i) - 1 for i in path[1:])
        return Route(order, secs, self.status_of(self.measured + list(order)), by)

    def choose_route(self, here_s: np.ndarray, between_s: np.ndarray, per_config_s: float, exclude=()) -> Choice:
        """The next candidate: the first of ``plan_route``'s tour (re-planned after every
        measurement, as σ and what was measured change). The Choice carries its gain given what
        was measured, its seconds, the tour's second stop as the runner-up and the planned rest."""
        route = self.plan_route(here_s, between_s, per_config_s, exclude)
        first = route.order[0]
        secs = float(here_s[first]) + float(per_config_s)
        g = self.gains(np.array([first]))
        total = float(sum(v[0] for v in g.values()))
        second = route.order[1] if len(route.order) > 1 else None
        second_score = 0.0
        if second is not None:
            g2 = sum(v[0] for v in self.gains(np.array([second]), planned=[first]).values())
            second_score = float(g2) / (float(between_s[first][second]) + float(per_config_s))
        return Choice(first, {k: float(v[0]) for k, v in g.items()}, secs, total / secs, second, second_score,
                      route.order, route.seconds, route.by)

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


#: Which gain (``SequentialDesign.gains``) serves each criterion of the stop rule.
GAIN_OF = {"interval_deg": "interval", "region_error_mm": "region", "workspace_within_pct": "workspace",
           "held_out_within_pct": "held_out", "joint_space_error_mm": "joint_space",
           "joint_space_within_pct": "joint_space"}

#: How each criterion reads in a stop reason: (what, unit).
WORDING = {"interval_deg": ("every determinable offset's 95 % half-width", "°"),
           "region_error_mm": ("predicted model error at new poses of the plan's region", " mm"),
           "joint_space_error_mm": ("predicted model error over the working joint space", " mm"),
           "workspace_within_pct": ("predicted workspace error over the full plan's", " %"),
           "held_out_within_pct": ("predicted held-out error over the full plan's", " %"),
           "joint_space_within_pct": ("predicted joint-space error over the full plan's", " %")}


def describe(check: Check) -> str:
    """A criterion as judged, in words: what, the limit and the prediction."""
    what, unit = WORDING[check.name]
    largest = "largest " if check.name == "interval_deg" else ""
    return (f"{what} {'≤' if check.met else '>'} {check.limit:g}{unit} ({largest}{check.predicted:.4g}{unit})")


def _inv_sym(a: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix (Cholesky; pseudo-inverse as a fallback)."""
    try:
        c = np.linalg.cholesky(a)
        ci = np.linalg.solve(c, np.eye(a.shape[0]))
        return ci.T @ ci
    except np.linalg.LinAlgError:
        return np.linalg.pinv(a, hermitian=True)
