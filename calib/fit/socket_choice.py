"""The data choose the model for socket data: candidate models of the arm scored by the error with
which they predict held-out socket placements (or configurations), the simplest within one
standard error of the best chosen — the socket counterpart of ``calib.fit.model_choice``.

Candidates (``socket_candidates``), simplest first, each fitted by ``calib.fit.socket.fit_socket``:

``offsets``              zero-offsets; the ball where the robot model declares it (not fitted);
``offsets+ball``         zero-offsets and the ball on the flange (the socket points are always free);
``offsets+ball+links``   … and every link parameter under a Gaussian prior whose two scales —
                         lengths (d, a; mm) and angles (α, β; degrees) — maximise the Laplace
                         evidence (``calib.fit.link_scale``): of each fold's training data
                         when it is scored, of all the data for the final fit;
``full``                 … the link parameters the data determine, without a prior (weakly
                         determined combinations left out);

each also ``+compliance`` (gravity sag) when the model has link masses.

Scoring (``choose_socket_model``). With two or more placements each placement is held out in turn
("placement"): the candidate is fitted on the others and predicts the held-out ball positions;
a held-out socket's place is not known to the fit, so it is estimated from those predictions (their
mean, 3 of the socket's ~20×3 coordinates) and every configuration scores its distance from it. A
compliance candidate predicts the held-out ball with the sag of its fold's fitted arm (torques and
lever arms at the fitted parameters, ``calib.fit.socket.ball_positions``), as it was fitted.
With a single placement the configurations of every socket are dealt into ``k`` folds
("configuration") and score their distance from the socket point the training fit found. A
candidate's error is the mean of the per-configuration distances (mm) with a standard error from
the per-socket means (configurations of one socket share its placement: they are not independent),
and their rms; the nominal model (data sheet, ball from the training data's pivot calibration)
is scored alike. The chosen model is the simplest whose mean is within one standard error of the
best (``calib.fit.model_choice.one_se_choice``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from calib.fit.link_scale import maximise_evidence
from calib.fit.model_choice import Candidate, ModelChoice, Score, fold_scale_text, one_se_choice
from calib.fit.socket import SocketDataError, SocketDataset, SocketFit, _pivot_start, ball_positions, fit_socket
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel

KINDS = ("offsets", "offsets+ball", "offsets+ball+links", "full")
#: The tracker candidates' names for the same models (``--model offsets+tool`` on socket data).
ALIASES = {"offsets+tool": "offsets+ball", "offsets+tool+links": "offsets+ball+links"}


@dataclass(frozen=True)
class SocketCandidate(Candidate):
    """A socket model to compare: ``kind`` of ``KINDS``, with joint ``compliance`` or not."""

    kinds: ClassVar[tuple[str, ...]] = KINDS


def socket_candidates(model: RobotModel, *, compliance_only: bool = False) -> list[SocketCandidate]:
    """Every candidate for ``model`` (``compliance_only``: only the compliance variants, ``--compliance``)."""
    out = [] if compliance_only else [SocketCandidate(k) for k in KINDS]
    if model.has_dynamics:
        out += [SocketCandidate(k, True) for k in KINDS]
    if not out:
        raise SocketDataError(f"{model.name}: the compliance model needs link masses and centres of mass in the robot model")
    return sorted(out, key=lambda c: c.rank)


def parse_socket_candidate(name: str, model: RobotModel) -> SocketCandidate:
    """``--model NAME`` as a socket candidate (the tracker names ``offsets+tool…`` too); ValueError
    naming the known ones."""
    for alias, real in ALIASES.items():
        if name == alias or name.startswith(alias + "+compliance"):
            name = real + name[len(alias):]
    known = {c.name: c for c in socket_candidates(model)}
    if name not in known:
        raise ValueError(f"model {name!r} unknown for socket data and {model.name}; known: {', '.join(known)}")
    return known[name]


def candidate_options(cand: SocketCandidate, link_scale: tuple[float, float] | None = None) -> dict:
    """``fit_socket``'s keyword arguments for ``cand`` (``link_scale``: (mm, deg), needed by
    ``offsets+ball+links``)."""
    if cand.kind == "offsets+ball+links":
        if link_scale is None:
            raise ValueError("the offsets+ball+links candidate needs a link scale")
        return {"tolerance": tuple(link_scale), "compliance": cand.compliance}
    if cand.kind == "full":
        return {"tolerance": None, "compliance": cand.compliance}
    return {"kinds": ("offset",), "tolerance": None, "compliance": cand.compliance, "fit_ball": cand.kind == "offsets+ball"}


def fit_candidate(model: RobotModel, ds: SocketDataset, cand: SocketCandidate,
                  link_scale: tuple[float, float] | None = None) -> SocketFit:
    """``cand`` fitted on ``ds`` (``candidate_options``)."""
    return fit_socket(model, ds, **candidate_options(cand, link_scale))


def socket_link_scale(model: RobotModel, ds: SocketDataset, compliance: bool = False) -> dict:
    """The (length mm, angle deg) link prior scales of maximum Laplace evidence on ``ds``
    (``calib.fit.link_scale.maximise_evidence``)."""
    return maximise_evidence(lambda mm, deg: fit_socket(model, ds, tolerance=(mm, deg), compliance=compliance).log_evidence)


# --- folds and held-out errors --------------------------------------------------------------------
def rows_subset(ds: SocketDataset, rows: np.ndarray) -> SocketDataset:
    """The configurations ``rows`` of ``ds``, every group and distance kept (same numbering)."""
    return SocketDataset(ds.q_rad[rows], ds.group[rows], list(ds.groups), list(ds.distances),
                         [ds.config_ids[i] for i in rows] if ds.config_ids else [], ds.source)


def socket_folds(ds: SocketDataset, k: int = 5, seed: int = 0) -> tuple[list[tuple[SocketDataset, SocketDataset]], str]:
    """[(train, test), …] and what is held out: each placement in turn with two or more placements,
    else every socket's configurations dealt (seeded shuffle) into ``k`` folds."""
    if len(ds.placements) >= 2:
        return [(ds.subset([p for p in ds.placements if p != held]), ds.subset([held])) for held in ds.placements], "placement"
    rng = np.random.default_rng(seed)
    fold = np.zeros(len(ds.q_rad), dtype=int)
    for g in range(len(ds.groups)):
        rows = np.flatnonzero(ds.group == g)
        fold[rng.permutation(rows)] = np.arange(rows.size) % k
    return [(rows_subset(ds, np.flatnonzero(fold != f)), rows_subset(ds, np.flatnonzero(fold == f)))
            for f in range(k)], "configuration"


