"""The data choose the model: candidate calibration models scored by cross-validated prediction
error on held-out configurations.

Candidates (``candidates``), simplest first:

``offsets``                 zero-offsets and the registration; the model's tool taken as exact;
``offsets+tool``            … and the measured markers' positions on the flange (tool prior);
``offsets+tool+links``      … and every link parameter under a Gaussian prior whose scale is
                            estimated from the data (empirical Bayes: a length scale (mm) and an
                            angle scale (deg), the pair that maximises the Laplace evidence,
                            ``empirical_link_scale``);
``full``                    full identification (``calib.fit.identification``, one staged start per fold);

each model with link masses also ``+compliance`` (joint compliance under gravity, ``calib.robot.gravity``;
not for ``full``, whose prediction here is geometric).

Scoring (``choose_model``): the configurations (or pose groups, where the data has them) are split
into K folds; each candidate is fitted (posterior mode, ``calib.fit.offsets.fit_mode``) on the other folds
and predicts the held-out configurations through the registration of that fit — never re-fitted on
the scored points. Only rows of markers the training folds measured are scored, the same rows for
every candidate. Per held-out configuration the error is the rms distance |measured − predicted|
(mm) over its rows; a candidate's score is the mean of those with its standard error, and their rms.
The uncalibrated (nominal) model, registered on the training folds, is scored alike. The chosen
model is the simplest whose mean is within one standard error of the best (the "one-standard-error
rule", Hastie, Tibshirani & Friedman, *Elements of Statistical Learning*, §7.10).

The link scale is a hyperparameter fitted to data, so it is part of what is validated: each fold
estimates its own from its training configurations (``empirical_link_scale`` on them), and the
held-out configurations never inform the scale they are scored with (the scale of all the data
would leak them into the choice). Each fold's search starts where that of all the data does (the
grid's middle), not at the all-data answer: where the evidence is flat between two scales the
starting point decides, and on the real UR10 series D a start at the all-data scale gave it in 5
of 5 folds where a start at the middle gave it in 1. The fit of the chosen model uses the scale of
all the data.
The table states the folds' scales beside it. (On the first 14 nuisance cells of
``tests/bench/study_model_choice.py`` the folds' scales were the all-data scale in 69 of 70 folds;
the chosen model and its cross-validated mean error, to 0.1 µm, were the same in all 14 cells as
with the all-data scale in every fold: the leak was real but did not move the choice there.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np

from calib.measure.dataset import Dataset
from calib.fit.offsets import FitOptions, ModeFit, _prior_precision, fit_mode
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.fit.link_scale import ANGLES_DEG, LENGTHS_MM, maximise_evidence
from calib.fit.registration import register_least_squares
from calib.fit.heldout_misfit import birge_ratio, heldout_chi2
from calib.fit.progress import Progress

#: Candidate kinds, simplest first (their rank orders "simplest" in the one-standard-error rule).
KINDS = ("offsets", "offsets+tool", "offsets+tool+links", "full")
#: Relative tolerance of the fold fits' solves: far below any held-out error that matters.
CV_TOL = 1e-8


@dataclass(frozen=True)
class Candidate:
    """A model to compare: ``kind`` of ``kinds`` (simplest first), with joint ``compliance`` or not."""

    kind: str
    compliance: bool = False
    kinds: ClassVar[tuple[str, ...]] = KINDS

    @property
    def name(self) -> str:
        return self.kind + ("+compliance" if self.compliance else "")

    @property
    def rank(self) -> float:
        return self.kinds.index(self.kind) + (0.5 if self.compliance else 0.0)


#: The model of the offsets a controller is given (``calib.fit.entered``).
ENTERED = Candidate("offsets+tool")


def candidates(model: RobotModel, *, include_full: bool = True, compliance_only: bool = False) -> list[Candidate]:
    """Every candidate for ``model``: the compliance variants only with link masses
    (``compliance_only``: only those — ``--compliance``)."""
    kinds = KINDS if include_full else KINDS[:-1]
    out = [] if compliance_only else [Candidate(k) for k in kinds]
    if model.has_dynamics:
        out += [Candidate(k, True) for k in kinds if k != "full"]
    if not out:
        raise ValueError(f"{model.name}: the compliance model needs link masses and centres of mass in the robot model")
    return sorted(out, key=lambda c: c.rank)


def parse_candidate(name: str, model: RobotModel) -> Candidate:
    """``--model NAME`` as a candidate; ValueError naming the known ones."""
    known = {c.name: c for c in candidates(model)}
    if name not in known:
        raise ValueError(f"model {name!r} unknown for {model.name}; known: {', '.join(known)}")
    return known[name]


def options_for(candidate: Candidate, base: FitOptions, link_tolerance: tuple[float, float] | None) -> FitOptions:
    """The ``FitOptions`` of a non-full candidate, from the user's ``base`` (joints, registration,
    error model, tool prior, seed)."""
    tool = base.tool_prior_mm if candidate.kind != "offsets" else 0.0
    links = link_tolerance if candidate.kind == "offsets+tool+links" else None
    if candidate.kind == "offsets+tool+links" and links is None:
        raise ValueError("the offsets+tool+links candidate needs a link scale")
    return replace(base, tool_prior_mm=tool, link_tolerance=links, compliance=candidate.compliance)


# --- empirical Bayes for the link prior's scale ----------------------------------------------------
def log_evidence(mf: ModeFit) -> float:
    """Laplace approximation of log p(data | priors) at the mode, σ at its mode, up to a constant
    that does not depend on the link prior's scale (the flat-prior parameters' terms cancel
    between scales with the same free parameters)."""
    post, theta = mf.post, mf.theta
    sigma = np.exp(mf.log_sigma)[post.sensor_index]  # (k,)
    r = post.residuals(theta)
    loglik = -0.5 * float(np.sum(r**2 / sigma[:, None] ** 2)) - 3.0 * float(np.sum(np.log(sigma)))
    pos, sd = post.link_free()
    logprior = -0.5 * float(np.sum((theta[pos] / sd) ** 2)) - float(np.sum(np.log(sd)))
    j = post.jacobian(theta).reshape(post.n_rows, 3, -1)
    h = np.einsum("kip,k,kiq->pq", j, sigma**-2, j) + _prior_precision(post)
    sign, logdet = np.linalg.slogdet(h)
    return loglik + logprior - 0.5 * logdet if sign > 0 else -math.inf


def _link_groups(post) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions in the free vector, their prior sds, group) of the Gaussian-prior entries; group
    0: a tool marker's coordinate (its sd stays), 1: a length (d, a; mm), 2: an angle (α, β; rad)."""
    pos, sd = post.link_free()
    start = post.n + 6 * post.S
    group = np.zeros(pos.size, dtype=int)
    for i, p in enumerate(pos):
        link = post.free[p] - start
        if not post.is_tool[link]:
            kind = post.chain.param_names[post.link_idx[link]].rsplit(".", 1)[1]
            group[i] = 1 if kind in ("d", "a") else 2
    return pos, sd, group


