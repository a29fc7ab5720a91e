"""The simulated cell: one truth model that every fake device reads from or writes to.

``SimCell`` holds a robot that is *not* the nominal model — hidden zero-offsets and link
errors applied through ``calib.robot.kinematics.Chain``'s parameter vector, plus a gravity sag the
kinematic model cannot express — together with reference sensors at their true poses, their
noise, and the geometry that hides a marker from a sensor. Fake controllers write the joint
positions (``RobotScene``); fake sensors read noisy marker positions (``MarkerScene``).

The sag model (``Deflection`` in the config). Every link j carries a point mass m_j at the
middle of the segment between the origins of DH frames j−1 and j (from FK), the tool its mass
at ``tool_com_mm`` in the flange frame. Joint i, rotating about z_{i−1} through o_{i−1},
carries the gravity torque of every mass beyond it,

    τ_i = z_{i−1} · Σ_{j ≥ i} (c_j − o_{i−1}) × m_j g          [N·m]

and yields by Δθ_i = k_i τ_i (k_i its compliance, rad/(N·m)), in the DH sense; in the
controller's convention that is Δq_i = sign_i Δθ_i. Torques come from the undeflected pose
(first order: deflections are 1e-4 rad). The sag is zero when the arm hangs vertical (every
lever arm is parallel to g), largest stretched horizontally, and varies with every joint — a
structured error that zero-offsets cannot absorb, like the paper's "unmodelled effects".

Observation of a marker by a sensor: it is visible when (1) it lies in the sensor's field of
view, (2) the sensor lies inside the marker's acceptance cone about the flange z axis, and
(3) no link capsule or obstacle crosses the segment sensor → marker (``drivers.sim.geometry``).
Its position is then ``base2sensor · p`` plus Gaussian noise with per-axis std
``noise_mm + noise_mm_per_m · range``; an invisible marker's position is NaN. Every visible
marker also carries its frame's orientation ``R_sensor←target`` (the flange's, turned by the
marker's ``rpy_deg`` when the model gives one), turned by a random rotation vector with per-axis
std ``attitude_noise_deg``, for 6-DoF targets (a T-Mac on the tracker); a motion-capture rigid
body's orientation is not taken from here but fitted by the fake Motive to its noisy markers.

Units: mm, rad, s; degrees only in the YAML file.
"""

from __future__ import annotations

import logging
import threading
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.robot.kinematics import Chain, joint_frames
from calib.robot.model import RobotModel, load_robot_model
from calib.robot.transforms import apply, euler_zyx_to_matrix, exp_so3, invert
from calib.io.yamlfile import ConfigError
from drivers.errors import LimitError
from drivers.sim import geometry
from drivers.sim.clock import SimClock
from drivers.sim.config import SensorConfig, SimConfig, load_sim_config
from drivers.sim.scene import MarkerObservation

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class SimTruth:
    """The hidden truth of a cell (arrays are read-only).

    offsets_rad: (n,) true zero-offsets, controller convention. params: (P,) the true
    ``Chain`` parameter vector (offsets, d, a, α, β, markers). nominal_params: (P,) the
    model's. base2sensor: per sensor (4, 4), ``p_sensor = base2sensor @ p_base``.
    compliance_rad_per_nm: (n,) the sag model's joint compliances.
    """

    seed: int
    axis_names: tuple[str, ...]
    param_names: tuple[str, ...]
    offsets_rad: np.ndarray
    params: np.ndarray
    nominal_params: np.ndarray
    base2sensor: dict[str, np.ndarray]
    compliance_rad_per_nm: np.ndarray

    @property
    def offsets_deg(self) -> np.ndarray:
        """(n,) true zero-offsets in degrees (controller convention)."""
        return np.degrees(self.offsets_rad)

    @property
    def param_errors(self) -> np.ndarray:
        """(P,) true minus nominal parameter vector (mm / rad)."""
        return self.params - self.nominal_params


@dataclass(frozen=True)
class _Sensor:
    name: str
    kind: str
    base2sensor: np.ndarray  # (4, 4)
    origin: np.ndarray  # (3,) in base
    optical_axis: np.ndarray  # (3,) in base
    markers: np.ndarray  # indices into the tool's markers
    marker_names: tuple[str, ...]
    cones_rad: np.ndarray  # (ms,) acceptance half-angles of those markers
    fov_rad: float
    noise_mm: float
    noise_mm_per_m: float
    rng: np.random.Generator
    rng_lock: threading.Lock
    attitude_noise_rad: float = 0.0
    att_rng: np.random.Generator | None = None  # its own stream: position noise stays as it was


