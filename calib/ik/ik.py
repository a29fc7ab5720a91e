"""Inverse kinematics: every solution of a flange pose, for 6R spherical-wrist and 7R S-R-S arms.

Public API (mm, rad, controller convention — the numbers the pendant shows, in radians):

``solve_all(model, pose, *, arm_angle=None, within_limits=True, params=None) -> IkSolutions``
``solve_many(model, poses, **same) -> list[IkSolutions]`` — vectorised over poses: for many poses
    one call is faster than a ``solve_all`` loop (6R and 7R at given arm angles: ~2×; but with
    the arm angle picked a ``solve_all`` loop is ~2× faster), see
    tests/bench/bench_ik.py. ``solve_all`` (6R; 7R at a given arm angle, or within limits at the
    one picked) solves in plain floats (``calib.ik.ik_scalar``, ``calib.ik.ik_arm_angle_scalar``) and
    hands singular, boundary and limit cases to ``solve_many``; the result is the same (rows to
    rounding, tests/calib/test_ik_one_pose.py, tests/calib/test_arm_angle_one_pose.py)
``arm_angle_intervals(model, pose, *, params=None) -> list[(lo, hi)]`` (7R; merged over the
    global configurations; ``arm_angle_intervals_by_configuration`` gives them per label,
    ``arm_angle_intervals_many`` for many poses at once)
``pick_arm_angle(model, pose, *, prefer=None, params=None) -> float`` (7R)
``arm_angle_of(model, q, *, params=None) -> ψ`` (7R, the arm angle of joint vectors)
``branch_labels(model) -> list[str]`` (the 8 principal labels)

Which solver runs is decided from the model's own chain: 6 joints → ``calib.ik.ik_spherical_wrist``
(8 branches), 7 joints → ``calib.ik.ik_srs`` (8 global configurations at one arm angle). Both check
the structure numerically and raise ``ValueError`` for a model outside their class
(``calib.ik.ik_numeric.solve_numeric`` is the slow numeric fallback for such arms).

What comes back (``IkSolutions``):

- every row reproduces the pose — each candidate is run through ``Chain.fk`` and kept only if
  the position is within ``POSITION_TOLERANCE_MM`` (1e-6 mm) and the orientation within
  ``ORIENTATION_TOLERANCE_RAD`` (1e-9 rad); nothing else is ever returned (``solve_all``'s
  float path runs the same FK in plain floats and keeps a row only within half of each);
- with ``within_limits=True`` (default) every row is inside the model's joint limits, and a
  joint whose limits reach beyond ±180° contributes each of its ±360° equivalents that fits
  (the KR 6's A4 and A6, and A2 near −180°; the TX60's J4 and J6): they are distinct
  configurations for the robot, labelled with a suffix such as ``" A6-360"``. With
  ``within_limits=False`` the 8 principal branches are returned, angles wrapped to (−π, π];
- ``status`` ``"ok"``; ``"unreachable"`` (no real solution, message says why);
  ``"singular"`` (rows are returned but the pose is within 1e-6 (rad, or mm for the shoulder)
  of a singularity — the message names it, e.g. A4 and A6 determined only as a sum at A5 = 0;
  at an exact singularity the rows are representatives of a continuum, e.g. A4 = 0);
  ``"limits"`` (solutions exist, none within limits; the message names the least-violated limit).

7R arm angle: given as a float (or one per pose); ``None`` picks, per pose, the centre of the
widest feasible interval when ``within_limits`` (status ``"limits"`` if there is none), else 0.
Arcs as wide to 1e-9 rad (the iiwa's feasible set is often symmetric: two arcs of one width)
tie, and the tie goes to the centre nearest ψ = 0, then to the positive one.

``params``: a ``Chain`` parameter vector (P,), e.g. a fitted model. If its geometry still
belongs to the solver's class (zero-offsets only, say) the closed form is built from it and is
exact; otherwise the closed form runs on the nominal geometry with the given zero-offsets and
each branch is polished by Gauss–Newton steps on ``Chain.flange_jacobian`` (7R: with the arm
angle as a seventh equation, so the requested ψ is kept). Near singularities a branch of the
perturbed model can then be missed or two merge (their solutions move far for small errors);
poses up to ``POLISH_REACH_SLACK`` beyond the nominal reach are tried too.
"""

from __future__ import annotations

import bisect
import itertools
import logging
import math
import operator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from calib.ik.ik_arm_angle_scalar import SrsArmAngleScalar
from calib.ik.ik_scalar import SrsScalar, WristArmScalar
from calib.ik.ik_spherical_wrist import REACH_SLACK, RawSolutions, WristArmGeometry
from calib.ik.ik_spherical_wrist import branch_labels as wrist_arm_labels
from calib.ik.ik_srs import SrsGeometry
from calib.ik.ik_srs import branch_labels as srs_labels
from calib.ik.ik_subproblems import ScrewAxes
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.robot.transforms import log_so3, rotation_angle

log = logging.getLogger(__name__)

POSITION_TOLERANCE_MM = 1e-6
ORIENTATION_TOLERANCE_RAD = 1e-9
#: Two solutions closer than this (max over joints, rad) are one.
DUPLICATE_TOLERANCE_RAD = 1e-7
POLISH_ITERATIONS = 12
#: With a polished (perturbed) model, poses up to this relative excess over the nominal reach
#: are still tried: the clamped nominal solution is polished, and kept only if it converges.
POLISH_REACH_SLACK = 0.02
#: The one-pose path accepts a row only this far inside the FK tolerances, and a ±360° candidate
#: only this far (rad) from a limit; anything closer goes to the vectorised path, so rounding
#: differences between the two can never change which rows come back.
_ONE_POSE_TOLERANCE_SHARE = 0.5
_ONE_POSE_LIMIT_MARGIN_RAD = 1e-9

@dataclass(frozen=True)
class IkSolutions:
    """All inverse-kinematics solutions of one flange pose.

    q (n_sol, n_joints) rad, controller convention, every row reproduces the pose;
    branch: one label per row (6R ``"shoulder=front elbow=up wrist=noflip"``, 7R
    ``"GC2=+1 GC4=+1 GC6=-1"``, plus e.g. ``" A6-360"`` for a ±360° equivalent);
    status: ``"ok" | "unreachable" | "singular" | "limits"``; message: plain-language detail,
    empty when ok.
    """

    q: np.ndarray
    branch: list[str]
    status: str
    message: str

    def __len__(self) -> int:
        return int(self.q.shape[0])