def linearised_log_evidence(mf: ModeFit):
    """``f(mm, deg)``: the Laplace log evidence of the model linearised at the mode ``mf`` (fitted
    under some link prior) with the link prior's length sd ``mm`` and angle sd ``deg`` instead —
    exact for a linear model, and link errors of a millimetre or a degree move the kinematics
    linearly to ~1e-4 mm. One fit then prices every scale: the new mode is one Newton step
    (H = JᵀWJ + P, g = JᵀWr + Pθ), its objective Φ(θ) − ½ gᵀH⁻¹g. σ stays at the fit's."""
    post, theta = mf.post, mf.theta
    sigma = np.exp(mf.log_sigma)[post.sensor_index]
    r = post.residuals(theta).reshape(-1)
    j = post.jacobian(theta).reshape(post.n_rows * 3, -1)
    w = np.repeat(sigma**-2, 3)
    a = j.T @ (w[:, None] * j)
    g_data = j.T @ (w * r)
    chi2 = float(np.sum(w * r**2))
    pos, sd0, group = _link_groups(post)
    const = -3.0 * float(np.sum(np.log(sigma)))

    def evidence(mm: float, deg: float) -> float:
        sd = np.where(group == 1, mm, np.where(group == 2, math.radians(deg), sd0))
        prec = np.zeros(post.dim)
        prec[pos] = sd**-2.0
        h = a + np.diag(prec)
        g = g_data + prec * theta
        sign, logdet = np.linalg.slogdet(h)
        if sign <= 0:
            return -math.inf
        phi = 0.5 * chi2 + 0.5 * float(np.sum(prec * theta**2)) - 0.5 * float(g @ np.linalg.solve(h, g))
        return const - phi - float(np.sum(np.log(sd))) - 0.5 * logdet

    return evidence


