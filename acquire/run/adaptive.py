"""An adaptive run's order (the plan's ``adaptive`` section, issue 27): after each measured
configuration the next is chosen by ``calib.plan.adaptive.SequentialDesign`` — expected gain of
the stated quantities per second of motion, settling and measuring from where the robot stands —
and the run stops when the plan's stop rule holds.

``AdaptiveOrder`` holds the design over the plan's configurations (``calib.fit.design``: the
fit's own parameters and priors, linearised at the nominal robot), the noise it predicts with
(``use_sigma``: σ of a configuration's averaged coordinates as measured — the spread of its
readings over √count, pooled over the records with the plan's ``noise_mm``/√samples as
``PLAN_SIGMA_DOF`` degrees of freedom — and, once the fast fit of the records has
``MIN_SIGMA_DOF`` degrees of freedom, the fit's σ, unbiased for the effective number of
parameters it fitted; the misfit is what the fit's σ has beyond the spread: error the model does
not explain; the choice after n records uses the fit at the schedule's last count before the
newest record, ``sigma_count``, so that it can be computed while that record is measured:
``acquire.run.lookahead``), the working joint space the plan declares (``joint_space_samples``),
and the history (predicted intervals and workspace error against the number of
configurations) that the summary shows. Nothing here moves the robot: the run's
``ConfigurationRunner`` does, with every check it always makes.

A resumed run rebuilds the design from the log's samples (``mark``) and continues choosing among
the configurations no sample has: nothing is measured twice.

A plan's ``adaptive.candidates`` adds generated configurations (``acquire.plan.schema.resolve_candidate_pool``:
the plan's own pose generator, another seed, the same checks) after the plan's: the design may
choose them (``admissible_pool`` keeps those inside the open commander's limits less its margin;
each chosen one is logged with its joint angles), while the workspace the rule's errors average
over, "the full plan" it compares with, and the full plan's cell time stay the plan's own.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from calib.plan.adaptive import SequentialDesign, StopRule, Status

log = logging.getLogger(__name__)

#: Degrees of freedom (coordinates less effective parameters) before the fast fit's σ is used.
MIN_SIGMA_DOF = 10
#: The plan's σ of a configuration (noise_mm / √samples) counts as this many degrees of freedom
#: beside the spread of the readings measured (each record gives count − 1 per axis).
PLAN_SIGMA_DOF = 6
#: σ is refitted once the records have grown by this fraction (and before every stop decision):
#: a fast fit of 60 configurations costs ~0.1 s (in the look-ahead worker while the robot moves,
#: except before a stop decision), and σ changes little from one configuration to the next.
REFIT_GROWTH = 0.15


def refit_counts(n: int) -> set[int]:
    """The record counts (up to ``n``) at which σ is refitted: 1, 2, 3, …, each at least
    ``REFIT_GROWTH`` more than the one before."""
    out, c = set(), 1
    while c <= n:
        out.add(c)
        c = max(c + 1, math.ceil(c * (1 + REFIT_GROWTH)))
    return out


def stop_rule(lp, n_configs: int) -> StopRule:
    """The plan's stop rule for ``n_configs`` configurations. Raises ConfigError (the plan's
    file, line and field) when ``min_configurations`` exceeds the plan's configurations."""
    from calib.fit.offsets import min_configurations

    ad = lp.plan.adaptive
    fit = lp.plan.fit
    n_fit = len(fit.joints) if fit.joints else lp.model.n_joints
    need = min_configurations(n_fit, [len(s.markers) for s in lp.plan.sensors], fix_registration=fit.fix_registration)
    lo = ad.min_configurations if ad.min_configurations is not None else min(n_configs, max(12, 2 * need))
    if lo > n_configs:
        raise lp.error(("adaptive", "min_configurations"), f"more than the plan's {n_configs} configurations "
                                                           f"(given {lo}; allowed 1…{n_configs})")
    if lo < need:
        raise lp.error(("adaptive", "min_configurations"), f"fewer than the fit needs (given {lo}; allowed "
                                                           f"{need}…{n_configs})")
    hi = ad.max_configurations
    w = ad.stop_when
    return StopRule(interval_deg=w.interval_deg, workspace_within_pct=w.workspace_within_pct,
                    held_out_within_pct=w.held_out_within_pct, region_error_mm=w.region_error_mm,
                    joint_space_error_mm=w.joint_space_error_mm, joint_space_within_pct=w.joint_space_within_pct,
                    min_configurations=lo, max_configurations=None if hi is None else min(hi, n_configs))


