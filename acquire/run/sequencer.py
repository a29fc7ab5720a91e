"""The sequencer: which configuration comes next, and what happens at each one.

Ordering (``order_configurations``): the cost of going from one configuration to another is the
duration of the commander's synchronised jerk-limited move under the plan's speed override
(``drivers.trajectory.motion_time`` on ``scaled_limits``) — the slowest axis decides, not the
joint-space distance. A nearest-neighbour tour from the robot's current position is improved by
2-opt (segment reversals of the open path; the start stays fixed) until no reversal shortens it.
``order_by_pose_proximity`` is the paper's procedure (Cartesian poses in nearest-neighbour
order, all configurations of a pose in a row); ``order_by_proximity`` is nearest neighbour in
joint-space distance.

Per configuration (``ConfigProcedure.run``): move (``commander.move_to``; a refusal is fatal
for that configuration, with its reason); wait until settled (``acquire.run.settle.wait_settled``:
robot still AND sensors stable over a window); measure N samples of every marker of every
sensor while sampling the measured joint angles (mean and std over the measurement window);
return the sample record of ``RUN_API.md``. A lost target raises ``TargetLostError`` out of
``settle_and_measure`` so the run can suspend at this configuration and re-measure it.

Units: radians and seconds inside; the record carries degrees (file boundary) and mm.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from acquire.run.settle import SettleResult, wait_settled
from drivers.errors import DeviceTimeoutError
from drivers.trajectory import motion_time, scaled_limits

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ ordering
def _q_matrix(configs) -> np.ndarray:
    return np.array([np.asarray(c.q_rad, dtype=float) for c in configs]).reshape(len(configs), -1)


def motion_cost_matrix(points_rad: np.ndarray, limits, speed: float) -> np.ndarray:
    """Move durations (s) between every pair of joint vectors.

    points_rad: (k, n) rad. Returns (k, k), symmetric, zero diagonal, in seconds at ``speed``.
    """
    v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed)
    p = np.asarray(points_rad, dtype=float)
    return np.asarray(motion_time(p[:, None, :], p[None, :, :], v, a, j), dtype=float)


def _nearest_neighbour(cost: np.ndarray) -> list[int]:
    """Open path from node 0 visiting every node, always to the cheapest unvisited one."""
    k = cost.shape[0]
    left = np.ones(k, dtype=bool)
    left[0] = False
    path = [0]
    for _ in range(k - 1):
        row = np.where(left, cost[path[-1]], np.inf)
        nxt = int(np.argmin(row))
        path.append(nxt)
        left[nxt] = False
    return path


def _two_opt(path: list[int], cost: np.ndarray, max_passes: int = 50) -> list[int]:
    """2-opt on an open path whose first node is fixed: reverse path[i..j] while that helps."""
    p = np.array(path)
    k = len(p)
    if k < 4:
        return list(p)
    for _ in range(max_passes):
        improved = False
        for i in range(1, k - 1):
            a = p[i - 1]
            js = np.arange(i + 1, k)
            b, c = p[i], p[js]
            after = np.append(p[js[:-1] + 1], -1)  # node after j (none at the end)
            old = cost[a, b] + np.where(after >= 0, cost[c, np.maximum(after, 0)], 0.0)
            new = cost[a, c] + np.where(after >= 0, cost[b, np.maximum(after, 0)], 0.0)
            gain = old - new
            best = int(np.argmax(gain))
            if gain[best] > 1e-9:
                j = int(js[best])
                p[i : j + 1] = p[i : j + 1][::-1].copy()
                improved = True
        if not improved:
            break
    return list(p)


def order_configurations(configs, start_q_rad, limits, speed) -> list:
    """Order ``configs`` (PlannedConfig-like, ``q_rad`` (n,)) for minimum total motion time
    from ``start_q_rad`` (n,) rad under ``limits`` (JointLimits) at ``speed`` in (0, 1].

    Deterministic: nearest neighbour by move duration, then 2-opt. Returns a new list.
    """
    configs = list(configs)
    if len(configs) <= 1:
        return configs
    pts = np.vstack([np.asarray(start_q_rad, dtype=float).reshape(1, -1), _q_matrix(configs)])
    cost = motion_cost_matrix(pts, limits, speed)
    path = _two_opt(_nearest_neighbour(cost), cost)
    return [configs[i - 1] for i in path[1:]]


def order_by_proximity(configs, start_q_rad) -> list:
    """The paper's baseline order: nearest neighbour by joint-space (Euclidean) distance."""
    configs = list(configs)
    if len(configs) <= 1:
        return configs
    pts = np.vstack([np.asarray(start_q_rad, dtype=float).reshape(1, -1), _q_matrix(configs)])
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    return [configs[i - 1] for i in _nearest_neighbour(dist)[1:]]