def empirical_link_scale(model: RobotModel, data: Dataset, base: FitOptions, lengths_mm: tuple[float, ...] = LENGTHS_MM,
                         angles_deg: tuple[float, ...] = ANGLES_DEG, *, start: ModeFit | None = None) -> dict:
    """The link prior's length (mm) and angle (deg) scales that maximise the Laplace evidence of
    the offsets+tool+links model on ``data``, each on its own grid (``calib.fit.link_scale``):
    the mode is fitted under a middle scale, every pair of the grids priced by
    ``linearised_log_evidence``, and the mode fitted again at the best pair until it stays (at most
    three fits). {"length_mm", "angle_deg", "log_evidence": {"mm/deg": value}, "at_grid_edge", "fits"}.
    ``start``: where the mode fits start (``fit_mode``); the grid search itself always starts at
    the middle scale."""
    ref = (lengths_mm[len(lengths_mm) // 2], angles_deg[len(angles_deg) // 2])
    for fits in range(1, 4):
        ev = linearised_log_evidence(fit_mode(model, data, replace(base, link_tolerance=ref), tol=CV_TOL, start=start))
        found = maximise_evidence(ev, lengths_mm, angles_deg, exhaustive=True)
        best = (found["length_mm"], found["angle_deg"])
        if best == ref:
            break
        ref = best
    found["fits"] = fits
    return found


# --- cross-validation ------------------------------------------------------------------------------
def fold_labels(data: Dataset, k: int = 5, seed: int = 0) -> tuple[np.ndarray, str]:
    """(rows,) fold number per row, and what was grouped ("pose group" where every row has one,
    else "configuration"): the groups are shuffled (seeded) and dealt round-robin into ``k`` folds."""
    by_pose = bool(np.all(data.pose != ""))
    groups = data.pose if by_pose else data.config
    names = np.unique(groups)
    if names.size < 2:
        raise ValueError(f"cross-validation needs at least 2 {'pose groups' if by_pose else 'configurations'}")
    k = min(k, names.size)
    order = np.random.default_rng(seed).permutation(names.size)
    fold_of = {names[i]: f % k for f, i in enumerate(order)}
    return np.array([fold_of[g] for g in groups]), ("pose group" if by_pose else "configuration")


@dataclass
class Score:
    """One candidate's cross-validated error: per held-out configuration the rms distance (mm)."""

    name: str
    rank: float
    n_params: int | None
    errors_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    failed: str | None = None
    configs: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))  # names, as errors_mm
    #: Σ r²/v and the number of held-out coordinates (``calib.fit.heldout_misfit``); 0 where not computed.
    chi2: float = 0.0
    n_chi2: int = 0

    @property
    def misfit(self) -> float | None:
        """The held-out Birge ratio (``calib.fit.heldout_misfit``): 1 for a model that describes the data."""
        return birge_ratio(self.chi2, self.n_chi2) if not self.failed else None

    @property
    def mean_mm(self) -> float:
        return float(self.errors_mm.mean()) if self.errors_mm.size and not self.failed else math.inf

    @property
    def se_mm(self) -> float:
        e = self.errors_mm
        return float(e.std(ddof=1) / math.sqrt(e.size)) if e.size > 1 and not self.failed else math.inf

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.errors_mm**2))) if self.errors_mm.size and not self.failed else math.inf

    def worst(self, n: int = 3) -> list[list]:
        """The ``n`` held-out configurations with the largest errors: [[name, mm], …]."""
        if self.failed or self.configs.size != self.errors_mm.size:
            return []
        return [[str(self.configs[i]), float(self.errors_mm[i])] for i in np.argsort(-self.errors_mm)[:n]]

    def to_dict(self) -> dict:
        med = float(np.median(self.errors_mm)) if self.errors_mm.size and not self.failed else math.inf
        return {"model": self.name, "free_parameters": self.n_params, "cv_rms_mm": _num(self.rms_mm),
                "cv_mean_mm": _num(self.mean_mm), "cv_se_mm": _num(self.se_mm), "cv_median_mm": _num(med),
                "worst_configurations": self.worst(), "heldout_misfit": self.misfit, "failed": self.failed}


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