def held_out_distances(chain: Chain, params: np.ndarray, compliance: np.ndarray | None, test: SocketDataset,
                       points: np.ndarray | None) -> np.ndarray:
    """(k_test,) mm: each held-out configuration's predicted ball centre from its socket's point —
    ``points`` (g, 3) of the training fit (configuration folds), or None: the mean of the held-out
    predictions of that socket (placement folds: the placement is estimated from them)."""
    pos = ball_positions(chain, test.q_rad, params, compliance)
    if points is None:
        points = np.array([pos[test.group == g].mean(axis=0) if np.any(test.group == g) else np.full(3, np.nan)
                           for g in range(len(test.groups))])
    return np.linalg.norm(pos - points[test.group], axis=1)


@dataclass
class SocketScore(Score):
    """A ``Score`` whose standard error comes from the per-socket means (``clusters``: (k,) the
    held-out socket of each error), the independent units of socket data."""

    clusters: np.ndarray | None = None

    @property
    def se_mm(self) -> float:
        e, c = self.errors_mm, self.clusters
        if self.failed or c is None or e.size < 2:
            return super().se_mm
        means = np.array([e[c == u].mean() for u in np.unique(c)])
        return float(means.std(ddof=1) / math.sqrt(means.size)) if means.size > 1 else math.inf


def _nominal_params(chain: Chain, train: SocketDataset) -> tuple[np.ndarray, np.ndarray]:
    """The data-sheet arm with the ball (and socket points) of the training data's pivot calibration."""
    p = chain.nominal.copy()
    ms = chain.marker_slice()
    ball, points = _pivot_start(chain, train, chain.nominal)
    p[ms.start:ms.start + 3] = ball
    return p, points


def cross_validate_sockets(model: RobotModel, ds: SocketDataset, cands: list[SocketCandidate],
                           scales: dict[bool, tuple[float, float] | None], *, k: int = 5,
                           seed: int = 0, fold_scales: dict[bool, list] | None = None,
                           ) -> tuple[list[SocketScore], SocketScore, int, str]:
    """Held-out scores of ``cands`` and of the nominal model (module docstring); ``scales``: the
    link scale per compliance flag, given by the user. ``fold_scales`` (a dict, when given): the
    links candidates' scales are instead estimated by evidence on each fold's training data only
    (the held-out data must not choose the prior they are scored under), and each fold's
    (mm, deg) is appended under its compliance flag."""
    chain = Chain(model)
    folds, grouping = socket_folds(ds, k, seed)
    scores = [SocketScore(c.name, c.rank, None) for c in cands]
    parts: list[list[np.ndarray]] = [[] for _ in cands]
    labels: list[np.ndarray] = []
    nominal_parts = []
    for f, (train, test) in enumerate(folds):
        by_point = grouping == "configuration"
        label = np.array([f"{test.groups[g][0]}/{test.groups[g][1]}" for g in test.group])
        labels.append(label)
        p0, pts0 = _nominal_params(chain, train)
        nominal_parts.append(held_out_distances(chain, p0, None, test, pts0 if by_point else None))
        fold_scale = dict(scales)
        for i, c in enumerate(cands):
            if scores[i].failed:
                continue
            try:
                if fold_scales is not None and c.kind == "offsets+ball+links" and c.compliance not in fold_scale:
                    sc = socket_link_scale(model, train, c.compliance)
                    fold_scale[c.compliance] = (sc["length_mm"], sc["angle_deg"])
                    fold_scales.setdefault(c.compliance, []).append(fold_scale[c.compliance])
                fit = fit_candidate(model, train, c, fold_scale.get(c.compliance))
            except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
                scores[i].failed = f"fold {f + 1}: {exc}"
                continue
            dist = held_out_distances(chain, fit.params, fit.compliance, test, fit.points if by_point else None)
            if not np.all(np.isfinite(dist)) or any("did not converge" in w for w in fit.warnings):
                scores[i].failed = f"fold {f + 1}: the fit did not converge"
                continue
            n_free = len(fit.free_names)
            scores[i].n_params = n_free if scores[i].n_params is None else max(scores[i].n_params, n_free)
            parts[i].append(dist)
    clusters = np.concatenate(labels)
    for s, pp in zip(scores, parts):
        if len(pp) == len(folds) and not s.failed:
            s.errors_mm, s.clusters = np.concatenate(pp), clusters
    nominal = SocketScore("nominal (data sheet, ball from the training data)", -1.0, 0, np.concatenate(nominal_parts),
                          clusters=clusters)
    return scores, nominal, len(folds), grouping