def joint_space_samples(lp, *, seed: int | None = None, n: int | None = None) -> np.ndarray:
    """(n, n_joints) rad: configurations drawn uniformly (Latin hypercube per joint) from the
    robot's working joint space as the plan declares it (``adaptive.joint_space``: its ranges,
    or the model's joint limits less the commander's margin; its ``samples`` and ``seed`` unless
    given) — where the predicted joint-space error averages."""
    spec = lp.plan.adaptive.joint_space if lp.plan.adaptive is not None else None
    n = int(n if n is not None else (spec.samples if spec is not None else 200))
    seed = int(seed if seed is not None else (spec.seed if spec is not None else 0))
    if spec is not None and spec.ranges_deg is not None:
        lo, hi = (np.radians([r[k] for r in spec.ranges_deg]) for k in (0, 1))
    else:
        margin = lp.commander_margin_rad
        lo = np.asarray(lp.model.lower_limits_rad, dtype=float) + margin
        hi = np.asarray(lp.model.upper_limits_rad, dtype=float) - margin
    rng = np.random.default_rng(seed)
    u = (np.argsort(rng.random((len(lo), n)), axis=1).T + rng.random((n, len(lo)))) / n  # (n, J) in [0, 1)
    return lo + u * (hi - lo)


def fit_options(lp):
    """The fit's options as the design linearises them (the Laplace fit's model: link and tool
    priors, compliance when the plan fits it and the model has masses)."""
    from calib.fit.offsets import FitOptions

    fit = lp.plan.fit
    mm, deg = getattr(fit, "link_tolerance_mm", 0.2), getattr(fit, "link_tolerance_deg", 0.02)
    return FitOptions(method="laplace", joints=tuple(fit.joints) if fit.joints else None,
                      fix_registration=bool(fit.fix_registration),
                      link_tolerance=None if mm is None or deg is None else (float(mm), float(deg)),
                      compliance=bool(fit.compliance) and lp.model.has_dynamics,
                      tool_prior_mm=float(fit.tool_prior_mm))