@dataclass
class ModelChoice:
    """The cross-validation table and the choice (``choose_model``)."""

    scores: list[Score]
    nominal: Score
    chosen: str
    forced: bool
    folds: int
    grouping: str
    link_scale: dict | None
    #: Candidates left out of the comparison and why (one line), or None.
    excluded: str | None = None
    #: Candidate name → its mode on all the data (``choose_model``), where the chosen one's fit starts.
    starts: dict[str, ModeFit] = field(default_factory=dict, repr=False)
    #: Fold → the offsets (n,) rad and fitted axes (n,) bool of ``ENTERED`` fitted on the other
    #: folds (``FoldResult.entered``), where it was a candidate: ``calib.fit.entered`` reuses them.
    entered_folds: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    def score(self, name: str) -> Score:
        return next(s for s in self.scores if s.name == name)

    def to_dict(self) -> dict:
        return {"chosen": self.chosen, "forced": self.forced, "folds": self.folds, "grouped_by": self.grouping,
                "rule": "the simplest model within one standard error of the best cross-validated mean error",
                "nominal": self.nominal.to_dict(), "candidates": [s.to_dict() for s in self.scores],
                "link_scale": self.link_scale, "excluded": self.excluded}

    def format(self) -> str:
        lines = [f"model choice: {self.folds}-fold cross-validation by {self.grouping} (fit on the other folds, "
                 "held-out configurations scored with that fit's registration)",
                 f"  {'model':<32}{'free':>6}{'CV rms (mm)':>13}{'CV mean ± se (mm)':>22}{'misfit':>8}"]
        if all(s.failed for s in self.scores):
            lines.append("  no model could be fitted on the training folds (too few configurations): the simplest "
                         f"({self.chosen}) is fitted unvalidated, and nothing is marked \"enter\"")
        for s in [self.nominal] + self.scores:
            if s.failed:
                lines.append(f"  {s.name:<32}{'—' if s.n_params is None else s.n_params:>6}  failed: {s.failed}")
                continue
            mark = "  ← chosen" + (" (--model)" if self.forced else "") if s.name == self.chosen else ""
            lines.append(f"  {s.name:<32}{'—' if s.n_params is None else s.n_params:>6}{s.rms_mm:>13.4f}"
                         f"{s.mean_mm:>13.4f} ± {s.se_mm:.4f}{_misfit_text(s.misfit):>8}{mark}")
        if self.excluded:
            lines.append(f"  not compared: {self.excluded}")
        if any(s.misfit is not None for s in self.scores):  # (socket scores and full identification have none)
            lines.append(_scale_line(self.score(self.chosen).misfit if self.chosen in {s.name for s in self.scores} else None))
        if self.link_scale:
            how = "given" if self.link_scale.get("given") else "empirical Bayes, max evidence"
            lines.append(f"  link prior of offsets+tool+links ({how}): lengths ±{self.link_scale['length_mm']:g} mm, "
                         f"angles ±{self.link_scale['angle_deg']:g}°" + fold_scale_text(self.link_scale))
        return "\n".join(lines)


def interval_factor(misfit: float | None) -> float:
    """The factor the chosen model's offset intervals are widened by: its held-out misfit where
    above 1 (``calib.fit.heldout_misfit``), else 1."""
    return misfit if misfit is not None and misfit > 1.0 else 1.0


def _misfit_text(misfit: float | None) -> str:
    return "—" if misfit is None else f"{misfit:.2f}"


def _scale_line(misfit: float | None) -> str:
    """What the misfit column means, and what it did to the chosen model's intervals."""
    what = ("  misfit: held-out error ÷ the spread each fold's fit predicts for it (a Birge ratio on data the fit "
            "never saw; 1 = the model describes the data)")
    f = interval_factor(misfit)
    return what + (f"; the chosen model's σ scaled ×{f:.2f} by held-out misfit" if f > 1.0 else "")


