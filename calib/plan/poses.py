"""The remastering pose plan: Latin-hypercube poses aimed at the sensor, every IK solution of each.

Method (remastering seed, section III.A, eqs. 1–5, and III.B):

1. A seeded Latin hypercube draws ``n`` points in four dimensions
   {base angle ``Rθz``, radius ``r``, height ``Rz``, tool roll ``Tθz``}, each scaled to the user's
   range (the paper: angle 0–2π, radius 200–500 mm, height 400–800 mm, roll 0–2π). Angle and
   radius are polar coordinates in the base X–Y plane: ``x = r cos θ``, ``y = r sin θ``.
2. The flange z-axis points from the pose's position at the sensor origin (eq. 2),
   ``z = (p_sensor − p) / ‖p_sensor − p‖``; ``x = z × Z_base`` (eq. 3), with a fallback axis
   (base X) where z and Z_base are (nearly) parallel; ``y = z × x`` (eq. 4); then the extra roll
   ``Tθz`` about the new z (eq. 5): ``R ← R · Rz(Tθz)``. ZYX Euler angles (yaw, pitch, roll —
   KUKA's A, B, C) are reported for each pose.
3. Every inverse-kinematics solution of each pose (``calib.ik.ik.solve_all``; for a 7R arm at the
   arm angle ``calib.ik.ik.pick_arm_angle`` chooses, and optionally at further arm angles), kept
   only inside the joint limits (minus an optional margin) and only when forward kinematics
   reproduces the pose. Whole turns of a joint are used to bring an angle inside its limits,
   but whole-turn twins of one configuration are planned once by default: they have the same
   forward kinematics for every parameter vector, so they add motion and no information.
   A pose with fewer than ``min_solutions`` (default 2) feasible
   configurations is dropped, with the reason.

Everything is seeded: the same robot, sensor origin, ranges, ``n`` and seed give the same plan.
Units inside: mm and radians; degrees only in the configurations file.

Configurations file (CSV, UTF-8, written by ``write_configurations``)::

    # remaster configurations v1
    # robot: KUKA KR 6 R900-2
    # seed: 1
    # sensor_origin_mm: 1500.000000,0.000000,500.000000
    # candidates: 60
    # ranges: radius_mm=200.000000,500.000000 height_mm=... angle_deg=... roll_deg=...
    # pose 3: xyz_mm=412.100000,-35.000000,611.200000 zyx_deg=170.200000,-12.500000,33.000000
    config,pose,branch,q1,q2,q3,q4,q5,q6
    0,3,shoulder=front elbow=up wrist=noflip,12.500000,-40.250000,...

* Lines starting with ``#`` are comments; ``key: value`` comments form the header. ``robot``,
  ``seed`` and ``sensor_origin_mm`` (x,y,z in the robot base frame, mm) are required;
  ``# pose i: ...`` lines record each valid pose's flange position (mm) and ZYX Euler angles
  (deg) for people and tools that read the file.
* ``config``: 0-based running number of the configuration in the plan.
* ``pose``: 0-based index of the pose in the seeded candidate list (dropped poses leave gaps).
* ``branch``: the IK branch label (for a 7R arm suffixed ``@ψ=<deg>`` with the arm angle).
* ``q1..qN``: joint angles in degrees, in the controller's convention (as the pendant shows them).
"""

from __future__ import annotations

import csv
import io
import itertools
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, Sequence

import numpy as np
from scipy.stats import qmc

from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel, wrap_to_pi
from calib.robot.transforms import homogeneous, matrix_to_euler_zyx, rot_z, rotation_angle
from calib.io.yamlfile import ConfigError

log = logging.getLogger(__name__)

FILE_MAGIC = "# remaster configurations v1"

#: |z × Z_base| below this means z is (nearly) parallel to the base z-axis: use the fallback.
PARALLEL_TOL = 1e-6


