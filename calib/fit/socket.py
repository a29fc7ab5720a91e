"""Sensorless socket calibration: a ball on the flange placed into fixed sockets.

A tool with spherical sockets a known distance apart (e.g. two sockets 50 mm apart) stands in
the cell; the robot puts a ball on its flange into a socket in many configurations. Within one
*placement* of the tool and one socket, every configuration puts the ball centre at the same
point; the sockets of one placement are a known distance apart. No external sensor.

Unknowns (all in the robot base frame, mm / rad):
- the kinematic parameters of ``calib.robot.kinematics.Chain`` that such data determine,
- the ball centre ``b`` in the flange frame (the chain's first marker slot),
- one point ``c_g`` per (placement, socket) group.

Residuals: ``FK(q_k) · b − c_g`` for every configuration (σ_point, the ball's play in the
socket), ``|c_a − c_b| − distance`` for every known distance (σ_distance, the caliper's), and a
Gaussian prior on the link parameters around the data sheet (``tolerance``), none on the
zero-offsets. The posterior is approximated at its mode (Laplace: the mode and the inverse of
the Gauss–Newton information), with σ_point estimated from the residuals — the fast Bayesian
fit of this data; it is exact for the linearised model, which the study in the tests checks by
interval coverage on simulated cells.

What the data cannot determine is found from the Jacobian, not assumed, and reported instead of
sampled into a made-up σ: the base frame (socket points are free), the first axis's offset (a
rotation of every point about the base z axis), every parameter of the last link that only
moves the ball within the flange frame (it is the ball's position instead: the tool is
preferred, so the corrected model holds for any other tool on the flange), and the global scale
when no distance is known.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.io import csvdialect
from calib.robot.kinematics import KINDS, Chain
from calib.robot.model import RobotModel

#: Relative residual below which a Jacobian column counts as a combination of the kept ones.
RANK_TOL = 1e-6
#: Without a prior, columns reproduced to this relative residual are left out as weakly determined.
WEAK_TOL = 3e-3
#: Condition number (columns scaled to mm of ball motion) above which a fit is called weak.
COND_WEAK = 1e4
#: Default prior on the link parameters: mm for d and a, degrees for α and β (as the fast fit's).
DEFAULT_TOLERANCE = (0.2, 0.02)


class SocketDataError(ValueError):
    """A socket dataset that cannot be read or fitted (text says where and why)."""


@dataclass
class SocketDataset:
    """Configurations (k, n) rad in the controller's convention; ``group`` (k,) int indexes
    ``groups`` [(placement, socket), …]; ``distances`` [(group_a, group_b, mm), …]."""

    q_rad: np.ndarray
    group: np.ndarray
    groups: list[tuple[str, str]]
    distances: list[tuple[int, int, float]]
    config_ids: list[str] = field(default_factory=list)
    source: str = ""

    @property
    def placements(self) -> list[str]:
        return sorted({p for p, _ in self.groups})

    def subset(self, placements: list[str]) -> "SocketDataset":
        """The rows of the given placements, groups and distances renumbered."""
        keep_groups = [i for i, (p, _) in enumerate(self.groups) if p in placements]
        remap = {old: new for new, old in enumerate(keep_groups)}
        rows = np.flatnonzero(np.isin(self.group, keep_groups))
        return SocketDataset(
            q_rad=self.q_rad[rows], group=np.array([remap[g] for g in self.group[rows]], dtype=int),
            groups=[self.groups[i] for i in keep_groups],
            distances=[(remap[a], remap[b], d) for a, b, d in self.distances if a in remap and b in remap],
            config_ids=[self.config_ids[i] for i in rows] if self.config_ids else [],
            source=self.source,
        )


def with_distance(groups: list[tuple[str, str]], distance_mm: float | None) -> list[tuple[int, int, float]]:
    """Distances between every pair of sockets within each placement (all equal to
    ``distance_mm``; the common two-socket tool); [] for None."""
    if distance_mm is None:
        return []
    if not 0 < distance_mm < 5000:
        raise SocketDataError(f"socket distance must be in mm, 0–5000; given {distance_mm}")
    out = []
    for i, (p, _) in enumerate(groups):
        for j in range(i + 1, len(groups)):
            if groups[j][0] == p:
                out.append((i, j, float(distance_mm)))
    return out


def read_socket_csv(path: str | Path, n_joints: int, *, distance_mm: float | None = None) -> SocketDataset:
    """Read ``config,q1..qN,placement,socket`` (degrees; ``#`` comments). A comment line
    ``# socket_distance_mm: 50`` gives the distance between the sockets of each placement unless
    ``distance_mm`` is given."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SocketDataError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    lines = csvdialect.decode(raw, str(path), SocketDataError).splitlines()
    meta_distance = None
    body = []
    for lineno, line in enumerate(lines, 1):
        m = re.match(r"\s*#\s*socket_distance_mm\s*[:=]\s*([-+0-9.,eE]+)\s*$", line)
        if m:
            try:  # a spreadsheet in a decimal-comma locale writes 50,02
                meta_distance = csvdialect.number(m.group(1), "," if "," in m.group(1) and "." not in m.group(1) else ".")
            except ValueError:
                raise SocketDataError(f"{path}:{lineno}: socket_distance_mm must be a number in mm "
                                      f"(given {m.group(1)!r})") from None
        elif line.strip() and not line.lstrip().startswith("#"):
            body.append((lineno, line))
    if not body:
        raise SocketDataError(f"{path}: no header and no rows")
    sep = csvdialect.sniff_separator(body[0][1], str(path), body[0][0], SocketDataError)
    header = csvdialect.split(body[0][1], sep)
    want = ["config"] + [f"q{i + 1}" for i in range(n_joints)] + ["placement", "socket"]
    if header != want:
        raise SocketDataError(f"{path}:{body[0][0]}: header must be {','.join(want)} (or with ';' or tabs); "
                              f"given {sep.join(header)}")
    rows = [(lineno, csvdialect.split(line, sep)) for lineno, line in body[1:]]
    dialect = csvdialect.Dialect(sep, csvdialect.sniff_decimal(rows, range(1, 1 + n_joints), str(path),
                                                               SocketDataError))
    q, keys, ids = [], [], []
    for lineno, cells in rows:
        if len(cells) != len(want):
            raise SocketDataError(csvdialect.width_error(str(path), lineno, cells, len(want), dialect))
        try:
            row = [csvdialect.number(c, dialect.decimal) for c in cells[1:1 + n_joints]]
        except ValueError as exc:
            raise SocketDataError(f"{path}:{lineno}: joint angles must be numbers in degrees (given {exc}; "
                                  f"this file is {dialect.describe()})") from exc
        if not all(math.isfinite(v) for v in row):
            raise SocketDataError(f"{path}:{lineno}: joint angles must be finite")
        q.append(row)
        keys.append((cells[-2], cells[-1]))
        ids.append(cells[0])
    q_deg = np.array(q)
    if np.all(np.abs(q_deg) <= math.pi + 1e-9) and len(q_deg) > 5:
        raise SocketDataError(f"{path}: every joint angle is within ±π: these look like radians; the file needs degrees")
    groups = sorted(set(keys))
    gidx = np.array([groups.index(k) for k in keys], dtype=int)
    d = distance_mm if distance_mm is not None else meta_distance
    return SocketDataset(np.radians(q_deg), gidx, groups, with_distance(groups, d), ids, str(path))


def read_hole_folder(folder: str | Path, *, distance_mm: float | None = 50.0) -> SocketDataset:
    """Read a folder of ``<placement>_hole_<k>.csv`` files, each row the joint angles in
    **radians** without a header (the layout of the public platonics-delft socket data)."""
    folder = Path(folder)
    files = sorted(folder.glob("*_hole_*.csv"))
    if not files:
        raise SocketDataError(f"{folder}: no <placement>_hole_<k>.csv files")
    q, keys = [], []
    for f in files:
        placement, socket = f.stem.rsplit("_hole_", 1)
        rows = np.atleast_2d(np.loadtxt(f, delimiter=","))
        q.append(rows)
        keys += [(placement, socket)] * len(rows)
    groups = sorted(set(keys))
    gidx = np.array([groups.index(k) for k in keys], dtype=int)
    qa = np.concatenate(q)
    ids = [f"{p}/{s}/{i}" for i, (p, s) in enumerate(keys)]
    return SocketDataset(qa, gidx, groups, with_distance(groups, distance_mm), ids, str(folder))


# ------------------------------------------------------------------------------------ fit
@dataclass
class SocketFit:
    """Result of ``fit_socket``. params: full Chain vector (P,) with the ball in marker slot 0;
    std (P,) NaN where not identified; points (g, 3) mm and their std; sigma_point_mm the
    fitted play; excluded: parameter → why the data cannot determine it; weak: combinations
    with little information (text)."""

    params: np.ndarray
    std: np.ndarray
    points: np.ndarray
    points_std: np.ndarray
    free_names: list[str]
    excluded: dict[str, str]
    weak: list[str]
    sigma_point_mm: float
    condition_number: float
    rms_mm: float
    iterations: int
    groups: list[tuple[str, str]]
    warnings: list[str] = field(default_factory=list)
    #: (n,) rad/(N·m) with the compliance model, 0 where not fitted; the sag it gives takes its torques
    #: at ``params`` (the fitted arm), as ``ball_positions`` does.
    compliance: np.ndarray | None = None
    compliance_std: np.ndarray | None = None  # (n,) NaN where not fitted
    #: The link prior the fit ran with, (mm, deg) sd of d, a / α, β; None: no prior.
    tolerance: tuple[float, float] | None = None
    #: The parameter kinds the fit was allowed to fit (``fit_socket``'s ``kinds``).
    kinds: tuple[str, ...] = ("offset", "d", "a", "alpha", "beta")
    #: Whether the ball was fitted (False: the robot model's declared ball, ``fit_socket``'s ``fit_ball``).
    fit_ball: bool = True
    #: Laplace approximation of log p(data | model, priors) at the mode, σ_point at its estimate, up
    #: to a constant shared by fits with the same free parameters (``calib.fit.link_scale``).
    log_evidence: float = math.nan

    def model_description(self, prior: str = "a fixed prior") -> str:
        """Which model of the arm this fit is, in one line (for the summary, result.json, report);
        ``prior`` names the link prior (e.g. "an empirical-Bayes prior")."""
        kinds = [k for k in self.kinds if k != "offset"]
        fitted = {n.rsplit(".", 1)[1] for n in self.free_names}
        ball = "the ball" if self.fit_ball else "the model's declared ball (not fitted)"
        if not kinds:
            text = f"joint zero-offsets and {ball} (link parameters at the data sheet's values)"
        elif self.tolerance is None:
            text = (f"joint zero-offsets, {ball} and every link parameter the data determine "
                    f"({', '.join(k for k in kinds if k in fitted) or 'none'}), without a prior")
        else:
            mm, deg = self.tolerance
            text = (f"joint zero-offsets, {ball} and the link parameters ({', '.join(k for k in kinds if k in fitted) or 'none'}) "
                    f"under {prior} of ±{mm:g} mm / ±{deg:g}° (sd) about the data sheet")
        if self.compliance is not None:
            text += ", with joint compliance (gravity sag)"
        return text

    def ball(self, chain: Chain) -> tuple[np.ndarray, np.ndarray]:
        s = chain.marker_slice()
        return self.params[s][:3], self.std[s][:3]


def _sag_gain(chain: Chain, q: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
    """sign_i τ_i(q) · 1e-6, (k, n): joint-angle change (rad) per µrad/(N·m) of compliance, the
    gravity torques τ (N·m) taken at the arm ``params`` (P,) (None: the nominal arm — only for
    scaling columns and deciding which axes gravity loads; the fit and its predictions pass the
    arm they evaluate)."""
    from calib.robot.gravity import gravity_torques

    return chain.sign * gravity_torques(chain, q, params) * 1e-6


class _SocketProblem:
    """Whitened residuals r(x) and Jacobian for x = [free extended params | group points].

    The extended vector is the chain's (P,) followed, with compliance, by one compliance per
    joint in µrad/(N·m) (first-order sag through the offsets' Jacobian, as in ``calib.fit.posterior``).
    The sag's torques and lever arms are both taken at the arm being evaluated (at the solution,
    the fitted arm: its offsets, links and ball), not the data sheet's — offsets of a degree or
    links of a millimetre move the torques by as much as the sag's size can show. The torques'
    own change with the parameters (k·∂τ/∂p, ~1e-4 of the columns it would join) is left out of
    the Jacobian.
    """

    def __init__(self, chain: Chain, ds: SocketDataset, free: np.ndarray, nominal: np.ndarray,
                 prior_sd: np.ndarray, sigma_point: float, sigma_distance: float) -> None:
        self.chain, self.ds, self.free = chain, ds, free
        self.nominal = nominal  # (P,) or (P + n,) with compliance
        self.prior_sd = prior_sd  # (len(free),) inf where no prior
        self.sp, self.sd = sigma_point, sigma_distance
        self.g = len(ds.groups)
        self.compliance = nominal.size > chain.n_params

    def full(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self.nominal.copy()
        p[self.free] = x[: len(self.free)]
        return p, x[len(self.free):].reshape(self.g, 3)

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ext, pts = self.full(x)
        nf, k = len(self.free), len(self.ds.q_rad)
        pos, jac = self.chain.marker_jacobian(self.ds.q_rad, ext[: self.chain.n_params])
        pos, jac = pos[:, 0], jac[:, 0]
        if self.compliance:
            gain = _sag_gain(self.chain, self.ds.q_rad, ext[: self.chain.n_params])
            sag = jac[..., : self.chain.n] * gain[:, None, :]  # (k, 3, n) per µrad/(N·m)
            pos = pos + np.einsum("kjn,n->kj", sag, ext[self.chain.n_params:])
            jac = np.concatenate([jac, sag], axis=-1)
        jac = jac[..., self.free]  # (k,3,nf)
        r_pt = (pos - pts[self.ds.group]) / self.sp
        j_pt = np.zeros((k, 3, nf + 3 * self.g))
        j_pt[..., :nf] = jac / self.sp
        for ax in range(3):
            j_pt[np.arange(k), ax, nf + 3 * self.ds.group + ax] = -1.0 / self.sp
        rows_r, rows_j = [r_pt.ravel()], [j_pt.reshape(3 * k, -1)]
        for a, b, dist in self.ds.distances:
            v = pts[a] - pts[b]
            n = float(np.linalg.norm(v))
            rows_r.append(np.array([(n - dist) / self.sd]))
            jd = np.zeros((1, nf + 3 * self.g))
            u = v / max(n, 1e-12)
            jd[0, nf + 3 * a: nf + 3 * a + 3] = u / self.sd
            jd[0, nf + 3 * b: nf + 3 * b + 3] = -u / self.sd
            rows_j.append(jd)
        has = np.isfinite(self.prior_sd)
        if np.any(has):
            idx = np.flatnonzero(has)
            rows_r.append((x[idx] - self.nominal[self.free[idx]]) / self.prior_sd[idx])
            jp = np.zeros((len(idx), nf + 3 * self.g))
            jp[np.arange(len(idx)), idx] = 1.0 / self.prior_sd[idx]
            rows_j.append(jp)
        return np.concatenate(rows_r), np.concatenate(rows_j)


def _pivot_start(chain: Chain, ds: SocketDataset, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ball in the flange frame and group points from the nominal model, by linear least
    squares (pivot calibration): R_k b − c_g = −p_k."""
    rot, pos = chain.flange_pose(ds.q_rad, params)
    k, g = len(ds.q_rad), len(ds.groups)
    a = np.zeros((3 * k, 3 + 3 * g))
    a[:, :3] = rot.reshape(3 * k, 3)
    for ax in range(3):
        a[np.arange(k) * 3 + ax, 3 + 3 * ds.group + ax] = -1.0
    sol, *_ = np.linalg.lstsq(a, -pos.reshape(-1), rcond=None)
    return sol[:3], sol[3:].reshape(g, 3)


def _select(jac: np.ndarray, names: list[str], order: list[int], n_fixed_first: int,
            rank_tol: float = RANK_TOL) -> tuple[list[int], dict[int, str]]:
    """Greedy column selection in ``order``: a column the kept ones reproduce (relative
    residual < ``rank_tol``) is dropped, with the kept columns it duplicates named. The first
    ``n_fixed_first`` entries of ``order`` are always kept (the group points)."""
    kept: list[int] = []
    dropped: dict[int, str] = {}
    basis = np.zeros((jac.shape[0], 0))
    ortho = np.zeros((jac.shape[0], 0))  # orthonormal basis of the kept columns (Gram–Schmidt, twice)
    for pos, c in enumerate(order):
        col = jac[:, c]
        norm = np.linalg.norm(col)
        if norm == 0:
            dropped[c] = "moves no ball position in this data"
            continue
        resid = col - ortho @ (ortho.T @ col)
        resid = resid - ortho @ (ortho.T @ resid)
        rel = float(np.linalg.norm(resid) / norm)
        if rel < rank_tol and pos >= n_fixed_first:
            coef, *_ = np.linalg.lstsq(basis, col, rcond=None)
            big = np.argsort(-np.abs(coef))[:3]
            partners = [names[kept[i]] for i in big if abs(coef[i]) > 1e-3 * np.abs(coef).max()]
            how = "indistinguishable from" if rel < RANK_TOL else f"nearly a combination (residual {rel:.1e}) of"
            dropped[c] = f"{how} {', '.join(partners)} in this data"
            continue
        kept.append(c)
        basis = np.column_stack([basis, col])
        if rel > 0:
            ortho = np.column_stack([ortho, resid / np.linalg.norm(resid)])
    return kept, dropped


def fit_socket(model: RobotModel, ds: SocketDataset, *, tolerance: tuple[float, float] | None = DEFAULT_TOLERANCE,
               kinds: tuple[str, ...] = ("offset", "d", "a", "alpha", "beta"), sigma_point_mm: float = 0.1,
               sigma_distance_mm: float = 0.1, max_nfev: int = 200, weak_tol: float | None = None,
               compliance: bool = False, fit_ball: bool = True) -> SocketFit:
    """Fit the identifiable kinematic parameters, the ball and the socket points.

    tolerance: (mm, deg) prior sd of d, a and α, β around the data sheet; None for no prior
    (then only what the data determine sharply should be asked for, e.g. ``kinds=("offset",)``).
    kinds: which parameter kinds may be fitted (``offset`` only: zero-offsets and the ball).
    weak_tol: also leave out columns the kept ones reproduce to this relative residual (weakly
    determined); default: ``WEAK_TOL`` without a prior (nothing else bounds them), none with one.
    compliance: also fit one joint compliance per axis (gravity sag; the model needs link
    masses); axes that carry a few % of the largest gravity torque are left out.
    fit_ball: False keeps the ball where the robot model declares it (its tool's first marker)
    instead of fitting it: the simplest candidate of ``calib.fit.socket_choice``.
    """
    chain = Chain(model)
    n, k = chain.n, len(ds.q_rad)
    if k < 6 or len(ds.groups) < 1:
        raise SocketDataError(f"{ds.source}: {k} configurations in {len(ds.groups)} groups; a socket fit needs more")
    small = [f"{p}/{s}" for i, (p, s) in enumerate(ds.groups) if np.sum(ds.group == i) < 4]
    if small:
        raise SocketDataError(f"{ds.source}: groups with fewer than 4 configurations: {', '.join(small)}")
    bad = [x for x in kinds if x not in KINDS]
    if bad:
        raise ValueError(f"unknown parameter kinds {bad}; allowed: {KINDS}")
    nominal = chain.nominal.copy()
    ms = chain.marker_slice()
    if fit_ball:
        ball0, pts0 = _pivot_start(chain, ds, nominal)
        nominal[ms.start:ms.start + 3] = ball0
    else:  # each socket's point starts at the mean of the declared ball's positions
        pos0 = chain.marker_positions(ds.q_rad, nominal)[:, 0]
        pts0 = np.array([pos0[ds.group == g].mean(axis=0) for g in range(len(ds.groups))])
    names = list(chain.param_names)
    cand = list(range(ms.start, ms.start + 3)) if fit_ball else []
    for kind in ("offset", "a", "d", "alpha", "beta"):
        if kind not in kinds or (kind == "beta" and model.convention == "dh"):
            continue
        cand += list(chain.index(kind))
    lever = float(np.median(np.linalg.norm(chain.flange_pose(ds.q_rad, nominal)[1], axis=1))) or 1000.0
    scale_of = {c: lever if names[c].rsplit(".", 1)[1] in ("offset", "alpha", "beta") else 1.0 for c in cand}
    excluded_first: dict[str, str] = {}
    if compliance:
        if not model.has_dynamics:
            raise SocketDataError(f"{model.name}: the compliance model needs link masses and centres of mass in the robot model")
        rms = np.sqrt(np.mean((_sag_gain(chain, ds.q_rad) * 1e6) ** 2, axis=0))
        names += [f"{ax}.compliance" for ax in model.axis_names]
        nominal = np.concatenate([nominal, np.zeros(n)])
        for i in range(n):
            if rms[i] < 0.05 * rms.max():
                excluded_first[names[chain.n_params + i]] = (
                    f"gravity turns this axis by only {rms[i] if rms[i] > 1e-9 * rms.max() else 0.0:.1g} N·m (rms) "
                    "in this data: its sag cannot be seen")
            else:
                cand.append(chain.n_params + i)
                scale_of[chain.n_params + i] = lever * 1e-6 * rms[i]

    # Identifiability from the Jacobian at the start, columns scaled to mm of ball motion.
    scale = np.array([scale_of[c] for c in cand])
    probe = _SocketProblem(chain, ds, np.array(cand), nominal, np.full(len(cand), np.inf), 1.0, sigma_distance_mm)
    _, j0 = probe(np.concatenate([nominal[cand], pts0.ravel()]))
    nc = len(cand)
    jcols = np.column_stack([j0[:, nc:], j0[:, :nc] * scale])
    all_names = [f"point.{p}/{s}.{ax}" for p, s in ds.groups for ax in "xyz"] + [names[c] for c in cand]
    order = list(range(3 * len(ds.groups))) + [3 * len(ds.groups) + i for i in range(nc)]
    kept, dropped = _select(jcols, all_names, order, 3 * len(ds.groups))
    # Judge again on consistent data: every ball position of a group at the group's point.
    # Measured scatter would otherwise lend a null direction that holds only there (A1's
    # rotation, which the free points absorb exactly) a sliver of fake information.
    pos = chain.marker_positions(ds.q_rad, nominal[: chain.n_params])[:, 0]
    jw = chain.flange_jacobian(ds.q_rad, nominal[: chain.n_params]).jw
    if compliance:
        jw = np.concatenate([jw, jw[..., :n] * _sag_gain(chain, ds.q_rad)[:, None, :]], axis=-1)
    jw = jw[..., cand]  # (k, 3, nc)
    scatter = (pos - pts0[ds.group])[:, :, None]
    consistent = jcols.copy()
    consistent[: 3 * k, 3 * len(ds.groups):] -= (np.cross(jw, scatter, axis=1) * scale).reshape(3 * k, nc)
    if weak_tol is None:
        weak_tol = WEAK_TOL if tolerance is None else RANK_TOL
    kept, more = _select(consistent, all_names, kept, 3 * len(ds.groups), max(weak_tol, RANK_TOL))
    dropped.update(more)
    free = np.array([cand[i - 3 * len(ds.groups)] for i in kept if i >= 3 * len(ds.groups)], dtype=int)
    excluded = {**excluded_first, **{all_names[i]: why for i, why in dropped.items()}}
    if not ds.distances:
        excluded["scale"] = "no distance between sockets is known: the data fix the arm only up to a scale"
    sv = np.linalg.svd(jcols[:, kept], compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf

    prior = np.full(len(free), np.inf)
    if tolerance is not None:
        mm, deg = tolerance
        for i, c in enumerate(free):
            kind = names[c].rsplit(".", 1)[1]
            if kind in ("d", "a"):
                prior[i] = mm
            elif kind in ("alpha", "beta"):
                prior[i] = math.radians(deg)
    from scipy.optimize import least_squares  # here, not at import: `acquire fit` loads this module for every file

    x = np.concatenate([nominal[free], pts0.ravel()])
    sigma, res, nfev = sigma_point_mm, None, 0
    for _ in range(2):  # fit, estimate the play from the residuals, refit with it
        prob = _SocketProblem(chain, ds, free, nominal, prior, sigma, sigma_distance_mm)
        res = least_squares(lambda v: prob(v)[0], x, jac=lambda v: prob(v)[1], method="lm", max_nfev=max_nfev * len(x))
        x, nfev = res.x, nfev + res.nfev
        p, pts = prob.full(x)
        dev = ball_positions(chain, ds.q_rad, p[: chain.n_params], p[chain.n_params:] * 1e-6 if compliance else None) \
            - pts[ds.group]
        dof = max(3 * k - 3 * len(ds.groups) - np.sum(~np.isfinite(prior)) - (3 if fit_ball else 0), 1)
        sigma = float(math.sqrt(np.sum(dev ** 2) / dof))
    prob = _SocketProblem(chain, ds, free, nominal, prior, sigma, sigma_distance_mm)
    r, j = prob(x)
    info = j.T @ j
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(info)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    evidence = _log_evidence(r, info, k, sigma, prior)
    std = np.full(nominal.size, np.nan)
    std[free] = sd[: len(free)]
    p, pts = prob.full(x)
    comp = comp_std = None
    if compliance:  # back to rad/(N·m); NaN std where not fitted
        comp, comp_std = p[chain.n_params:] * 1e-6, std[chain.n_params:] * 1e-6
        p, std = p[: chain.n_params], std[: chain.n_params]
    weak = []
    if cond > COND_WEAK:
        weak.append(f"scaled condition number {cond:.3g} (> {COND_WEAK:g}): some combinations are weakly determined")
    warnings = []
    if not res.success:
        warnings.append(f"the solver did not converge ({res.message})")
    if sigma > 1.0:
        warnings.append(f"the ball's positions scatter by {sigma:.2f} mm within a socket: far more than a ball's play; "
                        "check the data (wrong placement/socket labels, a loose ball)")
    return SocketFit(params=p, std=std, points=pts, points_std=sd[len(free):].reshape(-1, 3), free_names=[names[c] for c in free],
                     excluded=excluded, weak=weak, sigma_point_mm=sigma, condition_number=cond,
                     rms_mm=float(np.sqrt(np.mean(np.sum(dev ** 2, axis=1)))), iterations=int(nfev),
                     groups=list(ds.groups), warnings=warnings, compliance=comp, compliance_std=comp_std,
                     tolerance=None if tolerance is None else tuple(tolerance), kinds=tuple(kinds), fit_ball=fit_ball,
                     log_evidence=evidence)


def _log_evidence(r: np.ndarray, info: np.ndarray, k: int, sigma: float, prior_sd: np.ndarray) -> float:
    """Laplace log evidence from the whitened residuals ``r`` (3k point rows, the distance rows, then
    one row per finite entry of ``prior_sd``, in the parameter's own unit: mm or rad) and the
    information ``info`` = JᵀJ at the mode: log-likelihood (σ = ``sigma`` per axis) + log prior −
    ½ log det(info); terms that are the same for every prior scale are left out."""
    sign, logdet = np.linalg.slogdet(info)
    if sign <= 0:
        return -math.inf
    finite = prior_sd[np.isfinite(prior_sd)]
    return float(-0.5 * np.sum(r ** 2) - 3 * k * math.log(sigma) - np.sum(np.log(finite)) - 0.5 * logdet)


# -------------------------------------------------------------------------------- metrics
@dataclass(frozen=True)
class PlacementScore:
    """Spread (RMS distance of the predicted ball centre from its socket's mean, mm) and the
    socket-distance error (| |m_a − m_b| − distance |, mm; NaN without a distance)."""

    placement: str
    spread_mm: float
    distance_error_mm: float


def ball_positions(chain: Chain, q: np.ndarray, params: np.ndarray, compliance: np.ndarray | None = None) -> np.ndarray:
    """Ball centre (k, 3) mm in the base frame for q (k, n): marker slot 0 of ``params``, with
    the first-order gravity sag of ``compliance`` (n,) rad/(N·m) when given — its torques and
    lever arms at the arm ``params`` (as the fit takes them), so held-out predictions and
    cross-validation folds carry the sag of the fitted arm."""
    pos, jac = chain.marker_jacobian(q, params)
    pos = pos[:, 0]
    if compliance is not None:
        gain = _sag_gain(chain, q, params) * 1e6 * compliance  # rad per joint
        pos = pos + np.einsum("kjn,kn->kj", jac[:, 0, :, : chain.n], gain)
    return pos


def socket_scores(chain: Chain, params: np.ndarray, ds: SocketDataset,
                  compliance: np.ndarray | None = None) -> list[PlacementScore]:
    """Scores of ``params`` (ball in marker slot 0; with ``compliance`` its sag) on every
    placement of ``ds``; nothing is fitted."""
    pos = ball_positions(chain, ds.q_rad, params, compliance)
    means = np.array([pos[ds.group == g].mean(axis=0) for g in range(len(ds.groups))])
    out = []
    for placement in ds.placements:
        gs = [g for g, (p, _) in enumerate(ds.groups) if p == placement]
        d2 = np.concatenate([np.sum((pos[ds.group == g] - means[g]) ** 2, axis=1) for g in gs])
        errs = [abs(np.linalg.norm(means[a] - means[b]) - dist) for a, b, dist in ds.distances if a in gs and b in gs]
        out.append(PlacementScore(placement, float(np.sqrt(d2.mean())), float(np.mean(errs)) if errs else math.nan))
    return out


def placement_distances(chain: Chain, params: np.ndarray, ds: SocketDataset,
                        compliance: np.ndarray | None = None) -> np.ndarray:
    """(k,) mm: each configuration's predicted ball centre from the mean of its socket's predictions
    (the terms of ``socket_scores``' spread: their rms over a placement is its spread)."""
    pos = ball_positions(chain, ds.q_rad, params, compliance)
    means = np.array([pos[ds.group == g].mean(axis=0) for g in range(len(ds.groups))])
    return np.linalg.norm(pos - means[ds.group], axis=1)


@dataclass(frozen=True)
class HeldOutPlacement:
    """One placement held out (``held_out_placements``): its scores before (data sheet, ball from the
    training data's pivot calibration) and after (the fit on the other placements), and per held-out
    configuration (``config_ids``, ``sockets``) its distance from its socket's mean prediction, mm."""

    before: PlacementScore
    after: PlacementScore
    config_ids: list[str]
    sockets: list[str]
    before_mm: np.ndarray
    after_mm: np.ndarray


def held_out_placements(model: RobotModel, ds: SocketDataset, **fit_options) -> list[HeldOutPlacement]:
    """For each placement: fit on the others, score the held-out one before and after — per
    placement and per configuration (nothing is fitted on the scored configurations)."""
    chain = Chain(model)
    out = []
    for held in ds.placements:
        train = ds.subset([p for p in ds.placements if p != held])
        test = ds.subset([held])
        fit = fit_socket(model, train, **fit_options)
        before = chain.nominal.copy()
        ms = chain.marker_slice()
        before[ms.start:ms.start + 3] = _pivot_start(chain, train, chain.nominal)[0]
        ids = test.config_ids or [f"#{i + 1}" for i in range(len(test.q_rad))]
        out.append(HeldOutPlacement(
            socket_scores(chain, before, test)[0], socket_scores(chain, fit.params, test, fit.compliance)[0],
            list(ids), [test.groups[g][1] for g in test.group],
            placement_distances(chain, before, test), placement_distances(chain, fit.params, test, fit.compliance)))
    return out


def leave_one_placement_out(model: RobotModel, ds: SocketDataset, **fit_options) -> list[tuple[PlacementScore, PlacementScore]]:
    """For each placement: fit on the others, score the held-out one before (nominal model with
    the ball from the training data's pivot calibration) and after. [(before, after), …]."""
    return [(h.before, h.after) for h in held_out_placements(model, ds, **fit_options)]