def fold_scale_text(scale: dict) -> str:
    """The folds' own link scales (``cross_validate``), as ``; folds: 1 mm/0.3° ×4, 0.3 mm/0.3° ×1``."""
    per = scale.get("per_fold")
    if not per:
        return ""
    counts: dict[str, int] = {}
    for t in per:
        key = f"{t[0]:g} mm/{t[1]:g}°" if t else "not estimated"
        counts[key] = counts.get(key, 0) + 1
    return "; each fold its own (on its training configurations): " + ", ".join(f"{k} ×{v}" for k, v in counts.items())


def format_table(mc: dict) -> str:
    """The cross-validation table of a result document's ``model_choice`` (``ModelChoice.to_dict``,
    tracker or socket) as text: for summaries printed from ``result.json``."""
    lines = [f"model choice ({mc['folds']}-fold cross-validation by {mc['grouped_by']}; {mc['rule']}):",
             f"  {'model':<50}{'free':>6}{'held-out rms (mm)':>19}{'mean ± se (mm)':>20}{'misfit':>8}"]
    for c in [mc["nominal"]] + mc["candidates"]:
        free = "—" if c.get("free_parameters") is None else c["free_parameters"]
        if c.get("failed") or c.get("cv_mean_mm") is None:
            lines.append(f"  {c['model']:<50}{free:>6}  failed: {c.get('failed') or 'not scored'}")
            continue
        mark = "  ← chosen" + (" (--model)" if mc.get("forced") else "") if c["model"] == mc["chosen"] else ""
        se = "—" if c.get("cv_se_mm") is None else f"{c['cv_se_mm']:.4f}"
        lines.append(f"  {c['model']:<50}{free:>6}{c['cv_rms_mm']:>19.4f}{c['cv_mean_mm']:>12.4f} ± {se}"
                     f"{_misfit_text(c.get('heldout_misfit')):>8}{mark}")
    if mc.get("excluded"):
        lines.append(f"  not compared: {mc['excluded']}")
    if any(c.get("heldout_misfit") is not None for c in mc["candidates"]):
        lines.append(_scale_line(next((c.get("heldout_misfit") for c in mc["candidates"] if c["model"] == mc["chosen"]), None)))
    return "\n".join(lines)


def config_errors(data: Dataset, dist: np.ndarray) -> np.ndarray:
    """Per configuration of ``data``, the rms of ``dist`` (rows,) over its rows."""
    _, inv = np.unique(data.config, return_inverse=True)
    inv = inv.ravel()
    return np.sqrt(np.bincount(inv, dist**2) / np.bincount(inv))


def _nominal_distances(model: RobotModel, train: Dataset, test: Dataset) -> np.ndarray:
    chain = Chain(model)
    out = np.zeros(len(test))

    def base(ds: Dataset) -> np.ndarray:
        p = chain.marker_positions(ds.q_rad)
        return p[np.arange(len(ds)), [chain.marker_names.index(m) for m in ds.marker]]

    pb_train, pb_test = base(train), base(test)
    for s in np.unique(test.sensor):
        tr, te = train.sensor == s, test.sensor == s
        reg = register_least_squares(pb_train[tr], train.xyz_mm[tr]).base2sensor
        pred = pb_test[te] @ reg[:3, :3].T + reg[:3, 3]
        out[te] = np.linalg.norm(test.xyz_mm[te] - pred, axis=1)
    return out


def _full_fit(model: RobotModel, train: Dataset, base: FitOptions):
    from calib.fit.identification import IdentOptions, identify

    exclude = tuple((f"{model.axis_names[i]}.offset", "not in --joints") for i in range(model.n_joints)
                    if base.joints is not None and i + 1 not in base.joints)
    return identify(model, train, IdentOptions(tool_prior_mm=base.tool_prior_mm, n_starts=1, seed=base.seed,
                                               exclude_reasons=exclude))