class AdaptiveOrder:
    """The sequential design over ``configs`` (the plan's PlannedConfigs) for a run.

    limits: the commander's ``JointLimits``; speed: the plan's speed override; per_config_s:
    expected settle + measure seconds per configuration; pool: generated candidates beyond the
    plan (``acquire.plan.schema.resolve_candidate_pool``), chosen like the plan's but never part of the
    full plan the rule compares with (``admissible_pool`` keeps those the commander accepts).
    """

    def __init__(self, lp, configs, limits, speed: float, per_config_s: float, pool=()) -> None:
        from calib.fit.design import design_model

        self.plan_configs = list(configs)
        pool = admissible_pool(pool, limits, lp.commander_margin_rad)
        self.lp, self.model, self.configs = lp, lp.model, self.plan_configs + pool
        self.index = {c.config_id: i for i, c in enumerate(self.configs)}
        self.limits, self.speed, self.per_config_s = limits, float(speed), float(per_config_s)
        self.noise_mm = max(float(s.noise_mm) for s in lp.plan.sensors)  # per reading
        self.samples = int(lp.plan.sequencing.samples)
        self.plan_sigma_mm = self.noise_mm / math.sqrt(self.samples)  # of a configuration's mean, as planned
        self.options = fit_options(lp)
        q = np.stack([np.asarray(c.q_rad, dtype=float) for c in self.configs])
        sensors = {s.name: list(s.markers) for s in lp.plan.sensors}
        n_plan = len(self.plan_configs)
        model = design_model(lp.model, q, sensors, self.options, plan_size=n_plan if pool else None,
                             joint_space_q=joint_space_samples(lp))
        self.design = SequentialDesign(model, stop_rule(lp, n_plan), self.plan_sigma_mm)
        self.require_fit = True  # a rule's stop waits for the fit's σ (``simulate`` assumes the plan's)
        self.held_for_fit = False  # the last status met the rule but waited for the fit's σ
        self.dropped: set[int] = set()  # skipped or failed: not chosen again in this run
        self.records: list[dict] = []
        self.history: list[dict] = []
        self.fitted_sigma_mm: float | None = None
        self.spread_sigma_mm: float | None = None
        self._sigma_n = 0  # records when σ was last fitted
        self._fits: dict[int, float | None] = {}  # fast-fit σ by record count (records only grow)

    def __getstate__(self) -> dict:
        """Picklable state for the look-ahead worker (``acquire.run.lookahead``): the plan's
        model as its validated dict (the model object caches unpicklable solvers), no plan."""
        state = dict(self.__dict__)
        state["lp"], state["model"] = None, self.model.model_dump()
        return state

    def __setstate__(self, state: dict) -> None:
        from calib.robot.model import robot_model_from_dict

        state = dict(state)
        state["model"] = robot_model_from_dict(state["model"])
        self.__dict__.update(state)

    def copy(self) -> "AdaptiveOrder":
        """An independent copy of the design's state (for predictions: ``simulate``)."""
        import copy

        other = copy.copy(self)
        d = self.design
        other.design = SequentialDesign(d.model, d.rule, d.sigma_mm, measured=list(d.measured), misfit_mm=d.misfit_mm)
        other.dropped, other.records, other.history = set(self.dropped), list(self.records), []
        other._fits = dict(self._fits)
        other._between = self.between_seconds()
        return other

    # ------------------------------------------------------------------ state
    def mark(self, config_id: str, record: dict | None = None) -> None:
        """``config_id`` was measured (its sample ``record`` updates σ when given)."""
        i = self.index.get(config_id)
        if i is None or i in self.design.measured:
            return
        self.design.add(i)
        if record is not None:
            self.records.append(record)

    def drop(self, config_id: str) -> None:
        """``config_id`` was skipped or failed: not chosen again in this run (a resume may)."""
        i = self.index.get(config_id)
        if i is not None:
            self.dropped.add(i)

    def sigma_count(self, n_records: int | None = None) -> int:
        """The record count whose fast fit gives σ for the choice after ``n_records`` records
        (default: those so far): the schedule's (``refit_counts``: 1, 2, …, each at least
        ``REFIT_GROWTH`` more than the one before) last count before the newest record — one record
        behind, so the choice can be computed while that record is being measured. A function of
        the records alone: a resumed run predicts with the σ an uninterrupted one had. The stop
        decision is judged with σ of every record (``AdaptiveRun.choices``)."""
        n = len(self.records) if n_records is None else int(n_records)
        return max(refit_counts(n - 1), default=0)

    def sigma_stale(self) -> bool:
        """Records have arrived since the σ the design predicts with was fitted."""
        return self._sigma_n < len(self.records)

    def fitted_sigma(self, upto: int) -> float | None:
        """The fast fit's σ (mm) of the first ``upto`` records, fitted once (None: no fit yet)."""
        if upto not in self._fits:
            self._fits[upto] = self.fast_fit_sigma(upto) if upto > 0 else None
        return self._fits[upto]

    def spread_sigma(self, upto: int | None = None) -> float:
        """σ of a configuration's averaged coordinates as the first ``upto`` records measured it
        (mm per axis): each marker's reading spread per axis (``std_mm``, ddof 1) over √count,
        pooled by degrees of freedom (count − 1) with the plan's noise_mm / √samples as
        ``PLAN_SIGMA_DOF`` of them (the plan's alone before a record has a spread)."""
        var, dof = PLAN_SIGMA_DOF * self.plan_sigma_mm**2, float(PLAN_SIGMA_DOF)
        for rec in self.records[:upto]:
            for m in rec.get("markers", []):
                std, count = m.get("std_mm"), m.get("count")
                if std is None or count is None or int(count) < 2:
                    continue
                s2 = np.asarray(std, dtype=float) ** 2 / int(count)
                s2 = s2[np.isfinite(s2)]
                var += float(np.sum(s2)) * (int(count) - 1)
                dof += len(s2) * (int(count) - 1)
        return math.sqrt(var / dof)

    def use_sigma(self, upto: int) -> None:
        """Predict with the noise of the first ``upto`` records: σ their fast fit's (what the data
        say the model leaves, misfit included) once it is determined, else the spread of their
        readings (``spread_sigma``) — never less than the spread: a fit of few degrees of freedom
        that leaves less than the sensor's own noise has fitted some of it; the misfit
        sqrt(max(0, σ_fit² − σ_spread²)) — error the model does not explain, which the predicted
        model errors count and no configuration reduces."""
        fitted = self.fitted_sigma(upto)
        spread = self.spread_sigma(upto)
        self._sigma_n = upto
        self.fitted_sigma_mm, self.spread_sigma_mm = fitted, spread
        sigma = spread if fitted is None else max(fitted, spread)
        misfit = 0.0 if fitted is None else math.sqrt(max(0.0, fitted**2 - spread**2))
        if (sigma, misfit) != (self.design.sigma_mm, self.design.misfit_mm):
            self.design.set_noise(sigma, misfit)

    def update_sigma(self, upto: int | None = None) -> None:
        """σ of every record so far (or of the first ``upto``): ``use_sigma``."""
        self.use_sigma(len(self.records) if upto is None else min(upto, len(self.records)))

    def choice_key(self, here_q_rad) -> tuple:
        """What a choice depends on: the measured (in order) and dropped candidates, σ and where
        the robot stands. A choice computed ahead is used only when its key is the state's."""
        return (tuple(int(i) for i in self.design.measured), tuple(sorted(int(i) for i in self.dropped)),
                float(self.design.sigma_mm), float(self.design.misfit_mm), tuple(float(x) for x in np.asarray(here_q_rad, dtype=float).ravel()))

    def fast_fit_sigma(self, upto: int | None = None) -> float | None:
        """The fitted σ (mm, largest over sensors) of the posterior mode on the records, or None
        while there are too few of them for the fit."""
        from calib.fit.offsets import fit_mode
        from calib.measure.dataset import DatasetError, from_arrays

        q, xyz, mk, sn, cid = [], [], [], [], []
        for rec in self.records[:upto]:
            for m in rec.get("markers", []):
                q.append(np.radians(rec["q_measured_deg"]))
                xyz.append(m["mean_mm"])
                mk.append(m["marker"])
                sn.append(m["sensor"])
                cid.append(rec["config_id"])
        if len(set(cid)) < self.design.rule.min_configurations // 2 or not q:
            return None
        data = from_arrays(np.array(q), np.array(xyz, dtype=float), marker=np.array(mk), sensor=np.array(sn),
                           config=np.array(cid))
        try:
            mf = fit_mode(self.model, data, self.options, tol=1e-8)
        except (DatasetError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            log.info("adaptive: no fast fit yet (%s)", exc)
            return None
        # The mode's σ is the maximum-likelihood one, low by the parameters the data fitted (the
        # effective number: link and tool parameters count in part): unbias it, and trust it only
        # with MIN_SIGMA_DOF degrees of freedom left.
        n_coord = 3 * len(data)
        fitted = sorted({self.index[c] for c in cid if c in self.index})
        p_eff = self.design.effective_parameters(fitted, self.spread_sigma(upto))
        if n_coord - p_eff < MIN_SIGMA_DOF:
            return None
        sigma = float(np.max(np.exp(mf.log_sigma))) * math.sqrt(n_coord / (n_coord - p_eff))
        return sigma if math.isfinite(sigma) and sigma > 0 else None

    def status(self) -> Status:
        """The design's status; a rule met before the fit's σ is determined does not stop the run
        (the spread alone cannot tell what the model leaves unexplained) unless ``require_fit``
        is off (``simulate``: the plan's noise assumed)."""
        from dataclasses import replace

        st = self.design.status()
        self.held_for_fit = (st.stop and self.require_fit and self.fitted_sigma_mm is None
                             and st.reason.startswith("stop rule met"))
        if self.held_for_fit:
            st = replace(st, stop=False, reason="")
        if not st.stop and not self._choosable().size:
            st = replace(st, stop=True, reason=f"plan exhausted: {st.n_measured} measured, the rest skipped or failed")
        return st

    def _choosable(self) -> np.ndarray:
        left = self.design.remaining
        return np.array([i for i in left if i not in self.dropped], dtype=int)

    # ------------------------------------------------------------------ the choice
    def seconds_from(self, here_q_rad: np.ndarray) -> np.ndarray:
        """(N,) move + settle + measure seconds from ``here_q_rad`` to every configuration."""
        from drivers.trajectory import motion_time, scaled_limits

        v, a, j = scaled_limits(self.limits.max_velocity_rad_s, self.limits.max_acceleration_rad_s2, self.speed)
        q = np.stack([np.asarray(c.q_rad, dtype=float) for c in self.configs])
        here = np.asarray(here_q_rad, dtype=float)[None, :]
        return np.asarray(motion_time(np.repeat(here, len(q), axis=0), q, v, a, j), dtype=float) + self.per_config_s

    def between_seconds(self) -> np.ndarray:
        """(N, N) move seconds between the plan's configurations (computed once)."""
        if getattr(self, "_between", None) is None:
            from acquire.run.sequencer import motion_cost_matrix

            q = np.stack([np.asarray(c.q_rad, dtype=float) for c in self.configs])
            self._between = motion_cost_matrix(q, self.limits, self.speed)
        return self._between

    def choose(self, here_q_rad: np.ndarray):
        """(PlannedConfig, event fields) of the next configuration from ``here_q_rad``: the first
        stop of the planned rest of the run (``SequentialDesign.choose_route``: a batch predicted
        to meet the stop rule, toured from here); the event fields say why (gain per stated
        quantity, seconds, score, the tour's next stop, the planned count and seconds)."""
        design = self.design
        moves = self.seconds_from(here_q_rad) - self.per_config_s
        choice = design.choose_route(moves, self.between_seconds(), self.per_config_s, exclude=sorted(self.dropped))
        cfg = self.configs[choice.index]
        fields = {"config_id": cfg.config_id, **choice.to_dict(), "sigma_mm": round(design.sigma_mm, 5),
                  **self.generated_fields(choice.index)}
        if choice.runner_up is not None:
            fields["runner_up"] = self.configs[choice.runner_up].config_id
        return cfg, fields

    def pool_fields(self) -> dict:
        """How many candidates are the plan's and how many generated (and measured of those); {} without a pool."""
        n_plan = len(self.plan_configs)
        if len(self.configs) == n_plan:
            return {}
        return {"plan_configurations": n_plan, "generated_candidates": len(self.configs) - n_plan,
                "generated_measured": sum(1 for i in self.design.measured if i >= n_plan)}

    def generated_fields(self, index: int) -> dict:
        """A chosen candidate from the generated pool, for the log (it is not in the plan file):
        ``generated: true``, its pose group, IK branch and joint angles (deg); {} for the plan's own."""
        if index < len(self.plan_configs):
            return {}
        cfg = self.configs[index]
        return {"generated": True, "pose": cfg.pose, "branch": cfg.branch,
                "q_deg": [round(float(math.degrees(v)), 6) for v in cfg.q_rad]}

    def record_status(self, st: Status) -> dict:
        """One history row (also the ``adaptive_status`` event's fields)."""
        r6 = lambda v: None if v is None else round(v, 6)  # noqa: E731
        row = {"n": st.n_measured, "max_half_width_deg": round(st.max_half_width_deg, 6),
               "workspace_mm": round(st.workspace_mm, 6), "full_workspace_mm": round(st.full_workspace_mm, 6),
               "held_out_mm": round(st.held_out_mm, 6), "full_held_out_mm": round(st.full_held_out_mm, 6),
               "region_mm": round(st.region_mm, 6), "joint_space_mm": r6(st.joint_space_mm),
               "full_joint_space_mm": r6(st.full_joint_space_mm),
               "sigma_mm": round(self.design.sigma_mm, 5), "misfit_mm": round(self.design.misfit_mm, 5),
               "sigma_from": "fit" if self.fitted_sigma_mm is not None else "spread"}
        self.history.append(row)
        return row

    def decision(self, st: Status) -> dict:
        """What backs a stop decision: every stated criterion (limit, predicted, met), the noise
        it was judged with (the plan's per reading and per configuration, the readings' spread, the
        fit's σ, the misfit, the σ used) and the predicted errors against the full plan's."""
        r6 = lambda v: None if v is None else round(float(v), 6)  # noqa: E731
        d = self.design
        return {"checks": [c.to_dict() for c in st.checks],
                "noise": {"plan_per_reading_mm": self.noise_mm, "samples": self.samples,
                          "plan_per_configuration_mm": r6(self.plan_sigma_mm), "spread_mm": r6(self.spread_sigma_mm),
                          "fitted_mm": r6(self.fitted_sigma_mm), "misfit_mm": r6(d.misfit_mm), "used_mm": r6(d.sigma_mm)},
                "predicted": {"max_half_width_deg": r6(st.max_half_width_deg),
                              "full_max_half_width_deg": r6(max(d.half_widths_deg(d.covariance(
                                  range(d.model.n_plan))).values(), default=0.0)),
                              "region_mm": r6(st.region_mm), "full_region_mm": r6(st.full_region_mm),
                              "joint_space_mm": r6(st.joint_space_mm), "full_joint_space_mm": r6(st.full_joint_space_mm),
                              "held_out_mm": r6(st.held_out_mm), "full_held_out_mm": r6(st.full_held_out_mm)}}

    # ------------------------------------------------------------------ cell time
    def full_plan_seconds(self, start_q_rad: np.ndarray) -> float:
        """Estimated cell time of the whole plan in the run's usual order from ``start_q_rad``."""
        from acquire.run.sequencer import move_times, order_configurations

        order = order_configurations(self.plan_configs, start_q_rad, self.limits, self.speed)
        return float(move_times(order, start_q_rad, self.limits, self.speed).sum() + len(order) * self.per_config_s)

    def visited_seconds(self, visited, start_q_rad: np.ndarray) -> float:
        """Estimated cell time of the configurations ``visited`` (in that order) from ``start_q_rad``."""
        from acquire.run.sequencer import move_times

        return float(move_times(list(visited), start_q_rad, self.limits, self.speed).sum()
                     + len(visited) * self.per_config_s)


def found_after_the_fact(ad: dict, fit: dict) -> dict:
    """What the run's fit found, beside what the stop was predicted with (``AdaptiveRun.summary``'s
    ``decision``): the largest 95 % half-width (deg) of the offsets the design called determinable
    that the fit determined, the fit's σ (mm, largest over sensors) and, with it, the misfit over
    the readings' spread; and the predicted values they stand against. ``fit``: result.json's document."""
    names = {n.split(".")[0] for n in ad.get("half_width_deg", {})}
    widths = [(e["ci95_deg"][1] - e["ci95_deg"][0]) / 2 for e in fit.get("joint_offsets", [])
              if e.get("joint") in names and e.get("ci95_deg")]
    sigmas = [v["value"] for v in (fit.get("sigma_mm") or {}).values() if v and v.get("value") is not None]
    sigma = max(sigmas) if sigmas else None
    noise = (ad.get("decision") or {}).get("noise", {})
    spread = noise.get("spread_mm")
    misfit = None if sigma is None or spread is None else math.sqrt(max(0.0, sigma**2 - spread**2))
    pred = (ad.get("decision") or {}).get("predicted", {})
    return {"max_half_width_deg": round(max(widths), 6) if widths else None,
            "determined": len(widths), "of": len(names),
            "predicted_max_half_width_deg": pred.get("max_half_width_deg"),
            "sigma_mm": None if sigma is None else round(sigma, 6), "predicted_sigma_mm": noise.get("used_mm"),
            "misfit_mm": None if misfit is None else round(misfit, 6), "predicted_misfit_mm": noise.get("misfit_mm")}


def admissible_pool(pool, limits, margin_rad: float) -> list:
    """The generated candidates (``PlannedConfig``) a run may choose: those inside the commander's
    joint limits less its margin (the plan's configurations were checked against the model's
    limits at load; the pool also against what the open commander reports), ids not repeated."""
    lo = np.asarray(limits.lower_rad, dtype=float) + margin_rad
    hi = np.asarray(limits.upper_rad, dtype=float) - margin_rad
    out, seen = [], set()
    for c in pool:
        q = np.asarray(c.q_rad, dtype=float)
        if q.shape == lo.shape and np.all((q >= lo) & (q <= hi)) and c.config_id not in seen:
            out.append(c)
            seen.add(c.config_id)
    if len(out) < len(pool):
        log.info("adaptive: %d of %d generated candidates outside the commander's limits less %.3g°; not chosen",
                 len(pool) - len(out), len(pool), math.degrees(margin_rad))
    return out


def simulate(order: AdaptiveOrder, start_q_rad: np.ndarray, *, to_the_end: bool = False) -> tuple[list, Status]:
    """The choices an adaptive run would make if every configuration is measured and the noise is
    the plan's (σ = noise_mm): (configurations in order, final status). For ``--dry-run``.
    to_the_end: ignore the criteria, choose until ``max_configurations`` or the plan's end (the
    longest the run can take)."""
    order = order.copy()
    order.require_fit = False
    if to_the_end:
        from dataclasses import replace

        order.design.rule = replace(order.design.rule, interval_deg=1e-12, workspace_within_pct=None,
                                    held_out_within_pct=None, region_error_mm=None, joint_space_error_mm=None,
                                    joint_space_within_pct=None)
    here = np.asarray(start_q_rad, dtype=float)
    chosen = []
    st = order.status()
    while not st.stop:
        cfg, _ = order.choose(here)
        order.mark(cfg.config_id)
        chosen.append(cfg)
        here = np.asarray(cfg.q_rad, dtype=float)
        st = order.status()
    return chosen, st


class AdaptiveRun:
    """An adaptive run's side of ``RunController._run``: the design over the plan's ``configs``,
    rebuilt from a resumed log (its samples are measured, its ``ended`` ids are not chosen), the
    choices as the run goes (``choices``: a generator of configurations, each with an
    ``adaptive_choice`` event), each outcome (``outcome``), and the summary at the end.

    cmd: the open commander (its limits; where the robot stands before each choice).
    lookahead: compute each next choice while the current configuration is measured
    (``acquire.run.lookahead``): "process" (a worker process, as ``RunController`` runs),
    "inline" (computed in the caller when the configuration is handed out: tests, studies) or
    None (computed after each outcome). The choices are the same; only the seconds the robot
    stands while the run chooses differ.
    """

    def __init__(self, lp, configs, cmd, speed: float, per_config_s: float, resumed, ended, start_q_rad,
                 pool=(), *, lookahead: str | None = None) -> None:
        self.cmd = cmd
        self.order = AdaptiveOrder(lp, configs, cmd.limits, speed, per_config_s, pool)
        for rec in (resumed.samples if resumed is not None else []):
            self.order.mark(rec["config_id"], rec)
        for cid in ended:
            if cid not in {rec["config_id"] for rec in self.order.records}:
                self.order.drop(cid)
        self.order.use_sigma(self.order.sigma_count())  # σ as the uninterrupted run had it
        self.start_q = np.asarray(start_q_rad, dtype=float)
        self.resumed_n = len(self.order.design.measured)
        self.visited: list = []  # configurations this segment moved to, in order
        self.final: Status | None = None
        self.compute_s = 0.0  # wall seconds the robot stood while this segment chose and refitted
        self._last_outcome: str | None = None
        self.predicted, self.predicted_status = simulate(self.order, self.start_q)
        self.lookahead = None
        if lookahead is not None:
            from acquire.run.lookahead import Lookahead

            self.lookahead = Lookahead.start(self.order, lookahead)

    def started_fields(self) -> dict:
        rule = self.order.design.rule
        o = self.order
        return {"stop_when": {"interval_deg": rule.interval_deg, "workspace_within_pct": rule.workspace_within_pct,
                              "held_out_within_pct": rule.held_out_within_pct},
                "min_configurations": rule.min_configurations, "max_configurations": rule.max_configurations,
                "candidates": len(o.plan_configs), **o.pool_fields(), "measured_before": self.resumed_n,
                "determinable": list(o.design.model.offset_names), "noise_mm": o.noise_mm,
                "sigma_per_configuration_mm": round(o.plan_sigma_mm, 6),
                "predicted_configurations": len(self.predicted) + self.resumed_n,
                "predicted_seconds": round(o.visited_seconds(self.predicted, self.start_q), 1),
                "full_plan_seconds": round(o.full_plan_seconds(self.start_q), 1)}

    def _here(self, last) -> np.ndarray:
        """Where the next choice starts: the last configuration when it was measured (the robot
        settled there, within the plan's tolerance; a choice computed ahead assumed it), else
        where the robot reports it stands."""
        from drivers.errors import DriverError

        if last is not None and self._last_outcome == "measured":
            return np.asarray(last.q_rad, dtype=float)
        try:
            return np.asarray(self.cmd.joint_state().position_rad, dtype=float)
        except DriverError:
            return np.asarray(last.q_rad, dtype=float) if last is not None else self.start_q

    def _stop_status(self) -> Status:
        """The rule at this many records, with the σ the choices use; a predicted stop is judged
        again with σ of every record, and when it does not hold the next choice is made with that
        σ too (the rule already holds at the schedule's σ: a choice with it would plan nothing).
        Both are functions of the records: a resumed run decides and chooses the same."""
        o = self.order
        o.use_sigma(o.sigma_count())
        st = o.status()
        if (st.stop or o.held_for_fit) and o.sigma_stale():
            o.use_sigma(len(o.records))
            st = o.status()
        return st

    def choices(self, event):
        """Configurations to measure, chosen one at a time; stops when the rule holds, the plan
        is exhausted or ``max_configurations`` is reached (event ``adaptive_stop``). With a
        look-ahead the choice after each configuration is computed while it is measured and used
        when the state it assumed is the state after the outcome (event field ``precomputed``)."""
        last = None
        try:
            while True:
                t0 = time.perf_counter()
                ahead = self.lookahead.result(self.order) if self.lookahead is not None else None
                st = self._stop_status()
                row = self.order.record_status(st)
                if st.stop:
                    self.final = st
                    self.compute_s += time.perf_counter() - t0
                    return
                here = self._here(last)
                taken = ahead.choice(self.order, here) if ahead is not None else None
                cfg, why = taken if taken is not None else self.order.choose(here)
                if self.lookahead is not None:
                    if ahead is not None:
                        self.lookahead.count(taken is not None)
                    why["precomputed"] = taken is not None
                self.compute_s += time.perf_counter() - t0
                event("adaptive_choice", **why, status=row)
                if self.lookahead is not None:
                    self.lookahead.submit(self.order, cfg)
                self.visited.append(cfg)
                last = cfg
                yield cfg
        finally:
            self.close()

    def outcome(self, cfg, outcome: str, record: dict | None) -> None:
        """What became of ``cfg``: measured (its record joins the design's σ), skipped or failed."""
        self._last_outcome = outcome
        if outcome == "measured":
            ok = record is not None and record.get("config_id") == cfg.config_id
            self.order.mark(cfg.config_id, record if ok else None)
        elif outcome in ("skipped", "failed"):
            self.order.drop(cfg.config_id)

    def close(self) -> None:
        """End the look-ahead worker (idempotent; ``choices`` does it when the run stops)."""
        if self.lookahead is not None:
            self.lookahead.close()

    def summary(self) -> dict:
        """Why the run stopped, the predicted intervals against the number of configurations, and
        the estimated cell time of what was visited against the full plan's: moves, settling and
        measuring as the plan's estimate has them, plus the seconds (wall) the robot stood while
        this segment chose and refitted (``compute_seconds``; a fixed-order run has none)."""
        o = self.order
        st = self.final if self.final is not None else o.status()
        full = o.full_plan_seconds(self.start_q)
        before = [o.configs[i] for i in o.design.measured[: self.resumed_n]]
        spent = o.visited_seconds(before + self.visited, self.start_q) + self.compute_s
        return {"stopped": self.final is not None, "reason": st.reason if self.final is not None else
                "the run ended before the stop rule was evaluated (aborted or failed)",
                "measured": st.n_measured, "candidates": len(o.plan_configs), **o.pool_fields(),
                "half_width_deg": {k: round(v, 6) for k, v in st.half_width_deg.items()},
                "workspace_mm": round(st.workspace_mm, 6), "full_workspace_mm": round(st.full_workspace_mm, 6),
                "held_out_mm": round(st.held_out_mm, 6), "full_held_out_mm": round(st.full_held_out_mm, 6),
                "sigma_mm": round(o.design.sigma_mm, 5),
                "fitted_sigma_mm": None if o.fitted_sigma_mm is None else round(o.fitted_sigma_mm, 5),
                "decision": o.decision(st),
                "history": o.history, "estimated_seconds": round(spent, 1),
                "compute_seconds": round(self.compute_s, 1), "full_plan_seconds": round(full, 1),
                **({"lookahead": self.lookahead.stats()} if self.lookahead is not None else {}),
                "saved_seconds": round(full - spent, 1), "saved_pct": round(100 * (1 - spent / full), 1) if full else None}