@dataclass(frozen=True)
class _Pose:
    """Noise-free geometry at one or many configurations (leading dims ...)."""

    markers: np.ndarray  # (..., m, 3) base frame, with sag
    normal: np.ndarray  # (..., 3) flange z in base
    flange_rot: np.ndarray  # (..., 3, 3) R_base←flange, with sag
    cap_a: np.ndarray  # (..., c, 3)
    cap_b: np.ndarray  # (..., c, 3)


@dataclass(frozen=True)
class _View:
    """One sensor's noise-free view at one configuration."""

    positions: np.ndarray  # (ms, 3) sensor frame; NaN where invisible
    visible: np.ndarray  # (ms,) bool
    std: np.ndarray  # (ms,) per-axis noise std, mm
    rotations: np.ndarray  # (ms, 3, 3) R_sensor←target of each marker's frame, noise-free


def _rng(seed: int, purpose: str) -> np.random.Generator:
    """An independent stream per purpose, so adding a sensor never changes the robot's truth."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(zlib.crc32(purpose.encode()),)))


def _per_joint(values: list[float] | None, n: int, field: str) -> np.ndarray | None:
    if values is None:
        return None
    if len(values) != n:
        raise ConfigError(f"{field}: {len(values)} values given, the robot has {n} joints (one per joint needed)")
    return np.asarray(values, dtype=float)


class SimCell:
    """A simulated robot cell; implements ``MarkerScene`` and ``RobotScene``.

    ``SimCell(config, *, clock=None)``; ``SimCell.from_yaml(path)`` reads a config file. All
    public methods are thread-safe: fake controllers call ``set_joint_positions`` at their
    cycle rate while fake sensors call ``observe`` from their own threads.
    """

    def __init__(self, config: SimConfig, *, clock: SimClock | None = None, model: RobotModel | None = None) -> None:
        """``model`` overrides loading ``config.robot`` (for tests that build a model in memory)."""
        self.config = config
        self.clock = clock if clock is not None else SimClock()
        self.model = model if model is not None else load_robot_model(config.robot)
        self.chain = Chain(self.model)
        n, m = self.chain.n, self.chain.m
        self._lock = threading.Lock()
        self._cache: tuple[bytes, _Pose, dict[str, _View]] | None = None

        params, offsets = self._draw_truth(config, n, m)
        self._params = params
        self._flange = self.chain.flange
        #: (m, 3, 3) R_flange←target of each tool marker's frame (identity without rpy_deg)
        self._marker_rot = np.stack([
            np.eye(3) if mk.rpy_deg is None
            else euler_zyx_to_matrix(*np.radians([mk.rpy_deg[2], mk.rpy_deg[1], mk.rpy_deg[0]]))
            for mk in self.model.tool.markers])

        dfl = config.deflection
        masses = _per_joint(dfl.link_masses_kg, n, "deflection.link_masses_kg")
        compliance = _per_joint(dfl.compliance_rad_per_nm, n, "deflection.compliance_rad_per_nm")
        # (n+1,) kg: one point mass per link, then the tool's.
        self._masses = np.append(np.zeros(n) if masses is None else masses, dfl.tool_mass_kg)
        self._compliance = np.zeros(n) if compliance is None else compliance
        self._gravity = np.asarray(dfl.gravity_m_s2, dtype=float)
        self._tool_com = np.asarray(dfl.tool_com_mm, dtype=float)
        self._downstream = np.arange(n)[:, None] <= np.arange(n + 1)[None, :]  # (n joints, n+1 masses)

        occ = config.occlusion
        radii = _per_joint(occ.link_radii_mm, n, "occlusion.link_radii_mm")
        self._link_radii = np.zeros(n) if radii is None else radii
        self._obs_a = np.array([o.a_mm for o in occ.obstacles], dtype=float).reshape(-1, 3)
        self._obs_b = np.array([o.b_mm for o in occ.obstacles], dtype=float).reshape(-1, 3)
        self._radii = np.concatenate([self._link_radii, [o.radius_mm for o in occ.obstacles]])

        self._sensors = {s.name: self._make_sensor(s) for s in config.sensors}
        self.truth = SimTruth(
            seed=config.seed,
            axis_names=tuple(self.model.axis_names),
            param_names=tuple(self.chain.param_names),
            offsets_rad=_frozen(offsets),
            params=_frozen(params),
            nominal_params=_frozen(self.chain.nominal.copy()),
            base2sensor={k: _frozen(s.base2sensor) for k, s in self._sensors.items()},
            compliance_rad_per_nm=_frozen(self._compliance.copy()),
        )

        _per_joint(config.controller.mastering_deg, n, "controller.mastering_deg")  # the controller's (SimLaunch)
        q0 = _per_joint(config.initial_joint_positions_deg, n, "initial_joint_positions_deg")
        q0 = np.zeros(n) if q0 is None else np.radians(q0)
        self._q = self._validated_q(q0)
        log.info(
            "simulated cell: %s, sensors %s, seed %d", self.model.name, ", ".join(self._sensors), config.seed
        )

    # --- construction -------------------------------------------------------------------
    @classmethod
    def from_yaml(cls, path: str | Path, *, seed: int | None = None, clock: SimClock | None = None) -> "SimCell":
        """Build a cell from a config file; ``seed`` overrides the file's seed."""
        config = load_sim_config(path)
        if seed is not None:
            if seed < 0:
                raise ValueError(f"seed must be a non-negative integer, got {seed}")
            config = config.model_copy(update={"seed": int(seed)})
        return cls(config, clock=clock)

    def _draw_truth(self, config: SimConfig, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
        truth, seed = config.truth, config.seed
        chain = self.chain
        params = chain.nominal.copy()
        explicit = _per_joint(truth.offsets_deg, n, "truth.offsets_deg")
        if explicit is not None:
            offsets = np.radians(explicit)
        else:
            offsets = np.radians(truth.offset_std_deg) * _rng(seed, "offsets").standard_normal(n)
        params[:n] = offsets
        le = truth.link_errors
        kinds = [
            ("d", le.d_mm, le.d_std_mm, 1.0),
            ("a", le.a_mm, le.a_std_mm, 1.0),
            ("alpha", le.alpha_deg, le.alpha_std_deg, np.pi / 180),
            ("beta", le.beta_deg, le.beta_std_deg if self.model.convention == "mdh" else 0.0, np.pi / 180),
        ]
        for kind, given, std, unit in kinds:
            values = _per_joint(given, n, f"truth.link_errors.{kind}_{'mm' if unit == 1.0 else 'deg'}")
            if values is None:
                values = std * _rng(seed, f"link.{kind}").standard_normal(n)
            params[chain.index(kind)] += values * unit
        ms = chain.marker_slice()
        params[ms] += truth.marker_std_mm * _rng(seed, "markers").standard_normal(3 * m)
        return params, offsets

    def _make_sensor(self, s: SensorConfig) -> _Sensor:
        if s.frame is not None:
            sensor2base = s.frame.matrix()
        else:
            try:
                sensor2base = geometry.look_at_frame(np.array(s.origin_mm), np.array(s.look_at_mm))
            except ValueError as exc:
                raise ConfigError(f"sensors.{s.name}: {exc}") from None
        tool = self.model.tool.markers
        names = self.model.marker_names
        if s.markers is not None:
            unknown = [x for x in s.markers if x not in names]
            if unknown:
                raise ConfigError(f"sensors.{s.name}.markers: unknown markers {unknown}; the tool has {names}")
            idx = [names.index(x) for x in s.markers]
        else:
            kinds = {"mocap": ("infrared", "other"), "tracker": ("retroreflector",)}[s.kind]
            idx = [i for i, mk in enumerate(tool) if mk.kind in kinds]
            if not idx:
                raise ConfigError(
                    f"sensors.{s.name}: the tool has no {' or '.join(kinds)} marker for a {s.kind}; "
                    f"list the markers it measures (tool markers: {names})"
                )
        cones = self.config.cones_deg
        return _Sensor(
            name=s.name,
            kind=s.kind,
            base2sensor=invert(sensor2base),
            origin=sensor2base[:3, 3].copy(),
            optical_axis=sensor2base[:3, 2].copy(),
            markers=np.array(idx),
            marker_names=tuple(names[i] for i in idx),
            cones_rad=np.radians([getattr(cones, tool[i].kind) for i in idx]),
            fov_rad=float(np.radians(s.field_of_view_deg)),
            noise_mm=s.noise_mm,
            noise_mm_per_m=s.noise_mm_per_m,
            rng=_rng(self.config.seed, f"noise.{s.name}"),
            rng_lock=threading.Lock(),
            attitude_noise_rad=float(np.radians(s.attitude_noise_deg)),
            att_rng=_rng(self.config.seed, f"attitude.{s.name}"),
        )

    # --- names --------------------------------------------------------------------------
    @property
    def sensor_names(self) -> list[str]:
        return list(self._sensors)

    @property
    def marker_names(self) -> list[str]:
        """Every marker of the tool, in the model's order."""
        return list(self.chain.marker_names)

    def sensor_markers(self, sensor: str) -> list[str]:
        """The markers ``sensor`` measures, in the order ``observe`` returns them."""
        return list(self._sensor(sensor).marker_names)

    def _sensor(self, name: str) -> _Sensor:
        try:
            return self._sensors[name]
        except KeyError:
            raise ValueError(f"unknown sensor {name!r}; this cell has {self.sensor_names}") from None

    # --- RobotScene ---------------------------------------------------------------------
    def _validated_q(self, q_rad: np.ndarray) -> np.ndarray:
        q = np.array(q_rad, dtype=float).reshape(-1) if np.ndim(q_rad) <= 1 else None
        if q is None or q.shape != (self.chain.n,):
            raise ValueError(f"joint positions must have shape ({self.chain.n},), got {np.shape(q_rad)}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"joint positions must be finite, got {q.tolist()}")
        margin = np.radians(self.config.end_stop_margin_deg)
        lo, hi = self.model.lower_limits_rad - margin, self.model.upper_limits_rad + margin
        bad = (q < lo) | (q > hi)
        if np.any(bad):
            axes = [
                f"{ax} {np.degrees(v):.3f}° not in [{np.degrees(a):.1f}, {np.degrees(b):.1f}]"
                for ax, v, a, b, x in zip(self.model.axis_names, q, lo, hi, bad)
                if x
            ]
            raise LimitError(
                f"joint positions beyond the mechanical end stops (limits ± {self.config.end_stop_margin_deg}°): "
                + "; ".join(axes)
            )
        return q

    def set_joint_positions(self, q_rad: np.ndarray) -> None:
        """The robot's actual joint positions now, controller convention, rad, shape (n,).

        Raises ValueError for a wrong shape or non-finite values, ``LimitError`` beyond the end
        stops (the model's limits widened by ``end_stop_margin_deg``, so a servo's overshoot at
        a limit passes; a fake controller must refuse targets outside the limits themselves).
        """
        q = self._validated_q(q_rad)
        with self._lock:
            self._q = q

    def joint_positions(self) -> np.ndarray:
        """A copy of the last positions set (or the initial pose), shape (n,), rad."""
        with self._lock:
            return self._q.copy()

    # --- truth model --------------------------------------------------------------------
    def _qs(self, q_rad: np.ndarray) -> np.ndarray:
        q = np.asarray(q_rad, dtype=float)
        if q.ndim == 0 or q.shape[-1] != self.chain.n:
            raise ValueError(f"joint vectors must have shape (..., {self.chain.n}), got {q.shape}")
        return q

    def gravity_torques(self, q_rad: np.ndarray) -> np.ndarray:
        """Gravity torque on each joint about its axis (DH sense), (..., n) N·m, for q (..., n)."""
        frames = joint_frames(self.chain, self._qs(q_rad), self._params)
        return self._torques(frames)

    def _torques(self, frames: np.ndarray) -> np.ndarray:
        n = self.chain.n
        origins = frames[..., :, :3, 3]  # (..., n+1, 3)
        centres = np.empty(origins.shape[:-2] + (n + 1, 3))
        centres[..., :n, :] = 0.5 * (origins[..., :-1, :] + origins[..., 1:, :])
        flange = frames[..., n, :, :] @ self._flange
        centres[..., n, :] = apply(flange, self._tool_com)
        weights = self._masses[:, None] * self._gravity  # (n+1, 3) N
        lever = centres[..., None, :, :] - origins[..., :n, None, :]  # (..., n, n+1, 3) mm
        moments = geometry.cross(lever, weights) * self._downstream[..., None]  # N·mm
        axes = frames[..., :n, :3, 2]  # z_{i-1}, (..., n, 3)
        return np.einsum("...ij,...ij->...i", moments.sum(axis=-2), axes) / 1000.0

    def deflection(self, q_rad: np.ndarray) -> np.ndarray:
        """Gravity sag of each joint in the controller's convention, (..., n) rad, for q (..., n)."""
        return self.chain.sign * self._compliance * self.gravity_torques(q_rad)

    def _pose(self, q: np.ndarray) -> _Pose:
        """Noise-free geometry with sag at q (..., n)."""
        n = self.chain.n
        if np.any(self._compliance):
            q = q + self.chain.sign * self._compliance * self._torques(joint_frames(self.chain, q, self._params))
        frames = joint_frames(self.chain, q, self._params)
        flange = frames[..., n, :, :] @ self._flange
        mk = self._params[self.chain.marker_slice()].reshape(self.chain.m, 3)
        markers = apply(flange[..., None, :, :], mk)
        origins = frames[..., :, :3, 3]
        cap_a = origins[..., :-1, :]
        cap_b = origins[..., 1:, :].copy()
        # The last link ends flush with the flange face: its axis stops one radius short.
        last_a, face = cap_a[..., -1, :], flange[..., :3, 3]
        span = face - last_a
        length = np.linalg.norm(span, axis=-1, keepdims=True)
        r = self._link_radii[-1]
        cap_b[..., -1, :] = np.where(length > r, face - r * span / np.where(length > 0, length, 1.0), last_a)
        lead = q.shape[:-1]
        if len(self._obs_a):
            cap_a = np.concatenate([cap_a, np.broadcast_to(self._obs_a, lead + self._obs_a.shape)], axis=-2)
            cap_b = np.concatenate([cap_b, np.broadcast_to(self._obs_b, lead + self._obs_b.shape)], axis=-2)
        return _Pose(markers=markers, normal=flange[..., :3, 2], flange_rot=flange[..., :3, :3], cap_a=cap_a, cap_b=cap_b)

    def _visible(self, pose: _Pose, s: _Sensor) -> np.ndarray:
        """(..., ms) bool visibility of the sensor's markers."""
        markers = pose.markers[..., s.markers, :]
        to_sensor = s.origin - markers
        facing = geometry.within_cone(pose.normal[..., None, :], to_sensor, s.cones_rad)
        in_view = geometry.within_cone(s.optical_axis, -to_sensor, s.fov_rad)
        clear = geometry.line_of_sight(s.origin, markers, pose.cap_a, pose.cap_b, self._radii)
        return facing & in_view & clear

    def true_marker_positions(self, q_rad: np.ndarray, frame: str = "base") -> np.ndarray:
        """Noise-free positions of every tool marker, with sag: (..., m, 3) mm for q (..., n) rad.

        ``frame`` is ``"base"`` (robot base) or a sensor name (that sensor's frame).
        """
        pose = self._pose(self._qs(q_rad))
        if frame == "base":
            return pose.markers
        return apply(self._sensor(frame).base2sensor, pose.markers)

    def visibility(self, q_rad: np.ndarray, sensor: str) -> np.ndarray:
        """Whether ``sensor`` sees each of its markers: (..., ms) bool for q (..., n) rad.

        Column order is ``sensor_markers(sensor)``. Noise-free and without side effects, for
        planners and benchmarks.
        """
        s = self._sensor(sensor)
        return self._visible(self._pose(self._qs(q_rad)), s)

    def noise_std_mm(self, sensor: str, range_mm: np.ndarray | float) -> np.ndarray:
        """Per-axis noise std (mm) of ``sensor`` at the given range(s) (mm)."""
        s = self._sensor(sensor)
        return s.noise_mm + s.noise_mm_per_m * np.asarray(range_mm, dtype=float) / 1000.0

    # --- MarkerScene --------------------------------------------------------------------
    def _view(self, s: _Sensor) -> _View:
        q = self.joint_positions()
        key = q.tobytes()
        cache = self._cache
        if cache is None or cache[0] != key:
            cache = (key, self._pose(q), {})
            self._cache = cache
        views = cache[2]
        view = views.get(s.name)
        if view is None:
            pose = cache[1]
            visible = self._visible(pose, s)
            markers = pose.markers[s.markers]
            positions = apply(s.base2sensor, markers)
            positions[~visible] = np.nan
            std = self.noise_std_mm(s.name, np.linalg.norm(markers - s.origin, axis=-1))
            rotations = s.base2sensor[:3, :3] @ pose.flange_rot @ self._marker_rot[s.markers]
            view = _View(positions=positions, visible=visible, std=std, rotations=rotations)
            views[s.name] = view
        return view

    def observe(self, sensor: str) -> list[MarkerObservation]:
        """The sensor's markers as it sees them now: one fresh noisy sample each.

        position_mm (3,) in the sensor frame, mm, NaN when not visible. Order:
        ``sensor_markers(sensor)``. Raises ValueError for an unknown sensor.
        """
        s = self._sensor(sensor)
        view = self._view(s)
        with s.rng_lock:
            noise = s.rng.standard_normal(view.positions.shape)
        positions = view.positions + noise * view.std[:, None]
        with s.rng_lock:
            turn = s.att_rng.standard_normal(positions.shape) * s.attitude_noise_rad
        rotations = exp_so3(turn) @ view.rotations
        return [
            MarkerObservation(name, positions[i], bool(view.visible[i]), rotations[i] if view.visible[i] else None)
            for i, name in enumerate(s.marker_names)
        ]


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a