def _candidate_distances(candidate: Candidate, model: RobotModel, train: Dataset, test: Dataset, base: FitOptions,
                         link_tolerance, start: ModeFit | None = None
                         ) -> tuple[np.ndarray, int, tuple[float, int], ModeFit | None]:
    """(held-out distances (rows of ``test``,) mm, free parameters, (Σ r²/v, coordinates) of the
    held-out misfit — (0, 0) for full identification —, the mode fit or None for full
    identification) of ``candidate`` fitted on ``train``, its solves started at ``start`` (``fit_mode``)."""
    if candidate.kind == "full":
        from calib.fit.identification import pose_errors

        res = _full_fit(model, train, base)
        return pose_errors(model, res.params, test, res.base2sensor), len(res.free_names), (0.0, 0), None
    mf = fit_mode(model, train, options_for(candidate, base, link_tolerance), tol=CV_TOL, start=start)
    return np.linalg.norm(mf.predict_residuals(test), axis=1), mf.post.dim, heldout_chi2(mf, test), mf


@dataclass
class FoldJob:
    """What every fold of ``cross_validate`` shares (given once to each worker process)."""

    model: RobotModel
    data: Dataset
    labels: np.ndarray
    cands: list[Candidate]
    base: FitOptions
    link_tolerance: tuple[float, float] | None
    starts: dict[str, ModeFit]


@dataclass
class FoldResult:
    """One fold's scores: ``configs`` (the held-out configurations, ``config_errors``' order),
    ``nominal`` (their errors, mm), ``scale`` (the fold's link scale (mm, deg) or None) and why it
    is missing, and per candidate either (per-configuration errors, free parameters, Σ r²/v,
    coordinates) or the reason it failed (None: not fitted). ``entered``: the offsets (n,) rad and
    the fitted axes (n,) bool of the controller's model (``ENTERED``) on the other folds, where
    it was a candidate (``calib.fit.entered.heldout_by_folds`` scores that robot with them)."""

    configs: np.ndarray
    nominal: np.ndarray
    scale: tuple[float, float] | None
    scale_failed: str | None
    per: list[tuple[np.ndarray, int, float, int] | str | None]
    entered: tuple[np.ndarray, np.ndarray] | None = None


def fold_scores(job: FoldJob, fold: int, skip: frozenset[int] = frozenset(), progress=None) -> FoldResult | None:
    """Fold ``fold`` of ``cross_validate``: every candidate (but those of ``skip``, by index)
    fitted on the other folds and scored on this one; None where the fold has no row to score."""
    model, data, cands, base = job.model, job.data, job.cands, job.base
    train, test = data.subset(job.labels != fold), data.subset(job.labels == fold)
    ok = np.isin(test.marker, np.unique(train.marker)) & np.isin(test.sensor, np.unique(train.sensor))
    if not ok.any():
        return None
    test = test.subset(ok)
    nominal = config_errors(test, _nominal_distances(model, train, test))
    tol, why = job.link_tolerance, None
    if tol is None and any(c.kind == "offsets+tool+links" for c in cands):
        try:  # the fold's own scale: its held-out configurations never inform it
            found = empirical_link_scale(model, train, replace(base, compliance=False), start=next(
                (job.starts[n] for n in ("offsets+tool+links", "offsets+tool+links+compliance") if n in job.starts), None))
            tol = (found["length_mm"], found["angle_deg"])
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            why = f"fold {fold + 1}: the link scale could not be estimated on its training configurations: {exc}"
    out = FoldResult(np.unique(test.config), nominal, tol, why, [None] * len(cands))
    n_folds = int(job.labels.max()) + 1
    for i, c in enumerate(cands):
        if i in skip:
            continue
        if c.kind == "offsets+tool+links" and tol is None:
            out.per[i] = why
            continue
        if progress is not None:
            progress.step(f"cross-validation: fold {fold + 1} of {n_folds}, model {i + 1} of {len(cands)} ({c.name})")
        try:
            dist, n_params, (chi2, n_chi2), mf = _candidate_distances(c, model, train, test, base, tol, job.starts.get(c.name))
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            out.per[i] = f"fold {fold + 1}: {exc}"
            continue
        if not np.all(np.isfinite(dist)):
            out.per[i] = f"fold {fold + 1}: the fit did not converge (non-finite predictions)"
            continue
        out.per[i] = (config_errors(test, dist), n_params, chi2, n_chi2)
        if c == ENTERED and mf is not None:
            out.entered = (mf.post.full_vector(mf.theta)[: model.n_joints].copy(), mf.mask.offsets.copy())
    return out