class NoFeasibleArmAngle(ValueError):
    """No arm angle puts the 7R arm's joints within limits for this pose (or it is out of reach)."""


# --- solver set-up (cached per model and parameter vector) ---------------------------------------
#: The ±360° choice of a joint whose angle is within limits as it is: (step rad, label suffix) pairs.
_UNSHIFTED = ((0.0, ""),)


class _JointImages(NamedTuple):
    """Which ±360° images of one joint's wrapped angle x (rad) are within limits (``_fitting_steps``):
    ``inner`` when inner_lo < x < inner_hi (the widest stretch, already shrunk by
    ``_ONE_POSE_LIMIT_MARGIN_RAD``), else ``fits[bisect(breaks, x)]``; each is a tuple of
    (step rad, label suffix) pairs, empty where no image fits."""

    inner_lo: float
    inner_hi: float
    inner: tuple[tuple[float, str], ...]
    breaks: list[float]
    fits: list[tuple[tuple[float, str], ...]]


@dataclass
class _OnePose:
    """What ``_solve_one`` needs, as plain floats: the closed form; the FK links
    (``Chain._links_floats``, right angles snapped); the flange frame's inverse as rows of
    (R_fᵀ | −R_fᵀ·t_f) and |t_f| mm (rows are checked at the last joint's frame against
    pose·flange⁻¹); per joint the ±360° images that fit (``_fitting_steps``, ``_joint_images``);
    (7R) the feasible arm angles (``_picked_configurations``)."""

    closed_form: WristArmScalar | SrsScalar
    links: list[tuple[float, ...]]
    flange_inv: list[list[float]]
    flange_reach: float
    images: list[_JointImages]
    shiftable: list[int]  # the joints with a ±360° image within limits somewhere
    arm_angles: SrsArmAngleScalar | None
    # the widest stretches of all joints, for ``_limit_images``' first test (from ``images``)
    inner_lo: list[float] = field(init=False)
    inner_hi: list[float] = field(init=False)
    inner: list[tuple[tuple[float, str], ...]] = field(init=False)

    def __post_init__(self) -> None:
        self.inner_lo = [im.inner_lo for im in self.images]
        self.inner_hi = [im.inner_hi for im in self.images]
        self.inner = [im.inner for im in self.images]

@dataclass
class _Solver:
    model: RobotModel
    chain: Chain
    kind: str  # "6r" | "7r"
    geometry: WristArmGeometry | SrsGeometry
    labels: list[str]
    params: np.ndarray | None  # the parameter vector FK checks use (None: nominal)
    polish: bool  # closed form is on an approximation: polish every row
    shifts: np.ndarray  # (n_combos, n) multiples of 2π to try for ±360° equivalents
    shift_labels: list[str]
    one_pose: _OnePose | None  # the one-pose float path (where the closed form is exact)


#: Solvers kept per model: one per parameter vector, oldest dropped first.
_SOLVERS_PER_MODEL = 32


def _solvers_of(model: RobotModel) -> dict[bytes | None, _Solver]:
    """The solvers built for ``model`` (keyed by parameter-vector bytes, None = nominal), kept on
    the model itself so they live and die with it: a daemon that loads a fresh model for every
    run holds none of the old ones. A copy of a model (``model_copy``, ``copy``) starts with the
    original's ``__dict__``, so the entry names its owner and a copy builds its own."""
    owner, solvers = model.__dict__.get("_ik_solvers", (None, None))
    if owner != id(model):
        solvers = {}
        model.__dict__["_ik_solvers"] = (id(model), solvers)
    return solvers


def _shift_steps(model: RobotModel) -> list[list[int]]:
    """Per joint, the multiples k of 360° for which [lo − 2πk, hi − 2πk] overlaps (−π, π],
    in the order tried (0, then ±1, …); joints whose limits lie inside (−π, π] only get k = 0."""
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    per_joint = []
    for j in range(model.n_joints):
        ks = [k for k in range(-3, 4) if lo[j] - 2 * np.pi * k <= np.pi and hi[j] - 2 * np.pi * k > -np.pi]
        per_joint.append(sorted(ks, key=lambda k: (abs(k), k)))
    return per_joint


def _shift_label(model: RobotModel, j: int, k: float) -> str:
    return f" {model.axis_names[j]}{int(360 * k):+d}" if k != 0 else ""


def _wide_shifts(model: RobotModel) -> tuple[np.ndarray, list[str]]:
    """Every combination of ±360° multiples that can bring a wrapped angle into the limits
    (``_shift_steps``). Returns shifts (C, n) rad (row 0 all zeros) and label suffixes such as
    " A6-360"."""
    n = model.n_joints
    combos = np.array(list(itertools.product(*_shift_steps(model))), dtype=float).reshape(-1, n)
    labels = ["".join(_shift_label(model, j, c[j]) for j in range(n)) for c in combos]
    return combos * 2 * math.pi, labels


def _fitting_steps(model: RobotModel) -> list[tuple[list[float], list[tuple[tuple[float, str], ...]]]]:
    """Per joint: the wrapped angles at which some ±360° image meets a limit (lo − 2πk, hi − 2πk;
    sorted) and, for each stretch between them (``bisect`` index), the steps (2πk rad, label
    suffix) that put the angle within limits, in ``_shift_steps`` order (the unshifted angle alone
    as the one object ``_UNSHIFTED``)."""
    out = []
    for j, (lo, hi, ks) in enumerate(zip(model.lower_limits_rad.tolist(), model.upper_limits_rad.tolist(), _shift_steps(model))):
        steps = [(k * 2 * math.pi, _shift_label(model, j, k)) for k in map(float, ks)]
        breaks = sorted(lim - step for step, _ in steps for lim in (lo, hi))
        mids = [breaks[0] - 1.0] + [0.5 * (a + b) for a, b in zip(breaks, breaks[1:])] + [breaks[-1] + 1.0]
        fits = [tuple((st, sf) for st, sf in steps if lo <= x + st <= hi) for x in mids]
        out.append((breaks, [_UNSHIFTED if f == _UNSHIFTED else f for f in fits]))
    return out