@dataclass
class SocketChoice(ModelChoice):
    """``ModelChoice`` for socket data: ``link_scale`` maps each links candidate's name to its
    empirical Bayes scales (``socket_link_scale``)."""

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["rule"] += "; socket data: held-out configurations scored by their distance from their socket"
        d["standard_error"] = "from the per-socket means of the held-out distances"
        return d

    def format(self) -> str:
        held = ("placement (fit on the other placements; a held-out socket's place is the mean of its predicted "
                "ball positions)" if self.grouping == "placement" else
                "configuration (fit on the other configurations, scored against the socket points that fit found)")
        lines = [f"model choice: {self.folds}-fold cross-validation by {held}",
                 f"  {'model':<50}{'free':>6}{'held-out rms (mm)':>19}{'mean ± se (mm)':>20}"]
        if all(s.failed or not s.errors_mm.size for s in self.scores):
            lines.append(f"  no model could be fitted on every training fold: the simplest ({self.chosen}) is fitted "
                         "unvalidated, and nothing is marked \"enter\"")
        for s in [self.nominal] + self.scores:
            free = "—" if s.n_params is None else s.n_params
            if s.failed:
                lines.append(f"  {s.name:<50}{free:>6}  failed: {s.failed}")
                continue
            mark = "  ← chosen" + (" (--model)" if self.forced else "") if s.name == self.chosen else ""
            lines.append(f"  {s.name:<50}{free:>6}{s.rms_mm:>19.4f}{s.mean_mm:>12.4f} ± {s.se_mm:.4f}{mark}")
        for name, sc in (self.link_scale or {}).items():
            how = "given" if sc.get("given") else "empirical Bayes, max evidence"
            lines.append(f"  link prior of {name} ({how}): lengths ±{sc['length_mm']:g} mm, angles ±{sc['angle_deg']:g}°"
                         + fold_scale_text(sc))
        return "\n".join(lines)


def choose_socket_model(model: RobotModel, ds: SocketDataset, *, force: str | None = None, k: int = 5, seed: int = 0,
                        link_tolerance: tuple[float, float] | None = None,
                        compliance_only: bool = False) -> SocketChoice:
    """Score every candidate on ``ds`` and choose (``force``: ``--model NAME``, that candidate only,
    still scored against the nominal model); ``link_tolerance``: that (mm, deg) link prior instead of
    the empirical Bayes one."""
    cands = socket_candidates(model, compliance_only=compliance_only)
    if force is not None:
        cands = [parse_socket_candidate(force, model)]
        force = cands[0].name
    scales: dict[bool, tuple[float, float] | None] = {}
    shown: dict[str, dict] = {}
    for c in cands:
        if c.kind != "offsets+ball+links":
            continue
        if link_tolerance is not None:
            sc = {"length_mm": link_tolerance[0], "angle_deg": link_tolerance[1], "given": True}
        else:
            sc = socket_link_scale(model, ds, c.compliance)
        scales[c.compliance] = (sc["length_mm"], sc["angle_deg"])
        shown[c.name] = sc
    per_fold: dict[bool, list] | None = None if link_tolerance is not None else {}
    scores, nominal, n_folds, grouping = cross_validate_sockets(model, ds, cands, scales if per_fold is None else {},
                                                                k=k, seed=seed, fold_scales=per_fold)
    for c in cands:
        if per_fold and c.name in shown:
            shown[c.name]["per_fold"] = [list(t) for t in per_fold.get(c.compliance, [])]
    try:
        chosen = force if force is not None else one_se_choice(scores)
    except ValueError:  # nothing could be fitted on the training folds: the simplest, unvalidated
        chosen = min(cands, key=lambda c: c.rank).name
    return SocketChoice(scores, nominal, chosen, force is not None, n_folds, grouping, shown)


def chosen_options(model: RobotModel, choice: SocketChoice) -> dict:
    """``fit_socket``'s keyword arguments for the chosen candidate, with its link scale."""
    cand = parse_socket_candidate(choice.chosen, model)
    sc = (choice.link_scale or {}).get(cand.name)
    return candidate_options(cand, None if sc is None else (sc["length_mm"], sc["angle_deg"]))
