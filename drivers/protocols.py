"""The two capability protocols every device driver implements, and the records they return.

Units: positions in millimetres in the *sensor* frame, joint angles in radians in the
*controller's* axis convention (see ``calib.robot.model``), times in seconds.

Every record carries two stamps: ``device_time`` from the device's own clock (seconds, its
epoch is the device's), and ``host_time`` from ``time.monotonic()`` when the host received it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True, slots=True)
class MarkerSample:
    """One marker seen once.

    position_mm: shape (3,), sensor frame, mm. ``visible`` is False for an occluded marker
    (its position is then the last known or NaN and must not be averaged). ``rotation``: for a
    6-DoF target (a rigid body), its frame's orientation (3, 3) ``R_sensor←target`` (rotates
    target-frame vectors into the sensor frame); None for a point.
    """

    marker: str
    position_mm: np.ndarray
    device_time: float
    host_time: float
    visible: bool = True
    std_mm: float | None = None
    residual_mm: float | None = None
    rotation: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class MarkerMeasurement:
    """N samples of one marker averaged while the robot stood still.

    mean_mm, std_mm: shape (3,), sensor frame, mm (std is the per-axis sample spread).
    rotation: for a 6-DoF target, the mean orientation (3, 3) ``R_sensor←target`` (chordal mean);
    std_deg: its per-axis spread (rotation vector of each sample against the mean, RMS over the
    axes, degrees); both None for a point.
    """

    marker: str
    mean_mm: np.ndarray
    std_mm: np.ndarray
    count: int
    device_time: float
    host_time: float
    rotation: np.ndarray | None = None
    std_deg: float | None = None


@dataclass(frozen=True, slots=True)
class JointState:
    """Measured joint positions as the controller reports them.

    position_rad: shape (n_axes,), controller convention, radians.
    """

    position_rad: np.ndarray
    device_time: float
    host_time: float
    commanded_rad: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class JointLimits:
    """What a commander may command, in the controller's convention.

    lower_rad, upper_rad, max_velocity_rad_s, max_acceleration_rad_s2: shape (n_axes,).
    """

    lower_rad: np.ndarray
    upper_rad: np.ndarray
    max_velocity_rad_s: np.ndarray
    max_acceleration_rad_s2: np.ndarray
    names: tuple[str, ...] = field(default=())

    @property
    def n_axes(self) -> int:
        return int(np.asarray(self.lower_rad).shape[0])

    @classmethod
    def from_model(cls, model) -> "JointLimits":
        """Limits of a ``calib.robot.model.RobotModel`` (duck-typed to keep layers one-way)."""
        return cls(
            lower_rad=np.asarray(model.lower_limits_rad, dtype=float),
            upper_rad=np.asarray(model.upper_limits_rad, dtype=float),
            max_velocity_rad_s=np.asarray(model.max_velocity_rad_s, dtype=float),
            max_acceleration_rad_s2=np.asarray(model.max_acceleration_rad_s2, dtype=float),
            names=tuple(model.axis_names),
        )


@dataclass(frozen=True, slots=True)
class LinkStats:
    """Timing of a commander's cyclic exchange, over the last ``window`` cycles.

    period_*: time between controller packets (s). latency_*: packet arrival → answer sent (s).
    late_answers: answers we sent later than one cycle after the packet arrived.
    gaps: cycles missing from the controller's counter sequence. restarts: the controller's
    counter went back. guard_clamps: commands the step guard shortened. delay: the RSI
    controller's last ``Delay`` value (None elsewhere). notes: protocol-specific lines for a
    person (session state, FRI version, ...).
    """

    packets: int
    window: int
    period_mean_s: float
    period_std_s: float
    period_max_s: float
    latency_p50_s: float
    latency_p99_s: float
    latency_max_s: float
    late_answers: int
    gaps: int
    malformed: int
    restarts: int
    guard_clamps: int
    delay: int | None
    realtime: bool
    notes: tuple[str, ...] = ()

    def report(self) -> list[str]:
        """The figures as lines for a person."""
        lines = [
            f"link: {self.packets} packets, cycle {self.period_mean_s * 1e3:.3f} ms "
            f"(jitter σ {self.period_std_s * 1e3:.3f} ms, max {self.period_max_s * 1e3:.3f} ms)",
            f"answers: latency p50 {self.latency_p50_s * 1e6:.0f} µs, p99 {self.latency_p99_s * 1e6:.0f} µs, "
            f"max {self.latency_max_s * 1e6:.0f} µs; late {self.late_answers}, missing cycles {self.gaps}, "
            f"malformed {self.malformed}, controller restarts {self.restarts}",
            f"real-time priority: {'yes' if self.realtime else 'no (see log)'}",
        ]
        return lines + list(self.notes)


@runtime_checkable
class PositionSensor(Protocol):
    """Streams marker positions (mm, sensor frame)."""

    name: str

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def marker_names(self) -> list[str]:
        """Markers this sensor can report, by the names the plan uses."""
        ...

    def read(self, timeout: float) -> list[MarkerSample]:
        """The next sample of every selected marker (occluded ones with ``visible=False``)."""
        ...

    def measure(self, marker: str, n: int, timeout: float) -> MarkerMeasurement:
        """Average ``n`` visible samples of one marker; raise TargetLostError if it vanishes."""
        ...


@runtime_checkable
class JointCommander(Protocol):
    """Streams measured joint positions and moves the robot safely to joint targets.

    Optional: ``ready() -> JointState`` — the measured state when a move could start now, else
    ``NotReadyError`` saying why (``CommanderBase`` has one; a run waiting out a device fault
    probes it, falling back to ``joint_state()``). A refusal that may clear by itself (drives
    off, session not commanding, stale state) is a ``NotReadyError``, a ``LimitError`` subclass.
    """

    name: str
    limits: JointLimits

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def joint_state(self) -> JointState:
        """The latest measured state; raise DeviceTimeoutError if it is stale."""
        ...

    def move_to(self, target_rad: np.ndarray, speed: float, timeout: float) -> None:
        """Move to ``target_rad`` (controller convention) at ``speed`` (0–1 of the model's
        limits) and return once the trajectory has been commanded to its end. Refuse with
        LimitError before anything moves if the target or speed is not allowed."""
        ...

    def wait_settled(self, tolerance_rad: float, window_s: float, timeout: float) -> JointState:
        """Return once the measured position has held within ``tolerance_rad`` for
        ``window_s``; raise DeviceTimeoutError after ``timeout``."""
        ...

    def stop(self) -> None:
        """Decelerate within limits and hold."""
        ...


@dataclass(frozen=True, slots=True)
class JointCapture:
    """Joint angles recorded by a joint sensor (e.g. a ball held in a socket).

    mean_rad, std_rad: shape (n_axes,), controller convention, radians, over ``count`` states.
    trigger: what ended the wait — ``"still"`` (the robot was guided away from its commanded
    position and then held still for the settling window), ``"confirm"`` (the operator: a key,
    the daemon's control call) or ``"input"`` (the operator pressed a controller input).
    """

    label: str
    mean_rad: np.ndarray
    std_rad: np.ndarray
    count: int
    trigger: str
    device_time: float
    host_time: float


@runtime_checkable
class DigitalInputs(Protocol):
    """A commander that also reads the controller's digital inputs (e.g. a button on the flange)."""

    def digital_input(self, name: str) -> bool:
        """Whether input ``name`` is set now; DeviceTimeoutError when the controller's state is stale."""
        ...


@runtime_checkable
class JointSensor(Protocol):
    """Records the robot's joint angles when a condition holds (the operator's confirmation, the
    robot held still after hand-guiding) instead of measuring marker positions. It reads the
    run's commander (``attach``)."""

    name: str

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def attach(self, commander: "JointCommander") -> None:
        """The commander whose ``joint_state`` stream the sensor reads."""
        ...

    def capture(self, label: str, n: int, timeout: float) -> JointCapture:
        """Wait for the trigger at ``label`` (what the operator is asked to do), then average
        ``n`` joint states; DeviceTimeoutError after ``timeout`` seconds."""
        ...