def _joint_images(steps: list[tuple[list[float], list[tuple[tuple[float, str], ...]]]]) -> list[_JointImages]:
    """``_fitting_steps`` with, per joint, the stretch overlapping (−π, π] most as an interval
    (shrunk by ``_ONE_POSE_LIMIT_MARGIN_RAD``), tested first."""
    out = []
    for breaks, fits in steps:
        i = max(range(1, len(breaks)), key=lambda i: min(breaks[i], math.pi) - max(breaks[i - 1], -math.pi))
        m = _ONE_POSE_LIMIT_MARGIN_RAD
        out.append(_JointImages(breaks[i - 1] + m, breaks[i] - m, fits[i], breaks, fits))
    return out


def _build(model: RobotModel, chain: Chain, params: np.ndarray | None) -> _Solver:
    n = model.n_joints
    names = tuple(model.axis_names)
    if n == 6:
        cls, labels, kind = WristArmGeometry, wrist_arm_labels(), "6r"
    elif n == 7:
        cls, labels, kind = SrsGeometry, srs_labels(), "7r"
    else:
        raise ValueError(
            f"{model.name} has {n} joints; analytic IK covers 6-joint arms with a spherical wrist and "
            f"7-joint S-R-S arms (use calib.ik.ik_numeric.solve_numeric for others)"
        )
    polish = False
    if params is None:
        geometry = cls.from_axes(ScrewAxes.from_chain(chain), names, model.name)
    else:
        try:
            geometry = cls.from_axes(ScrewAxes.from_chain(chain, params), names, model.name)
        except ValueError:
            # the fitted geometry left the class (link errors): nominal structure + offsets, then polish
            geometry = cls.from_axes(ScrewAxes.from_chain(chain, chain.with_offsets(params[:n])), names, model.name)
            polish = True
    shifts, shift_labels = _wide_shifts(model)
    one_pose = None
    if not polish:
        closed_form = WristArmScalar(geometry) if kind == "6r" else SrsScalar(geometry)
        steps = _fitting_steps(model)
        images = _joint_images(steps)
        one_pose = _OnePose(
            closed_form=closed_form,
            links=chain._links_floats((chain.nominal if params is None else params).tolist(), snap_right_angles=True),
            flange_inv=np.linalg.inv(chain.flange)[:3].tolist(),
            flange_reach=float(np.linalg.norm(chain.flange[:3, 3])),
            images=images,
            shiftable=[j for j, im in enumerate(images) if any(f not in ((), _UNSHIFTED) for f in im.fits)],
            arm_angles=None if kind == "6r" else SrsArmAngleScalar(
                geometry, closed_form, model.lower_limits_rad.tolist(), model.upper_limits_rad.tolist(), steps
            ),
        )
    return _Solver(model, chain, kind, geometry, labels, params, polish, shifts, shift_labels, one_pose)