# --- sampling ranges -----------------------------------------------------------------------
@dataclass(frozen=True)
class PoseRanges:
    """The four sampled quantities' ranges [low, high]: mm for radius and height, rad for angles.

    Defaults are the paper's: radius 200–500 mm, height 400–800 mm, base angle and tool roll
    0–2π. ``low == high`` fixes that quantity.
    """

    radius_mm: tuple[float, float] = (200.0, 500.0)
    height_mm: tuple[float, float] = (400.0, 800.0)
    angle_rad: tuple[float, float] = (0.0, 2.0 * math.pi)
    roll_rad: tuple[float, float] = (0.0, 2.0 * math.pi)

    def __post_init__(self) -> None:
        for name in ("radius_mm", "height_mm", "angle_rad", "roll_rad"):
            value = getattr(self, name)
            if len(value) != 2:
                raise ValueError(f"{name} must be (low, high), got {value!r}")
            lo, hi = float(value[0]), float(value[1])
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"{name} must be finite, got {value!r}")
            if lo > hi:
                raise ValueError(f"{name}: low {lo} must not exceed high {hi}")
            object.__setattr__(self, name, (lo, hi))
        if self.radius_mm[0] < 0:
            raise ValueError(f"radius_mm must be ≥ 0 (a radius), got {self.radius_mm!r}")

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds (4,) in sample order (angle, radius, height, roll)."""
        order = (self.angle_rad, self.radius_mm, self.height_mm, self.roll_rad)
        return np.array([o[0] for o in order]), np.array([o[1] for o in order])


def latin_hypercube(n: int, ranges: PoseRanges, seed: int) -> np.ndarray:
    """``n`` seeded Latin-hypercube samples (n, 4): base angle rad, radius mm, height mm, roll rad."""
    if int(n) != n or n < 1:
        raise ValueError(f"number of candidate poses must be a positive integer, got {n!r}")
    unit = qmc.LatinHypercube(d=4, rng=np.random.default_rng(seed)).random(int(n))
    lo, hi = ranges.bounds()
    return lo + unit * (hi - lo)


def aim_rotations(
    positions_mm: np.ndarray,
    sensor_origin_mm: np.ndarray,
    roll_rad: np.ndarray,
    *,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    fallback: Sequence[float] = (1.0, 0.0, 0.0),
) -> np.ndarray:
    """Rotations (k, 3, 3) whose z-axis points from each position at the sensor (eqs. 2–5).

    positions_mm (k, 3) and sensor_origin_mm (3,) in the robot base frame; roll_rad (k,) is the
    extra rotation about the new z. ``x = z × up`` (eq. 3), or ``z × fallback`` where z is within
    ``PARALLEL_TOL`` of ±up. Raises ValueError if a position coincides with the sensor origin.
    """
    p = np.atleast_2d(np.asarray(positions_mm, dtype=float))
    s = np.asarray(sensor_origin_mm, dtype=float).reshape(3)
    roll = np.broadcast_to(np.asarray(roll_rad, dtype=float), p.shape[:1])
    to_sensor = s - p
    dist = np.linalg.norm(to_sensor, axis=-1)
    if np.any(dist < 1e-9):
        bad = np.flatnonzero(dist < 1e-9).tolist()
        raise ValueError(f"pose positions {bad} coincide with the sensor origin {s.tolist()}: no aiming direction")
    z = to_sensor / dist[:, None]
    x = np.cross(z, np.asarray(up, dtype=float))
    xn = np.linalg.norm(x, axis=-1)
    parallel = xn < PARALLEL_TOL
    if np.any(parallel):
        x_alt = np.cross(z[parallel], np.asarray(fallback, dtype=float))
        if np.any(np.linalg.norm(x_alt, axis=-1) < PARALLEL_TOL):
            raise ValueError(f"the fallback axis {list(fallback)} is parallel to the up axis {list(up)}")
        x[parallel] = x_alt
        xn = np.linalg.norm(x, axis=-1)
    x = x / xn[:, None]
    y = np.cross(z, x)  # eq. 4: right-handed since x ⟂ z
    r = np.stack([x, y, z], axis=-1)  # columns x, y, z
    return r @ rot_z(roll)  # eq. 5


# --- candidate poses -----------------------------------------------------------------------
@dataclass(frozen=True)
class CandidatePoses:
    """The seeded candidate flange poses in the robot base frame.

    samples (n, 4): base angle rad, radius mm, height mm, tool roll rad;
    poses (n, 4, 4) flange frames (mm); xyz_mm (n, 3); zyx_rad (n, 3) yaw, pitch, roll.
    """

    samples: np.ndarray
    poses: np.ndarray
    seed: int
    sensor_origin_mm: np.ndarray
    ranges: PoseRanges

    @property
    def n(self) -> int:
        return len(self.poses)

    @property
    def xyz_mm(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @property
    def zyx_rad(self) -> np.ndarray:
        return matrix_to_euler_zyx(self.poses[:, :3, :3])


def _sensor_origin(sensor_origin_mm: Sequence[float] | np.ndarray) -> np.ndarray:
    try:
        s = np.asarray(sensor_origin_mm, dtype=float)
    except (TypeError, ValueError):
        s = np.zeros(0)
    if s.shape != (3,) or not np.all(np.isfinite(s)):
        raise ValueError(f"sensor origin must be three finite numbers x, y, z in mm, got {sensor_origin_mm!r}")
    return s


def candidate_poses(
    n: int, sensor_origin_mm: Sequence[float] | np.ndarray, *, seed: int, ranges: PoseRanges | None = None
) -> CandidatePoses:
    """``n`` seeded candidate flange poses aimed at ``sensor_origin_mm`` (robot base frame, mm).

    Raises ValueError if a sampled position falls on the sensor origin (put the sensor outside
    the sampled volume, as it is physically).
    """
    ranges = ranges or PoseRanges()
    s = _sensor_origin(sensor_origin_mm)
    samples = latin_hypercube(n, ranges, seed)
    angle, radius, height, roll = samples.T
    xyz = np.stack([radius * np.cos(angle), radius * np.sin(angle), height], axis=-1)
    rot = aim_rotations(xyz, s, roll)
    return CandidatePoses(samples=samples, poses=homogeneous(rot, xyz), seed=int(seed), sensor_origin_mm=s, ranges=ranges)


# --- IK interface --------------------------------------------------------------------------
class IkResult(Protocol):
    """What ``calib.ik.ik.solve_all`` returns (``IkSolutions``)."""

    q: np.ndarray
    branch: list[str]
    status: str
    message: str


class IkSolver(Protocol):
    """The part of ``calib.ik.ik`` the plan uses (the module itself satisfies it)."""

    def solve_all(self, model: RobotModel, pose: np.ndarray, **kwargs: Any) -> IkResult: ...

    def pick_arm_angle(self, model: RobotModel, pose: np.ndarray, **kwargs: Any) -> float: ...


def _default_solver() -> IkSolver:
    from calib.ik import ik  # imported on use: the plan's sampling works without it

    return ik  # type: ignore[return-value]


# --- the plan ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Configuration:
    """One joint configuration to visit: candidate pose index, IK branch, q (n,) rad."""

    config: int
    pose: int
    branch: str
    q: np.ndarray


@dataclass(frozen=True)
class DroppedPose:
    """A candidate pose that will not be measured, and why."""

    pose: int
    reason: str


@dataclass(frozen=True)
class PosePlan:
    """Candidates, the poses kept, the poses dropped (with reasons) and the configurations.

    ``valid`` and ``dropped`` index ``candidates``; ``configurations`` are ordered by pose, then
    as the IK returned them. ``q_rad`` stacks them (n_configs, n_joints).
    """

    robot: str
    axis_names: list[str]
    candidates: CandidatePoses
    valid: list[int]
    dropped: list[DroppedPose]
    configurations: list[Configuration]
    arm_angles_rad: dict[int, list[float]] = field(default_factory=dict)

    @property
    def q_rad(self) -> np.ndarray:
        if not self.configurations:
            return np.zeros((0, len(self.axis_names)))
        return np.stack([c.q for c in self.configurations])

    @property
    def valid_poses(self) -> np.ndarray:
        """(n_valid, 4, 4) flange frames of the kept poses."""
        return self.candidates.poses[self.valid]


def _limit_violation(model: RobotModel, q: np.ndarray, margin_rad: float) -> str | None:
    lo, hi = model.lower_limits_rad + margin_rad, model.upper_limits_rad - margin_rad
    for i, ax in enumerate(model.axis_names):
        if q[i] < lo[i] or q[i] > hi[i]:
            return f"{ax}={math.degrees(q[i]):.1f}° outside [{math.degrees(lo[i]):.1f}, {math.degrees(hi[i]):.1f}]°"
    return None


def _same_q(a: np.ndarray, b: np.ndarray, *, modulo_turns: bool, tol: float = 1e-6) -> bool:
    d = a - b
    return bool(np.max(np.abs(wrap_to_pi(d) if modulo_turns else d)) < tol)


def _into_limits(
    model: RobotModel, q: np.ndarray, margin_rad: float, all_turns: bool
) -> list[tuple[str, np.ndarray]]:
    """Whole-turn variants of ``q`` (n,) rad inside the limits shrunk by ``margin_rad``.

    Per joint the angles ``q_j + 2πk`` (|k| ≤ 2) that fit. ``all_turns=False``: one variant,
    each joint at its fitting angle closest to zero (the wrapped angle itself when it fits).
    ``all_turns=True``: every combination, labelled like ``" A6-360"``. Empty when some joint
    fits for no k.
    """
    lo, hi = model.lower_limits_rad + margin_rad, model.upper_limits_rad - margin_rad
    options = []
    for j in range(model.n_joints):
        ks = [k for k in (0, -1, 1, -2, 2) if lo[j] <= q[j] + 2 * math.pi * k <= hi[j]]
        if not ks:
            return []
        ks.sort(key=lambda k: abs(q[j] + 2 * math.pi * k))
        options.append(ks if all_turns else ks[:1])
    out = []
    for combo in itertools.product(*options):
        shifted = q + 2 * math.pi * np.array(combo, dtype=float)
        suffix = "".join(f" {model.axis_names[j]}{360 * k:+d}" for j, k in enumerate(combo) if k and all_turns)
        out.append((suffix, shifted))
    return out


def plan_poses(
    model: RobotModel,
    sensor_origin_mm: Sequence[float] | np.ndarray,
    *,
    n: int = 60,
    seed: int = 1,
    ranges: PoseRanges | None = None,
    extra_arm_angles_rad: Sequence[float] = (),
    prefer_arm_angle_rad: float | None = None,
    min_solutions: int = 2,
    limit_margin_rad: float = 0.0,
    whole_turn_twins: bool = False,
    params: np.ndarray | None = None,
    fk_tol_mm: float = 1e-3,
    fk_tol_rad: float = 1e-6,
    solver: IkSolver | None = None,
) -> PosePlan:
    """The paper's pose plan for ``model`` with the sensor at ``sensor_origin_mm`` (base frame).

    Every IK branch of each of the ``n`` seeded candidate poses (asked of the solver with
    ``within_limits=False``, so each branch comes once with wrapped angles) is kept when forward
    kinematics (with ``params``, default nominal) reproduces the pose within ``fk_tol_mm`` /
    ``fk_tol_rad`` and whole turns of its joints can bring it inside the joint limits shrunk by
    ``limit_margin_rad`` (e.g. the KR 6's A2 at 175° becomes −185°). Whole-turn twins of one
    configuration (the KR 6's A6 at 100° and −260°) have the same kinematics for every
    parameter vector, so by default only the one nearest zero is planned;
    ``whole_turn_twins=True`` plans every twin that fits (labels such as ``" A6-360"``).

    For a 7-joint arm the IK runs at ``solver.pick_arm_angle(model, pose,
    prefer=prefer_arm_angle_rad)`` and at each of ``extra_arm_angles_rad`` (absolute arm angles,
    rad); duplicates are removed. Poses with fewer than ``min_solutions`` feasible
    configurations are dropped with the reason.
    """
    if int(min_solutions) != min_solutions or min_solutions < 1:
        raise ValueError(f"min_solutions must be a positive integer, got {min_solutions!r}")
    if limit_margin_rad < 0:
        raise ValueError(f"limit_margin_rad must be ≥ 0, got {limit_margin_rad!r}")
    solver = solver or _default_solver()
    cands = candidate_poses(n, sensor_origin_mm, seed=seed, ranges=ranges)
    chain = Chain(model)
    redundant = model.n_joints == 7
    if extra_arm_angles_rad and not redundant:
        raise ValueError(f"arm angles apply to 7-joint arms; {model.name} has {model.n_joints} joints")

    valid: list[int] = []
    dropped: list[DroppedPose] = []
    configs: list[Configuration] = []
    arm_angles: dict[int, list[float]] = {}
    for k in range(cands.n):
        pose = cands.poses[k]
        runs: list[tuple[float | None, IkResult]] = []
        failures: list[str] = []
        if redundant:
            psis = []
            try:
                psis.append(float(solver.pick_arm_angle(model, pose, prefer=prefer_arm_angle_rad, params=params)))
            except ValueError as exc:  # calib.ik.ik.NoFeasibleArmAngle
                failures.append(f"no arm angle: {exc}")
            psis += [float(p) for p in extra_arm_angles_rad]
            arm_angles[k] = psis
            for psi in psis:
                runs.append((psi, solver.solve_all(model, pose, arm_angle=psi, within_limits=False, params=params)))
        else:
            runs.append((None, solver.solve_all(model, pose, within_limits=False, params=params)))

        kept: list[tuple[str, np.ndarray]] = []
        n_found, outside, off_pose, duplicates = 0, [], 0, 0
        for psi, sol in runs:
            q_all = np.asarray(sol.q, dtype=float).reshape(-1, model.n_joints)
            if len(q_all) == 0:
                failures.append(f"{sol.status}: {sol.message}" if sol.message else sol.status)
                continue
            n_found += len(q_all)
            t = chain.fk(q_all, params)
            dp = np.linalg.norm(t[:, :3, 3] - pose[:3, 3], axis=-1)
            dr = rotation_angle(np.swapaxes(t[:, :3, :3], -1, -2) @ pose[:3, :3])
            for q, label, e_p, e_r in zip(q_all, sol.branch, dp, dr):
                if e_p > fk_tol_mm or e_r > fk_tol_rad:
                    off_pose += 1
                    log.warning("pose %d: IK branch %s misses the pose by %.3g mm / %.3g rad; not used", k, label, e_p, e_r)
                    continue
                variants = _into_limits(model, q, limit_margin_rad, whole_turn_twins)
                if not variants:
                    outside.append(f"{label}: {_limit_violation(model, q, limit_margin_rad)}")
                    continue
                for suffix, qv in variants:
                    if any(_same_q(qv, other, modulo_turns=not whole_turn_twins) for _, other in kept):
                        duplicates += 1
                        continue
                    name = label + suffix if psi is None else f"{label}{suffix}@ψ={math.degrees(psi):.1f}"
                    kept.append((name, qv))

        if len(kept) >= min_solutions:
            valid.append(k)
            for name, q in kept:
                configs.append(Configuration(config=len(configs), pose=k, branch=name, q=q))
            continue
        if n_found == 0:
            reason = "no feasible IK solution (" + "; ".join(dict.fromkeys(failures)) + ")"
        else:
            parts = [f"{len(kept)} feasible of {n_found} IK solutions (need ≥ {min_solutions})"]
            if outside:
                parts.append(f"{len(outside)} outside joint limits: " + ", ".join(outside))
            if off_pose:
                parts.append(f"{off_pose} failed the FK check")
            if duplicates:
                parts.append(f"{duplicates} duplicates (equal up to whole turns)")
            reason = "; ".join(parts)
        dropped.append(DroppedPose(pose=k, reason=reason))
        log.debug("pose %d dropped: %s", k, reason)

    log.info(
        "pose plan for %s: %d candidates, %d valid, %d dropped, %d configurations",
        model.name, cands.n, len(valid), len(dropped), len(configs),
    )
    return PosePlan(
        robot=model.name,
        axis_names=model.axis_names,
        candidates=cands,
        valid=valid,
        dropped=dropped,
        configurations=configs,
        arm_angles_rad=arm_angles,
    )


# --- configurations file -------------------------------------------------------------------
@dataclass(frozen=True)
class ConfigurationsFile:
    """A configurations file's content: header values and rows (q in rad)."""

    robot: str
    seed: int
    sensor_origin_mm: np.ndarray
    configurations: list[Configuration]
    header: dict[str, str]

    @property
    def q_rad(self) -> np.ndarray:
        if not self.configurations:
            return np.zeros((0, 0))
        return np.stack([c.q for c in self.configurations])


def _fmt(values: Sequence[float]) -> str:
    return ",".join(f"{v:.6f}" for v in values)


def format_configurations(plan: PosePlan) -> str:
    """The configurations file's text for ``plan`` (format in the module docstring)."""
    out = io.StringIO()
    c = plan.candidates
    out.write(FILE_MAGIC + "\n")
    out.write(f"# robot: {plan.robot}\n")
    out.write(f"# seed: {c.seed}\n")
    out.write(f"# sensor_origin_mm: {_fmt(c.sensor_origin_mm)}\n")
    out.write(f"# candidates: {c.n}\n")
    r = c.ranges
    out.write(
        f"# ranges: radius_mm={_fmt(r.radius_mm)} height_mm={_fmt(r.height_mm)} "
        f"angle_deg={_fmt(np.degrees(r.angle_rad))} roll_deg={_fmt(np.degrees(r.roll_rad))}\n"
    )
    xyz, zyx = c.xyz_mm, np.degrees(c.zyx_rad)
    for k in plan.valid:
        out.write(f"# pose {k}: xyz_mm={_fmt(xyz[k])} zyx_deg={_fmt(zyx[k])}\n")
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["config", "pose", "branch"] + [f"q{i + 1}" for i in range(len(plan.axis_names))])
    for cfg in plan.configurations:
        writer.writerow([cfg.config, cfg.pose, cfg.branch] + [f"{v:.6f}" for v in np.degrees(cfg.q)])
    return out.getvalue()


def write_configurations(plan: PosePlan, path: str | Path) -> Path:
    """Write ``plan``'s configurations file to ``path``; returns the path."""
    path = Path(path)
    try:
        path.write_text(format_configurations(plan), encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write: {exc.strerror or exc}") from exc
    log.info("wrote %d configurations to %s", len(plan.configurations), path)
    return path


def read_configurations(path: str | Path, model: RobotModel | None = None) -> ConfigurationsFile:
    """Read a configurations file; q in radians.

    With ``model`` the joint count must match and every configuration must lie inside the
    model's joint limits. Raises ``ConfigError`` (a ValueError) naming ``path:line`` and the
    problem.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    header: dict[str, str] = {}
    rows: list[tuple[int, str]] = []
    for no, line in enumerate(lines, start=1):
        if line.startswith("#"):
            body = line[1:].strip()
            key, sep, value = body.partition(":")
            if sep and " " not in key.strip():
                header[key.strip()] = value.strip()
        elif line.strip():
            rows.append((no, line))

    def fail(no: int | None, msg: str) -> ConfigError:
        return ConfigError(f"{path}:{no}: {msg}" if no else f"{path}: {msg}")

    for key in ("robot", "seed", "sensor_origin_mm"):
        if key not in header:
            raise fail(None, f"missing header comment '# {key}: ...' (required: robot, seed, sensor_origin_mm)")
    try:
        seed = int(header["seed"])
    except ValueError:
        raise fail(None, f"seed must be an integer, given {header['seed']!r}") from None
    try:
        origin = np.array([float(v) for v in header["sensor_origin_mm"].split(",")])
    except ValueError:
        origin = np.zeros(0)
    if origin.shape != (3,):
        raise fail(None, f"sensor_origin_mm must be x,y,z in mm, given {header['sensor_origin_mm']!r}")
    if model is not None and header["robot"] != model.name:
        log.warning("%s was planned for %r, checking against %r", path, header["robot"], model.name)
    if not rows:
        raise fail(None, "no column header 'config,pose,branch,q1..qN' found")

    head_no, head_line = rows[0]
    cols = next(csv.reader([head_line]))
    n_q = len(cols) - 3
    expected = ["config", "pose", "branch"] + [f"q{i + 1}" for i in range(max(n_q, 0))]
    if n_q < 1 or cols != expected:
        raise fail(head_no, f"column header must be config,pose,branch,q1..qN, given {head_line!r}")
    if model is not None and n_q != model.n_joints:
        raise fail(head_no, f"file has {n_q} joint columns, {model.name} has {model.n_joints} joints")

    configs: list[Configuration] = []
    for no, line in rows[1:]:
        fields = next(csv.reader([line]))
        if len(fields) != len(cols):
            raise fail(no, f"expected {len(cols)} fields, given {len(fields)}: {line!r}")
        try:
            cfg_no, pose_no = int(fields[0]), int(fields[1])
        except ValueError:
            raise fail(no, f"config and pose must be integers, given {fields[0]!r}, {fields[1]!r}") from None
        try:
            q_deg = np.array([float(v) for v in fields[3:]])
        except ValueError:
            raise fail(no, f"joint angles must be numbers in degrees, given {fields[3:]!r}") from None
        if not np.all(np.isfinite(q_deg)):
            raise fail(no, f"joint angles must be finite, given {fields[3:]!r}")
        q = np.radians(q_deg)
        if model is not None:
            why = _limit_violation(model, q, 0.0)
            if why is not None:
                raise fail(no, f"configuration {cfg_no} is outside the joint limits: {why}")
        configs.append(Configuration(config=cfg_no, pose=pose_no, branch=fields[2], q=q))
    return ConfigurationsFile(
        robot=header["robot"], seed=seed, sensor_origin_mm=origin, configurations=configs, header=header
    )