def order_by_pose_proximity(configs, start_q_rad, chain) -> list:
    """The paper's procedure: Cartesian poses "ordered based on proximity to current pose" —
    nearest neighbour over poses by flange position (mm, nominal ``chain.fk``), every
    configuration of a pose in a row in the order given. Configurations without a pose id
    are their own pose."""
    configs = list(configs)
    if len(configs) <= 1:
        return configs
    groups: dict[str, list] = {}
    for i, c in enumerate(configs):
        groups.setdefault(c.pose or f"#{i}", []).append(c)
    names = list(groups)
    xyz = np.array([chain.fk(np.asarray(groups[g][0].q_rad, dtype=float))[:3, 3] for g in names])
    here = chain.fk(np.asarray(start_q_rad, dtype=float))[:3, 3]
    pts = np.vstack([here[None, :], xyz])
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    return [c for i in _nearest_neighbour(dist)[1:] for c in groups[names[i - 1]]]


def move_times(configs, start_q_rad, limits, speed) -> np.ndarray:
    """(k,) duration (s) of each move of the sequence, the first from ``start_q_rad``."""
    if not configs:
        return np.zeros(0)
    pts = np.vstack([np.asarray(start_q_rad, dtype=float).reshape(1, -1), _q_matrix(configs)])
    v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed)
    return np.asarray(motion_time(pts[:-1], pts[1:], v, a, j), dtype=float).reshape(-1)


@dataclass(frozen=True)
class CellTimeEstimate:
    """Estimated cell time of a sequence (s): motion + settle + measure, per config arrays (k,)."""

    motion_s: np.ndarray
    settle_s: float
    measure_s: float

    @property
    def per_config_s(self) -> np.ndarray:
        return self.motion_s + self.settle_s + self.measure_s

    @property
    def total_s(self) -> float:
        return float(self.per_config_s.sum())


def estimate_settle_s(window_s: float, servo_settle_s: float = 0.05) -> float:
    """Expected settling time (s): the servo's own settling after the trajectory ends plus one
    window (``wait_settled`` runs the robot's and the sensors' windows at the same time). The
    fake cell settles in ≈ window + 0.02 s (see tests/bench/bench_run.py)."""
    return servo_settle_s + window_s


def estimate_measure_s(samples: int, sensor_rates_hz: Sequence[float]) -> float:
    """Expected measuring time (s): ``samples`` at each sensor's rate, sensors one after another."""
    return float(sum(samples / max(r, 1e-9) for r in sensor_rates_hz))


def estimate_cell_time(configs, start_q_rad, limits, speed, *, settle_s: float, measure_s: float) -> CellTimeEstimate:
    return CellTimeEstimate(move_times(configs, start_q_rad, limits, speed), float(settle_s), float(measure_s))


# ------------------------------------------------------------------------------ per configuration
@dataclass
class SensorSpec:
    """A connected sensor with the plan markers it measures and its expected noise (mm)."""

    sensor: object
    markers: list[str]
    noise_mm: float = 0.0