def _solver(model: RobotModel, params: np.ndarray | None) -> _Solver:
    if not isinstance(model, RobotModel):
        raise TypeError(f"model must be a calib.robot.model.RobotModel, got {type(model).__name__}")
    p = None
    if params is not None:
        p = np.asarray(params, dtype=float)
        n_params = 5 * model.n_joints + 3 * len(model.tool.markers)
        if p.shape != (n_params,):
            raise ValueError(f"params must be one Chain parameter vector of shape ({n_params},), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("params contains NaN or infinite entries")
    solvers = _solvers_of(model)
    key = None if p is None else p.tobytes()
    hit = solvers.get(key)
    if hit is not None:
        return hit
    nominal = solvers.get(None)
    solver = _build(model, nominal.chain if nominal is not None else Chain(model), p)
    if len(solvers) >= _SOLVERS_PER_MODEL:
        solvers.pop(next(k for k in solvers if k is not None))  # the nominal solver stays
    solvers[key] = solver
    return solver


def _check_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (k, 4, 4) (flange frames in the base frame, mm), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("poses contain NaN or infinite entries")
    r = poses[:, :3, :3]
    ortho = np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max(axis=(-1, -2))
    det = np.linalg.det(r)
    bad = np.flatnonzero((ortho > 1e-6) | (det < 0) | np.any(np.abs(poses[:, 3, :] - [0, 0, 0, 1]) > 1e-12, axis=-1))
    if bad.size:
        raise ValueError(
            f"pose {int(bad[0])} is not a rigid transform (rotation must be orthonormal with det +1 to 1e-6, "
            f"last row [0, 0, 0, 1]); {bad.size} such pose(s) given"
        )
    return poses


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


# --- verification and polishing ---------------------------------------------------------------
def _pose_errors(chain: Chain, q: np.ndarray, targets: np.ndarray, params: np.ndarray | None):
    rot, pos = chain.flange_pose(q, params)
    dp = np.linalg.norm(pos - targets[:, :3, 3], axis=-1)
    dr = rotation_angle(np.swapaxes(targets[:, :3, :3], -1, -2) @ rot)
    return dp, dr


def _polish(
    s: _Solver, q: np.ndarray, targets: np.ndarray, psi: np.ndarray | None = None
) -> np.ndarray:
    """Gauss–Newton on the flange pose: q (m, n), targets (m, 4, 4) → refined q (m, n).

    For the 7R arm with ``psi`` (m,) the arm angle is a seventh equation, so the polished
    solution keeps the requested arm angle (as ``arm_angle_of`` measures it).
    """
    chain, params = s.chain, s.params
    n = chain.n
    q = q.copy()
    rows = 6 if psi is None else 7
    act = np.arange(q.shape[0])
    for _ in range(POLISH_ITERATIONS):
        qa, ta = q[act], targets[act]
        fj = chain.flange_jacobian(qa, params)
        e = np.concatenate([ta[:, :3, 3] - fj.position, log_so3(ta[:, :3, :3] @ np.swapaxes(fj.rotation, -1, -2))], -1)
        jac = np.concatenate([fj.jp[..., :n], fj.jw[..., :n]], -2)  # (m, 6, n)
        if psi is not None:
            h = 1e-7
            base = s.geometry.arm_angle(qa)
            grad = _wrap(s.geometry.arm_angle(qa[:, None, :] + h * np.eye(n)) - base[:, None]) / h
            e = np.concatenate([e, _wrap(psi[act] - base)[:, None]], -1)
            jac = np.concatenate([jac, grad[:, None, :]], -2)
        done = np.all(np.abs(e[:, :3]) < 1e-10, axis=-1) & np.all(np.abs(e[:, 3:]) < 1e-13, axis=-1)
        if done.all():
            break
        act, e, jac, qa = act[~done], e[~done], jac[~done], qa[~done]
        jjt = jac @ np.swapaxes(jac, -1, -2)
        damp = 1e-14 * np.trace(jjt, axis1=-2, axis2=-1)[:, None, None] * np.eye(rows)
        step = np.einsum("mji,mj->mi", jac, np.linalg.solve(jjt + damp, e[..., None])[..., 0])
        # limit wild steps near singularities
        big = np.abs(step).max(axis=-1, keepdims=True)
        q[act] = qa + step * np.minimum(1.0, 0.5 / np.maximum(big, 1e-300))
    return q


def _verified(s: _Solver, raw: RawSolutions, poses: np.ndarray, psi: np.ndarray | None = None) -> np.ndarray:
    """raw.q with failing rows marked NaN; polishes where needed. Returns q (k, B, n)."""
    k, nb, n = raw.q.shape
    q = raw.q.reshape(-1, n).copy()
    valid = raw.valid.reshape(-1)
    targets = np.repeat(poses, nb, axis=0)
    psis = None if psi is None else np.repeat(psi, nb)
    idx = np.flatnonzero(valid)
    if s.polish and idx.size:
        q[idx] = _polish(s, q[idx], targets[idx], None if psis is None else psis[idx])
    ok = np.zeros(k * nb, dtype=bool)
    if idx.size:
        dp, dr = _pose_errors(s.chain, q[idx], targets[idx], s.params)
        good = (dp <= POSITION_TOLERANCE_MM) & (dr <= ORIENTATION_TOLERANCE_RAD)
        bad = idx[~good]
        if bad.size:  # numerical safety net (near singularities): polish and check again
            q[bad] = _polish(s, q[bad], targets[bad], None if psis is None else psis[bad])
            dp2, dr2 = _pose_errors(s.chain, q[bad], targets[bad], s.params)
            good2 = (dp2 <= POSITION_TOLERANCE_MM) & (dr2 <= ORIENTATION_TOLERANCE_RAD)
            if not good2.all():
                log.debug("discarded %d IK candidate(s) that did not reproduce the pose", int((~good2).sum()))
            good[~good] = good2
        ok[idx] = good
    q = _wrap(q)
    q[~ok] = np.nan
    return q.reshape(k, nb, n)


def _limits_message(model: RobotModel, q: np.ndarray) -> str:
    """Which limit the closest solution (rows q (m, n), principal) violates."""
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    best = None
    for row in q:
        over = np.maximum(lo - row, 0) + np.maximum(row - hi, 0)
        # a ±360° equivalent may fit one joint better
        for j in range(len(row)):
            for sh in (-2 * np.pi, 2 * np.pi):
                alt = row[j] + sh
                o = max(lo[j] - alt, 0) + max(alt - hi[j], 0)
                if o < over[j]:
                    over[j] = o
                    row = row.copy()
                    row[j] = alt
        total = over.sum()
        if best is None or total < best[0]:
            best = (total, row, over)
    _, row, over = best
    worst = int(np.argmax(over))
    return (
        f"{len(q)} solution(s) reproduce the pose but none is within the joint limits; the closest has "
        f"{model.axis_names[worst]} = {np.degrees(row[worst]):.3f}° (limits {model.joints[worst].limits[0]:g}° … "
        f"{model.joints[worst].limits[1]:g}°)"
    )


def _recheck_singular(s: _Solver, raw: RawSolutions, q: np.ndarray) -> RawSolutions:
    """With a polished model the nominal geometry's singularity flags can be spurious: keep a
    flag only if some polished solution's Jacobian is within ~1e-6 of rank deficiency."""
    flagged = [i for i, m in enumerate(raw.singular) if m]
    if not flagged:
        return raw
    singular = list(raw.singular)
    n = q.shape[-1]
    for i in flagged:
        rows = q[i][~np.isnan(q[i, :, 0])]
        if rows.size == 0:
            continue
        fj = s.chain.flange_jacobian(rows, s.params)
        jac = np.concatenate([fj.jp[..., :n], 1000.0 * fj.jw[..., :n]], -2)  # rad rows scaled to mm at 1 m
        sv = np.linalg.svd(jac, compute_uv=False)
        if np.all(sv[:, -1] > 1e-6 * sv[:, 0]):
            singular[i] = ""
    return RawSolutions(q=raw.q, valid=raw.valid, unreachable=raw.unreachable, singular=singular)


def _assemble(s: _Solver, raw: RawSolutions, q: np.ndarray, within_limits: bool) -> list[IkSolutions]:
    model = s.model
    k, nb, n = q.shape
    if s.polish:
        raw = _recheck_singular(s, raw, q)
    lo, hi = model.lower_limits_rad, model.upper_limits_rad
    ok = ~np.isnan(q[..., 0])
    # duplicates among branches (exact singularities, branches polished onto one another)
    diff = np.abs(_wrap(q[:, :, None, :] - q[:, None, :, :])).max(-1)  # (k, B, B)
    same = (diff < DUPLICATE_TOLERANCE_RAD) & np.tril(np.ones((nb, nb), dtype=bool), -1)
    ok &= ~np.any(same & ok[:, None, :], axis=-1)
    if within_limits:
        cand = q[:, :, None, :] + s.shifts[None, None, :, :]  # (k, B, C, n)
        inside = np.all((cand >= lo) & (cand <= hi), axis=-1) & ok[..., None]
    out = []
    empty = np.zeros((0, n))
    for i in range(k):
        if raw.unreachable[i]:
            out.append(IkSolutions(empty, [], "unreachable", raw.unreachable[i]))
            continue
        rows = np.flatnonzero(ok[i])
        if rows.size == 0:
            why = raw.singular[i] or "the pose is numerically degenerate"
            status = "unreachable" if s.polish else "singular"
            msg = "no branch reproduces the pose to tolerance" + (" for the given parameters" if s.polish else "")
            out.append(IkSolutions(empty, [], status, f"{msg} ({why})"))
            continue
        if within_limits:
            b_idx, c_idx = np.nonzero(inside[i])
            if b_idx.size == 0:
                msg = _limits_message(model, q[i, rows])
                if raw.singular[i]:
                    msg += "; also " + raw.singular[i]
                out.append(IkSolutions(empty, [], "limits", msg))
                continue
            sol = cand[i, b_idx, c_idx]
            labels = [s.labels[b] + s.shift_labels[c] for b, c in zip(b_idx, c_idx)]
        else:
            sol = q[i, rows]
            labels = [s.labels[b] for b in rows]
        status = "singular" if raw.singular[i] else "ok"
        out.append(IkSolutions(np.ascontiguousarray(sol), labels, status, raw.singular[i]))
    return out


def _limit_images(q: list[float], one: _OnePose) -> list[tuple[tuple[float, str], ...]] | None:
    """Per joint of the wrapped row q (n) rad, its ±360° images within limits as (step rad,
    label suffix) pairs; [] when some joint has none; None when a joint is within
    ``_ONE_POSE_LIMIT_MARGIN_RAD`` of a limit or of one of its ±360° images. (Do not modify
    the list returned: it may be ``one.inner``.)"""
    if all(map(operator.lt, one.inner_lo, q)) and all(map(operator.lt, q, one.inner_hi)):
        return one.inner  # every joint on its widest stretch: tested without a Python loop
    picks = []
    images = one.images
    for qj, (inner_lo, inner_hi, inner, breaks, fits) in zip(q, images):
        if inner_lo < qj < inner_hi:
            picks.append(inner)
            continue
        i = bisect.bisect(breaks, qj)
        if (i and qj - breaks[i - 1] < _ONE_POSE_LIMIT_MARGIN_RAD) or (
            i < len(breaks) and breaks[i] - qj < _ONE_POSE_LIMIT_MARGIN_RAD
        ):
            return None
        if not fits[i]:
            return []
        picks.append(fits[i])
    return picks


def _solve_one(s: _Solver, pose: np.ndarray, within_limits: bool, psi: float | None = None) -> IkSolutions | None:
    """``solve_many`` for one pose (4, 4) in plain floats (6R; 7R at the arm angle ``psi`` rad,
    or with ``psi=None`` and ``within_limits`` the one ``solve_many`` picks), or None where the pose
    needs the vectorised path: not a clean rigid transform (it raises there), out of reach, near
    a singularity (``calib.ik.ik_scalar``), no clear pick, a row near a tolerance or limit, or no
    row within limits. Same rows, labels and order as ``solve_many`` (to rounding, ≲1e-12 rad).
    Every row within limits (every row, without limits) is checked by FK in floats
    (``Chain._walk_links``) before it is returned (``_last_frame_check``); ±360° images share
    their row's check."""
    one = s.one_pose
    if one is None:
        return None
    m = pose.tolist()
    (r00, r01, r02, p0), (r10, r11, r12, p1), (r20, r21, r22, p2), last = m
    if last != [0.0, 0.0, 0.0, 1.0] or not math.isfinite(r00 + r01 + r02 + p0 + r10 + r11 + r12 + p1 + r20 + r21 + r22 + p2):
        return None  # (a sum overflowing to inf only sends a huge pose the slow way)
    # a rigid transform to half the 1e-6 ``_check_poses`` asks (it raises where that fails)
    if max(
        abs(r00 * r00 + r10 * r10 + r20 * r20 - 1.0), abs(r01 * r01 + r11 * r11 + r21 * r21 - 1.0),
        abs(r02 * r02 + r12 * r12 + r22 * r22 - 1.0), abs(r00 * r01 + r10 * r11 + r20 * r21),
        abs(r00 * r02 + r10 * r12 + r20 * r22), abs(r01 * r02 + r11 * r12 + r21 * r22),
    ) > 0.5e-6 or (r10 * r21 - r20 * r11) * r02 + (r20 * r01 - r00 * r21) * r12 + (r00 * r11 - r10 * r01) * r22 < 0:
        return None
    rot = ((r00, r01, r02), (r10, r11, r12), (r20, r21, r22))
    pos = (p0, p1, p2)
    if s.kind == "6r":
        branches = one.closed_form.solve(rot, pos)
    elif psi is None and within_limits:
        branches = _picked_configurations(s, rot, pos)
    elif psi is not None and math.isfinite(psi):
        branches = one.closed_form.solve(rot, pos, psi)
    else:
        return None
    if branches is None:
        return None
    checked = _last_frame_check(one, rot, pos)
    walk, labels_b, shiftable = s.chain._walk_links, s.labels, one.shiftable
    n, shared = len(one.links), one.closed_form.shared_joints
    arm_links, wrist_links = one.links[:shared], one.links[shared:]
    arm_q, arm = None, ()  # branches 2i, 2i + 1 share their first joints: one walk to there serves both
    flat: list[float] = []  # the rows, one after the other
    labels: list[str] = []
    for b, q in enumerate(branches):
        if q is None:
            continue
        if within_limits:  # first, as a row outside the limits needs no FK check: it is dropped either way
            picks = _limit_images(q, one)
            if picks is None:
                return None
            if not picks:
                continue
        if q[:shared] != arm_q:
            arm_q = q[:shared]
            arm = walk(arm_q, arm_links)
        if not checked(walk(q[shared:], wrist_links, arm)):
            return None
        if not within_limits or picks.count(_UNSHIFTED) == n:  # the row is its only image
            flat.extend(q)
            labels.append(labels_b[b])
            continue
        # the row and its ±360° images, in ``itertools.product(*picks)`` order (earlier joints vary slowest)
        row_images, label_images = [q], [labels_b[b]]
        for j in shiftable:
            pick = picks[j]
            if pick is _UNSHIFTED:
                continue
            grown_rows, grown_labels = [], []
            for row, label in zip(row_images, label_images):
                for step, suffix in pick:
                    if step:
                        image = row.copy()
                        image[j] += step
                        grown_rows.append(image)
                    else:
                        grown_rows.append(row)
                    grown_labels.append(label + suffix)
            row_images, label_images = grown_rows, grown_labels
        for row in row_images:
            flat.extend(row)
        labels.extend(label_images)
    if not labels:
        return None  # "limits": the vectorised path names the least-violated limit
    return IkSolutions(np.fromiter(flat, float, len(flat)).reshape(len(labels), -1), labels, "ok", "")


def _last_frame_check(one: _OnePose, rot: tuple, pos: tuple):
    """A test of the last joint's frame (12 floats from ``Chain._walk_links``) against the flange
    pose ``rot`` (rows), ``pos`` (mm): true when the flange it carries is within
    ``_ONE_POSE_TOLERANCE_SHARE`` of the FK tolerances of the pose.

    The frame is compared with pose·flange⁻¹ (computed here once, not a flange product per row):
    the rotation's Frobenius distance is the flange's (the flange rotation is orthonormal); the
    flange position error is at most the origin's plus |t_f|·that distance, so the position
    test on that bound is never looser than ``solve_many``'s."""
    (g00, g01, g02, g03), (g10, g11, g12, g13), (g20, g21, g22, g23) = one.flange_inv
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rot
    # columns x, y, z, origin of pose·flange⁻¹
    tx0, tx1, tx2 = r00 * g00 + r01 * g10 + r02 * g20, r10 * g00 + r11 * g10 + r12 * g20, r20 * g00 + r21 * g10 + r22 * g20
    ty0, ty1, ty2 = r00 * g01 + r01 * g11 + r02 * g21, r10 * g01 + r11 * g11 + r12 * g21, r20 * g01 + r21 * g11 + r22 * g21
    tz0, tz1, tz2 = r00 * g02 + r01 * g12 + r02 * g22, r10 * g02 + r11 * g12 + r12 * g22, r20 * g02 + r21 * g12 + r22 * g22
    to0 = r00 * g03 + r01 * g13 + r02 * g23 + pos[0]
    to1 = r10 * g03 + r11 * g13 + r12 * g23 + pos[1]
    to2 = r20 * g03 + r21 * g13 + r22 * g23 + pos[2]
    tol_p = POSITION_TOLERANCE_MM * _ONE_POSE_TOLERANCE_SHARE
    # rotation angle θ from the Frobenius distance ‖R − R_target‖² = 8 sin²(θ/2)
    tol_frob_sq = 8.0 * math.sin(ORIENTATION_TOLERANCE_RAD * _ONE_POSE_TOLERANCE_SHARE / 2.0) ** 2
    reach = one.flange_reach

    def checked(frame: tuple[float, ...]) -> bool:
        fx0, fx1, fx2, fy0, fy1, fy2, fz0, fz1, fz2, fo0, fo1, fo2 = frame
        frob_sq = (
            (fx0 - tx0) ** 2 + (fx1 - tx1) ** 2 + (fx2 - tx2) ** 2
            + (fy0 - ty0) ** 2 + (fy1 - ty1) ** 2 + (fy2 - ty2) ** 2
            + (fz0 - tz0) ** 2 + (fz1 - tz1) ** 2 + (fz2 - tz2) ** 2
        )
        return frob_sq <= tol_frob_sq and math.hypot(fo0 - to0, fo1 - to1, fo2 - to2) + reach * math.sqrt(frob_sq) <= tol_p

    return checked


def _slack(s: _Solver) -> float:
    """Reach slack: a perturbed model may reach a little beyond the nominal one."""
    return POLISH_REACH_SLACK if s.polish else REACH_SLACK


# --- public API --------------------------------------------------------------------------------
def solve_many(
    model: RobotModel,
    poses: np.ndarray,
    *,
    arm_angle: float | np.ndarray | None = None,
    within_limits: bool = True,
    params: np.ndarray | None = None,
) -> list[IkSolutions]:
    """Every IK solution of each flange pose; poses (k, 4, 4) mm in the robot base frame.

    ``arm_angle`` (7R only): ψ rad, one float for all poses or an array (k,). ``None``: with
    ``within_limits`` the centre of the widest feasible arm-angle interval of each pose
    (``pick_arm_angle``), else ψ = 0. Passing it for a 6R arm raises ``ValueError``.
    Returns one ``IkSolutions`` per pose (see the module docstring).
    """
    s = _solver(model, params)
    poses = _check_poses(poses)
    k = poses.shape[0]
    if s.kind == "6r":
        if arm_angle is not None:
            raise ValueError(f"arm_angle applies to 7-joint arms; {model.name} has 6 joints (pass None)")
        raw = s.geometry.solve(poses, reach_slack=_slack(s))
        return _assemble(s, raw, _verified(s, raw, poses), within_limits)
    no_angle: list[str] = [""] * k
    if arm_angle is None:
        psi = np.zeros(k)
        if within_limits:
            for i, per in enumerate(_intervals_many(s, poses)):
                ivs = _merge([iv for v in per.values() for iv in v])
                if ivs:
                    psi[i] = _pick(ivs, None)
                else:
                    no_angle[i] = f"no arm angle puts every joint of {model.name} within limits for this pose"
    else:
        psi = np.asarray(arm_angle, dtype=float)
        if psi.ndim > 1 or (psi.ndim == 1 and psi.shape[0] != k):
            raise ValueError(f"arm_angle must be one float or one per pose (shape ({k},)), got shape {psi.shape}")
        psi = np.broadcast_to(psi, (k,)).copy()
        if not np.all(np.isfinite(psi)):
            raise ValueError(f"arm_angle must be finite (rad), got {arm_angle!r}")
    raw = s.geometry.solve(poses, psi, reach_slack=_slack(s))
    out = _assemble(s, raw, _verified(s, raw, poses, psi), within_limits)
    for i in range(k):
        if no_angle[i] and out[i].status != "unreachable":
            out[i] = IkSolutions(np.zeros((0, model.n_joints)), [], "limits", no_angle[i])
    return out


def solve_all(
    model: RobotModel,
    pose: np.ndarray,
    *,
    arm_angle: float | None = None,
    within_limits: bool = True,
    params: np.ndarray | None = None,
) -> IkSolutions:
    """Every IK solution of one flange pose (4, 4) mm; see ``solve_many``.

    A pose away from singularities, reach boundaries and limits (6R; 7R at a given arm angle or,
    within limits, the one picked) is solved in plain floats (``_solve_one``: one pose through
    numpy costs some hundred tiny array calls); the result is ``solve_many``'s, rows equal to
    rounding. (7R with ``within_limits=False`` and no arm angle solves at ψ = 0, where the iiwa's
    A3 is 0 or ±π — an end rounding chooses — in every pose: the vectorised path's alone.)
    """
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (4, 4):
        raise ValueError(f"pose must be one (4, 4) flange frame, got shape {pose.shape}")
    s = _solver(model, params)
    if arm_angle is None and (s.kind == "6r" or within_limits):
        one = _solve_one(s, pose, within_limits)
    elif s.kind == "7r" and isinstance(arm_angle, (float, int, np.floating, np.integer)):
        one = _solve_one(s, pose, within_limits, float(arm_angle))
    else:
        one = None
    if one is not None:
        return one
    return solve_many(model, pose[None], arm_angle=arm_angle, within_limits=within_limits, params=params)[0]


def branch_labels(model: RobotModel) -> list[str]:
    """The 8 principal branch labels of ``model``'s solver, in branch order (no ±360° suffixes)."""
    return list(_solver(model, None).labels)


# --- 7R arm angle ------------------------------------------------------------------------------
def _srs(model: RobotModel, params: np.ndarray | None) -> _Solver:
    s = _solver(model, params)
    if s.kind != "7r":
        raise ValueError(f"arm angles apply to 7-joint S-R-S arms; {model.name} has {model.n_joints} joints")
    return s


def arm_angle_of(model: RobotModel, q: np.ndarray, *, params: np.ndarray | None = None) -> np.ndarray:
    """Arm angle ψ (...) rad of joint vectors q (..., 7) rad (7R): ``solve_all(fk(q), arm_angle=ψ)`` contains q."""
    s = _srs(model, params)
    q = np.asarray(q, dtype=float)
    if q.shape[-1] != 7:
        raise ValueError(f"joint vectors must have 7 entries, got shape {q.shape}")
    return s.geometry.arm_angle(q)


def _feasible(s: _Solver, poses: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """(m, 8) — configuration exists and (some ±360° equivalent of) it is within limits;
    poses (m, 4, 4) or (4, 4) broadcast, ψ (m,)."""
    raw = s.geometry.solve(np.broadcast_to(poses, (psi.size, 4, 4)), psi)
    lo, hi = s.model.lower_limits_rad, s.model.upper_limits_rad
    cand = raw.q[:, :, None, :] + s.shifts[None, None, :, :]
    inside = np.all((cand >= lo) & (cand <= hi), axis=-1).any(axis=-1)
    return inside & raw.valid


def _intervals_many(s: _Solver, poses: np.ndarray) -> list[dict[str, list[tuple[float, float]]]]:
    """Per pose (k, 4, 4): feasible arm-angle intervals per configuration label."""
    k = poses.shape[0]
    cuts_all = s.geometry.limit_crossings(poses, s.model.lower_limits_rad, s.model.upper_limits_rad)
    reach = s.geometry.reachable(poses)
    cuts_per, mids, owner = [], [], []
    for i in range(k):
        cuts = np.unique(cuts_all[i][np.isfinite(cuts_all[i])]) if reach[i] else np.zeros(0)
        cuts_per.append(cuts)
        if not reach[i]:
            continue
        if cuts.size == 0:
            mids.append(np.zeros(1))
        else:
            ends = np.append(cuts[1:], cuts[0] + 2 * np.pi)  # gap g runs from cuts[g] to ends[g]
            mids.append(_wrap(0.5 * (cuts + ends)))
        owner.append(np.full(mids[-1].size, i))
    feas_all = _feasible(s, poses[np.concatenate(owner)], np.concatenate(mids)) if owner else np.zeros((0, 8), bool)
    out: list[dict[str, list[tuple[float, float]]]] = []
    start = 0
    for i in range(k):
        if not reach[i]:
            out.append({label: [] for label in s.labels})
            continue
        n_gaps = max(cuts_per[i].size, 1)
        cuts, columns = cuts_per[i].tolist(), feas_all[start : start + n_gaps].T.tolist()
        out.append({label: _gap_intervals(cuts, col) for label, col in zip(s.labels, columns)})
        start += n_gaps
    return out


def _gap_intervals(cuts: list[float], feasible: list[bool]) -> list[tuple[float, float]]:
    """Feasible arm-angle intervals (sorted, merged, within [−π, π]) from the sorted crossings
    ψ (rad, in (−π, π]) and whether each gap between them is feasible (gap g from cuts[g] to the
    next, the last through ±π; one gap, the whole circle, when there is no crossing). Plain
    Python: a handful of gaps per pose, where numpy's per-call cost dominated."""
    if all(feasible):
        return [(-np.pi, np.pi)]
    if not any(feasible):
        return []
    ends = cuts[1:] + [cuts[0] + 2 * np.pi]
    intervals: list[tuple[float, float]] = []
    g0 = feasible.index(False)
    run = None
    for g in [*range(g0 + 1, len(feasible)), *range(g0)]:  # starts after an infeasible gap
        if feasible[g] and run is None:
            run = [cuts[g], ends[g]]
        elif feasible[g]:
            run[1] = ends[g]
        elif run is not None:
            intervals.extend(_split(*run))
            run = None
    if run is not None:
        intervals.extend(_split(*run))
    return _merge(intervals)


def _picked_configurations(s: _Solver, rot, pos) -> list[list[float] | None] | None:
    """For one 7R pose given as plain floats (rotation rows, position mm): the configurations
    that may be within limits at the arm angle ``solve_many`` picks (``_widest_centre`` of
    ``_intervals_many``'s intervals, here from ``calib.ik.ik_arm_angle_scalar``), in the form of
    ``SrsScalar.solve``; None where the float path cannot decide, there is no feasible arm
    angle ("limits": the vectorised path writes the message), or a tie rounding could decide."""
    one = s.one_pose.arm_angles.pose(rot, pos)
    if one is None:
        return None
    ivs = _gap_intervals(one.cuts, one.feasible)  # the union over the configurations, merged
    psi = _widest_centre(ivs, guard=0.5 * _PICK_TIE_RAD) if ivs else None
    return None if psi is None else one.configurations(psi)


def arm_angle_intervals_by_configuration(
    model: RobotModel, pose: np.ndarray, *, params: np.ndarray | None = None
) -> dict[str, list[tuple[float, float]]]:
    """Feasible arm-angle intervals (rad, within [−π, π]) per global configuration label (7R).

    Method (Shimizu et al. 2008): every joint angle is a closed-form function of ψ, so the arm
    angles where any joint meets a limit are roots of ``a sin ψ + b cos ψ + c = 0``
    (``SrsGeometry.limit_crossings``). Between consecutive roots feasibility cannot change; it is
    tested once at each gap's midpoint. Boundaries are therefore exact to rounding (≈1e-12 rad;
    ≈1e-8 rad where a joint only grazes its limit) and no interval is missed however narrow.
    An interval through ±π is split into (lo, π) and (−π, hi). With ``params`` the intervals
    are those of the analytic geometry (nominal + zero-offsets when the fitted geometry is
    outside the class), so boundaries may differ from the polished model's by the link error.
    """
    s = _srs(model, params)
    pose = _check_poses(np.asarray(pose, dtype=float)[None])
    return _intervals_many(s, pose)[0]


def _split(lo: float, hi: float) -> list[tuple[float, float]]:
    """Arc from lo to hi (hi ≥ lo, hi − lo ≤ 2π) as intervals within [−π, π]."""
    if hi - lo >= 2 * np.pi:
        return [(-np.pi, np.pi)]
    lo, hi = math.pi - (math.pi - lo) % (2 * math.pi), math.pi - (math.pi - hi) % (2 * math.pi)  # _wrap, on floats
    if hi >= lo:
        return [(lo, hi)]
    return [(lo, np.pi), (-np.pi, hi)]


def _merge(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    merged: list[list[float]] = []
    for lo, hi in sorted(intervals):
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    return [(a, b) for a, b in merged]


def arm_angle_intervals(model: RobotModel, pose: np.ndarray, *, params: np.ndarray | None = None) -> list[tuple[float, float]]:
    """Arm angles ψ (rad) at which at least one global configuration is within limits (7R).

    The union over the 8 configurations of ``arm_angle_intervals_by_configuration`` (see there
    for the accuracy), as sorted disjoint (lo, hi) pairs within [−π, π]; an arc through ±π
    appears as (lo, π) and (−π, hi). Empty when the pose is out of reach or no arm angle works.
    """
    per = arm_angle_intervals_by_configuration(model, pose, params=params)
    return _merge([iv for ivs in per.values() for iv in ivs])


def arm_angle_intervals_many(
    model: RobotModel, poses: np.ndarray, *, params: np.ndarray | None = None
) -> list[list[tuple[float, float]]]:
    """``arm_angle_intervals`` for poses (k, 4, 4), vectorised (much faster than a loop)."""
    s = _srs(model, params)
    per_pose = _intervals_many(s, _check_poses(poses))
    return [_merge([iv for ivs in per.values() for iv in ivs]) for per in per_pose]


def _arcs(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Join (lo, π) and (−π, hi) into one arc (lo, hi + 2π)."""
    arcs = list(intervals)
    if len(arcs) >= 2 and arcs[0][0] <= -np.pi + 1e-12 and arcs[-1][1] >= np.pi - 1e-12:
        first, last = arcs.pop(0), arcs.pop()
        arcs.append((last[0], first[1] + 2 * np.pi))
    return arcs


#: Feasible arcs as wide as the widest to this (rad) tie for ``_widest_centre`` (the iiwa's
#: feasible set is often symmetric under ψ → ψ + π or ψ → −ψ: two arcs of one width).
_PICK_TIE_RAD = 1e-9


def _widest_centre(ivs: list[tuple[float, float]], guard: float = 0.0) -> float | None:
    """The centre (rad, in (−π, π]) of the widest arc of the feasible intervals ``ivs``; arcs
    within ``_PICK_TIE_RAD`` of the widest tie, and a tie goes to the centre nearest ψ = 0,
    then (centres ±c alike to ``_PICK_TIE_RAD``) to the positive one.

    ``guard`` > 0 (rad): None where a width or a distance from 0 lies within ``guard`` of a tie
    threshold, so that intervals equal to rounding never pick different arcs.
    """
    arcs = _arcs(ivs)
    top = max(hi - lo for lo, hi in arcs)
    tied = []
    for lo, hi in arcs:
        short = top - (hi - lo)
        if abs(short - _PICK_TIE_RAD) <= guard:
            return None
        if short < _PICK_TIE_RAD:
            tied.append(math.pi - (math.pi - 0.5 * (lo + hi)) % (2 * math.pi))
    nearest = min(map(abs, tied))
    closest = []
    for c in tied:
        if abs(abs(c) - nearest - _PICK_TIE_RAD) <= guard:
            return None
        if abs(c) - nearest < _PICK_TIE_RAD:
            closest.append(c)
    return max(closest)


def _pick(ivs: list[tuple[float, float]], prefer: float | None) -> float:
    if prefer is None:
        return _widest_centre(ivs)
    arcs = _arcs(ivs)
    best, best_d = prefer, math.inf
    for lo, hi in arcs:
        off = float(_wrap(prefer - lo))
        off = off if off >= 0 else off + 2 * np.pi
        if off <= hi - lo:
            return float(_wrap(prefer))
        margin = min(1e-6, 0.5 * (hi - lo))
        for edge, inward in ((lo, margin), (hi, -margin)):
            d = abs(float(_wrap(prefer - edge)))
            if d < best_d:
                best, best_d = edge + inward, d
    return float(_wrap(best))


def pick_arm_angle(
    model: RobotModel, pose: np.ndarray, *, prefer: float | None = None, params: np.ndarray | None = None
) -> float:
    """An arm angle ψ (rad, in (−π, π]) at which some configuration is within limits (7R).

    ``prefer=None``: the centre of the widest feasible arc (ties: see the module docstring). Otherwise ``prefer`` itself if
    feasible, else the feasible ψ closest to it (on the circle), 1e-6 rad inside the arc's end
    (or its centre if the arc is narrower). Raises ``NoFeasibleArmAngle`` (a ``ValueError``)
    when there is none.
    """
    if prefer is not None and not math.isfinite(float(prefer)):
        raise ValueError(f"prefer must be a finite arm angle in rad, got {prefer!r}")
    ivs = arm_angle_intervals(model, pose, params=params)
    if not ivs:
        s = _srs(model, params)
        raw = s.geometry.solve(np.asarray(pose, dtype=float)[None], np.zeros(1), reach_slack=_slack(s))
        why = raw.unreachable[0] or f"no arm angle puts every joint of {model.name} within limits for this pose"
        raise NoFeasibleArmAngle(why)
    return _pick(ivs, None if prefer is None else float(prefer))