def _fold_in_worker(job: FoldJob, fold: int) -> FoldResult | None:
    return fold_scores(job, fold)


#: Data of this many rows or more cross-validate their folds in parallel processes (``calib.fit.parallel``);
#: below, the fold fits are short (the README's run of 39 configurations: about 0.4 CPU-s per fold)
#: and the workers' start would take much of what they save; the tests' small cells stay serial.
PARALLEL_MIN_ROWS = 100


def cross_validate(model: RobotModel, data: Dataset, cands: list[Candidate], base: FitOptions,
                   link_tolerance: tuple[float, float] | None, *, k: int = 5, seed: int = 0,
                   fold_scales: list | None = None, starts: dict[str, ModeFit] | None = None,
                   progress: Progress | None = None, entered_folds: dict | None = None,
                   jobs: int | None = None) -> tuple[list[Score], Score, int, str]:
    """K-fold scores of ``cands`` and of the nominal model on ``data`` (see the module's docstring).
    ``link_tolerance`` None with a links candidate: each fold's link scale by empirical Bayes on its
    training configurations, appended to ``fold_scales`` (a list, when given) as (mm, deg) or None
    where it could not be estimated. ``starts``: candidate name → its mode on all the data, where
    that candidate's fold fits start (``fit_mode``); ``progress``: told of each fold fit;
    ``entered_folds`` (a dict, when given): fold → ``FoldResult.entered``, where ``ENTERED`` was fitted.
    ``jobs``: processes for the folds (None: ``calib.fit.parallel.fit_jobs``, with data of at least
    ``PARALLEL_MIN_ROWS`` rows); the scores are the same either way."""
    from calib.fit.parallel import fit_jobs, map_in_order

    labels, grouping = fold_labels(data, k, seed)
    n_folds = int(labels.max()) + 1
    job = FoldJob(model, data, labels, cands, base, link_tolerance, starts or {})
    if jobs is None:
        jobs = fit_jobs(n_folds) if len(data) >= PARALLEL_MIN_ROWS else 1
    if jobs > 1:
        def finished(fold: int, result) -> None:
            for c in cands:
                if progress is not None:
                    progress.step(f"cross-validation: fold {fold + 1} of {n_folds} done in a worker ({c.name})")

        folds = map_in_order(_fold_in_worker, job, range(n_folds), jobs, done=finished)
    else:  # in turn: a candidate that failed in one fold is not fitted in the next
        folds, failed = [], set()
        for f in range(n_folds):
            folds.append(fold_scores(job, f, frozenset(failed), progress))
            if folds[-1] is not None:
                failed |= {i for i, r in enumerate(folds[-1].per) if isinstance(r, str)}
    scores = [Score(c.name, c.rank, None) for c in cands]
    per = [[] for _ in cands]
    nominal_parts, names = [], []
    for f, fold in enumerate(folds):
        if fold is None:
            continue
        names.append(fold.configs)
        nominal_parts.append(fold.nominal)
        if fold_scales is not None:
            fold_scales.append(fold.scale)
        if entered_folds is not None and fold.entered is not None:
            entered_folds[f] = fold.entered
        for i, r in enumerate(fold.per):
            if scores[i].failed or r is None:
                continue
            if isinstance(r, str):
                scores[i].failed = r
                continue
            errors, n_params, chi2, n_chi2 = r
            scores[i].n_params = n_params if scores[i].n_params is None else max(scores[i].n_params, n_params)
            scores[i].chi2 += chi2
            scores[i].n_chi2 += n_chi2
            per[i].append(errors)
    all_names = np.concatenate(names) if names else np.zeros(0, dtype=str)
    for s, parts in zip(scores, per):
        if parts and not s.failed:
            s.errors_mm = np.concatenate(parts)
            s.configs = all_names
    nominal = Score("nominal (uncalibrated)", -1.0, 0, np.concatenate(nominal_parts) if nominal_parts else np.zeros(0),
                    configs=all_names)
    return scores, nominal, n_folds, grouping


def one_se_choice(scores: list[Score]) -> str:
    """The simplest (lowest rank) score whose mean is within one standard error of the best mean."""
    ok = [s for s in scores if not s.failed and s.errors_mm.size]
    if not ok:
        raise ValueError("no candidate model could be fitted in every fold: "
                         + "; ".join(f"{s.name}: {s.failed}" for s in scores))
    best = min(ok, key=lambda s: s.mean_mm)
    return min((s for s in ok if s.mean_mm <= best.mean_mm + best.se_mm), key=lambda s: s.rank).name