@dataclass
class SequencingSettings:
    """The plan's ``sequencing`` section in SI units (rad, s, mm)."""

    speed: float
    settle_window_s: float
    settle_tolerance_rad: float
    sensor_stable_mm: float
    samples: int
    move_timeout_s: float
    measure_timeout_s: float
    retries: int = 1
    robot_fault_wait_s: float = 30.0
    sensor_fault_wait_s: float = 30.0


class JointSampler:
    """Samples ``commander.joint_state()`` on its own thread between ``start`` and ``stop``.

    ``stop`` returns (mean (n,), std (n,), count) of the measured positions, rad.
    """

    def __init__(self, commander, period_s: float, sleep: Callable[[float], None]) -> None:
        self.commander = commander
        self.period_s = period_s
        self.sleep = sleep
        self._values: list[np.ndarray] = []
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None

    def _take(self) -> None:
        try:
            self._values.append(np.asarray(self.commander.joint_state().position_rad, dtype=float))
        except DeviceTimeoutError as exc:  # a late packet: skip that sample
            log.debug("joint sample skipped: %s", exc)

    def _loop(self) -> None:
        while not self._halt.is_set():
            self._take()
            self.sleep(self.period_s)

    def start(self) -> "JointSampler":
        self._take()
        self._thread = threading.Thread(target=self._loop, name="joint-sampler", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> tuple[np.ndarray, np.ndarray, int]:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._take()
        q = np.array(self._values)
        std = q.std(axis=0, ddof=1) if len(q) > 1 else np.zeros(q.shape[1])
        return q.mean(axis=0), std, len(q)


class ConfigProcedure:
    """Move → settle → measure at one configuration, producing the sample record.

    clock / sleep: the run's time source (simulated seconds under ``--fake``); wall: wall-clock
    stamps for ``t_start`` / ``t_end`` (Unix seconds).
    """

    def __init__(
        self,
        commander,
        sensors: Sequence[SensorSpec],
        settings: SequencingSettings,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        wall: Callable[[], float] = time.time,
        event: Callable[..., None] = lambda kind, **f: None,
        on_reading: Callable[[str, list], None] | None = None,
    ) -> None:
        self.commander = commander
        self.sensors = list(sensors)
        self.settings = settings
        self.clock = clock
        self.sleep = sleep
        self.wall = wall
        self.event = event
        self.on_reading = on_reading

    @property
    def position_sensors(self) -> list[SensorSpec]:
        """Sensors that measure marker positions (settle on them and average their markers)."""
        return [sp for sp in self.sensors if not is_joint_sensor(sp.sensor)]

    @property
    def joint_sensors(self) -> list[SensorSpec]:
        """Joint sensors (``drivers.protocols.JointSensor``): they record the joint angles."""
        return [sp for sp in self.sensors if is_joint_sensor(sp.sensor)]

    def move(self, cfg) -> float:
        """Move to ``cfg.q_rad``; returns the seconds it took. LimitError if refused."""
        t0 = self.clock()
        self.commander.move_to(np.asarray(cfg.q_rad, dtype=float), self.settings.speed, self.settings.move_timeout_s)
        dt = self.clock() - t0
        self.event("moved", config_id=cfg.config_id, seconds=round(dt, 4))
        return dt

    def settle(self, cfg) -> SettleResult:
        s = self.settings
        res = wait_settled(
            self.commander,
            [(sp.sensor, sp.markers, sp.noise_mm) for sp in self.position_sensors],
            tolerance_rad=s.settle_tolerance_rad,
            window_s=s.settle_window_s,
            sensor_stable_mm=s.sensor_stable_mm,
            timeout=s.measure_timeout_s,
            clock=self.clock,
            on_reading=self.on_reading,
        )
        self.event("settled", config_id=cfg.config_id, seconds=round(res.seconds, 4),
                   robot_s=round(res.robot_seconds, 4), sensor_s=round(res.sensor_seconds, 4), restarts=res.restarts)
        return res

    def capture(self, cfg, attempts: int, t_start_wall: float) -> dict:
        """At a socket configuration: the joint sensor records the joint angles once the ball is
        held in the socket; the record carries them as ``q_measured_deg`` and, under ``socket``,
        the placement, socket and what triggered the recording."""
        s = self.settings
        if getattr(cfg, "socket", None) is None:
            raise ValueError(f"{cfg.config_id}: a joint sensor records at socket configurations only "
                             "(the plan needs a socket section)")
        placement, socket = cfg.socket
        (sp,) = self.joint_sensors
        cap = sp.sensor.capture(f"socket {socket} of placement {placement}", s.samples, s.measure_timeout_s)
        self.event("measured", config_id=cfg.config_id, markers=0, trigger=cap.trigger)
        return {
            "config_id": cfg.config_id,
            "pose": cfg.pose,
            "branch": cfg.branch,
            "q_target_deg": np.degrees(np.asarray(cfg.q_rad, dtype=float)).tolist(),
            "q_measured_deg": np.degrees(cap.mean_rad).tolist(),
            "q_measured_std_deg": np.degrees(cap.std_rad).tolist(),
            "markers": [],
            "socket": {"sensor": sp.sensor.name, "placement": placement, "socket": socket, "trigger": cap.trigger,
                       "count": int(cap.count), "device_time": _finite(cap.device_time)},
            "t_start": t_start_wall,
            "t_end": self.wall(),
            "attempts": int(attempts),
        }

    def measure(self, cfg, attempts: int, t_start_wall: float) -> dict:
        """Measure every marker of every sensor; the record of RUN_API.md. With a joint sensor
        (socket calibration) the joint sensor's capture instead (``capture``)."""
        if self.joint_sensors:
            return self.capture(cfg, attempts, t_start_wall)
        s = self.settings
        sampler = JointSampler(self.commander, max(s.settle_window_s / 20, 0.004), self.sleep).start()
        markers = []
        try:
            for sp in self.sensors:
                for m in sp.markers:
                    mm = sp.sensor.measure(m, s.samples, s.measure_timeout_s)
                    markers.append({
                        "sensor": sp.sensor.name, "marker": m,
                        "mean_mm": [float(x) for x in mm.mean_mm], "std_mm": [float(x) for x in mm.std_mm],
                        "count": int(mm.count), "device_time": _finite(mm.device_time),
                        "host_time": _finite(mm.host_time),
                        **_orientation(mm),
                    })
        finally:
            q_mean, q_std, _ = sampler.stop()
        self.event("measured", config_id=cfg.config_id, markers=len(markers))
        return {
            "config_id": cfg.config_id,
            "pose": cfg.pose,
            "branch": cfg.branch,
            "q_target_deg": np.degrees(np.asarray(cfg.q_rad, dtype=float)).tolist(),
            "q_measured_deg": np.degrees(q_mean).tolist(),
            "q_measured_std_deg": np.degrees(q_std).tolist(),
            "markers": markers,
            "t_start": t_start_wall,
            "t_end": self.wall(),
            "attempts": int(attempts),
        }

    def settle_and_measure(self, cfg, attempts: int, t_start_wall: float) -> dict:
        self.settle(cfg)
        return self.measure(cfg, attempts, t_start_wall)


def is_joint_sensor(sensor) -> bool:
    """True for a ``drivers.protocols.JointSensor`` (it records joint angles, not markers)."""
    return callable(getattr(sensor, "capture", None))


def _finite(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _orientation(mm) -> dict:
    """A 6-DoF target's record fields: ``quat_wxyz`` (unit quaternion, scalar first, the mean
    R_sensor←target) and ``std_deg``; nothing for a point target."""
    rotation = getattr(mm, "rotation", None)
    if rotation is None:
        return {}
    from calib.robot.transforms import matrix_to_quat

    out = {"quat_wxyz": [float(x) for x in matrix_to_quat(rotation)]}
    if getattr(mm, "std_deg", None) is not None:
        out["std_deg"] = float(mm.std_deg)
    return out