def choose_model(model: RobotModel, data: Dataset, base: FitOptions = FitOptions(), *, force: str | None = None,
                 k: int = 5, include_full: bool = True, link_tolerance: tuple[float, float] | None = None,
                 compliance_only: bool = False, progress: Progress | None = None, jobs: int | None = None) -> ModelChoice:
    """Score every candidate and choose; ``force`` (``--model NAME``): that candidate — it is
    fitted on the folds and scored against the nominal model (its held-out misfit still widens its
    intervals, ``interval_factor``), and no other candidate is fitted. ``link_tolerance`` given:
    that link scale instead of the empirical Bayes one. ``progress``: told of each fit; ``jobs``:
    processes for the folds (``cross_validate``; None: as many as the machine has cores for). A forced model
    other than offsets+tool is scored beside offsets+tool, the model of the offsets to enter
    (``calib.fit.entered``), whose held-out misfit widens their intervals.

    Each candidate (but full identification) is first fitted on all the data; its fold fits start
    there (``fit_mode``'s ``start``), and ``ModelChoice.starts`` keeps these fits for the chosen
    model's own (``calib.fit.auto_fit``)."""
    cands = candidates(model, include_full=include_full, compliance_only=compliance_only)
    if force is not None:  # that model, and offsets+tool: its held-out misfit scales the controller's offsets
        cands = [parse_candidate(force, model)]
        if cands[0] != ENTERED:
            cands = sorted(cands + [ENTERED], key=lambda c: c.rank)
    scale = None
    if link_tolerance is None and any(c.kind == "offsets+tool+links" for c in cands):
        scale = empirical_link_scale(model, data, replace(base, compliance=False))
        link_tolerance = (scale["length_mm"], scale["angle_deg"])
    elif link_tolerance is not None:
        scale = {"length_mm": link_tolerance[0], "angle_deg": link_tolerance[1], "given": True}
    starts: dict[str, ModeFit] = {}
    own = [c for c in cands if c.kind != "full"]
    if progress is not None:
        progress.begin("fit of all the data", len(own))
    previous = None
    for c in own:  # simplest first, each from the one before it
        if progress is not None:
            progress.step(f"fit of all the data: {c.name}")
        try:
            starts[c.name] = previous = fit_mode(model, data, options_for(c, base, link_tolerance), tol=CV_TOL,
                                                 start=previous)
        except (ValueError, RuntimeError, np.linalg.LinAlgError):
            pass  # its folds start from the nominal model, and say why they fail where they do
    n_folds_max = min(k, np.unique(data.pose if np.all(data.pose != "") else data.config).size)
    if progress is not None:
        progress.begin("cross-validation", n_folds_max * len(cands))
    fold_scales: list = []
    entered_folds: dict = {}
    scores, nominal, n_folds, grouping = cross_validate(model, data, cands, base, None if scale and not scale.get("given")
                                                        else link_tolerance, k=k, seed=base.seed, fold_scales=fold_scales,
                                                        starts=starts, progress=progress, entered_folds=entered_folds,
                                                        jobs=jobs)
    if scale is not None and not scale.get("given"):
        scale["per_fold"] = [list(t) if t else None for t in fold_scales]
    try:
        chosen = force if force is not None else one_se_choice(scores)
    except ValueError:  # too few configurations to fit any model on four folds: the simplest, unvalidated
        chosen = min(cands, key=lambda c: c.rank).name
    excluded = None
    if force is not None:
        excluded = ("the other candidates: --model chose this one, so only it was fitted (and offsets+tool, the "
                    "model of the offsets to enter, whose held-out misfit scales their intervals)")
    elif not include_full:
        excluded = "full: left out by the caller"
    elif compliance_only:
        excluded = ("full: full identification is compared without compliance, and only the compliance models "
                    "were asked for (--compliance / fit.compliance)")
    return ModelChoice(scores, nominal, chosen, force is not None, n_folds, grouping, scale, excluded, starts,
                       entered_folds)
