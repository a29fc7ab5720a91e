"""Shared driver machinery: time stamps, timeouts, validation, averaging, target checks.

A driver subclasses ``SensorBase`` or ``CommanderBase`` and fills in only the device-specific
``_read_internal`` / ``_move_internal`` parts (python-can's ``recv`` / ``_recv_internal``).
"""

from __future__ import annotations

import inspect
import logging
import math
import time
from typing import Any, Callable, Mapping

import numpy as np

from drivers.errors import DeviceTimeoutError, LimitError, NotReadyError, TargetLostError
from drivers.protocols import JointLimits, JointState, MarkerMeasurement, MarkerSample

Clock = Callable[[], float]


def check_timeout(timeout: float) -> float:
    """Validate a timeout in seconds: finite and positive."""
    if not (isinstance(timeout, (int, float)) and math.isfinite(timeout) and timeout > 0):
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    return float(timeout)


class DeviceBase:
    """Name, logger, monotonic clock and context-manager plumbing for every driver."""

    def __init__(self, name: str, *, clock: Clock = time.monotonic) -> None:
        self.name = name
        self.clock = clock
        self.log = logging.getLogger(f"remaster.device.{name}")

    def connect(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SensorBase(DeviceBase):
    """A ``PositionSensor`` whose subclass implements ``_read_internal``."""

    def read(self, timeout: float) -> list[MarkerSample]:
        samples = self._read_internal(check_timeout(timeout))
        for s in samples:
            if s.visible and not np.all(np.isfinite(s.position_mm)):
                raise ValueError(f"{self.name}: visible marker {s.marker!r} has a non-finite position")
        return samples

    def _read_internal(self, timeout: float) -> list[MarkerSample]:  # pragma: no cover
        raise NotImplementedError

    def measure(self, marker: str, n: int, timeout: float) -> MarkerMeasurement:
        """Average ``n`` visible samples of ``marker``.

        Raises TargetLostError when the marker is reported invisible (the caller decides whether
        to wait, re-acquire or skip) and DeviceTimeoutError when ``n`` samples do not arrive
        within ``timeout`` seconds in total.
        """
        if n < 1:
            raise ValueError(f"n must be at least 1, got {n}")
        timeout = check_timeout(timeout)
        deadline = self.clock() + timeout
        got: list[MarkerSample] = []
        while len(got) < n:
            remaining = deadline - self.clock()
            if remaining <= 0:
                raise DeviceTimeoutError(
                    f"{self.name}: {len(got)} of {n} samples of {marker!r} in {timeout:.3g} s"
                )
            for s in self.read(remaining):
                if s.marker != marker:
                    continue
                if not s.visible:
                    raise TargetLostError(f"{self.name}: marker {marker!r} is not visible")
                got.append(s)
        pos = np.stack([s.position_mm for s in got[:n]])
        rotation, std_deg = mean_rotation([s.rotation for s in got[:n]])
        return MarkerMeasurement(
            marker=marker,
            mean_mm=pos.mean(axis=0),
            std_mm=pos.std(axis=0, ddof=1) if n > 1 else np.zeros(3),
            count=n,
            device_time=got[n - 1].device_time,
            host_time=got[n - 1].host_time,
            rotation=rotation,
            std_deg=std_deg,
        )


def mean_rotation(rotations: list) -> tuple[np.ndarray | None, float | None]:
    """The chordal mean (3, 3) of sample orientations and their per-axis spread (degrees: the
    RMS over axes of each sample's rotation vector against the mean, ddof 1); (None, None) unless
    every sample has one (a point target, or a body that lost its orientation)."""
    if not rotations or any(r is None for r in rotations):
        return None, None
    from calib.robot.transforms import log_so3

    stack = np.stack([np.asarray(r, dtype=float) for r in rotations])
    u, _, vt = np.linalg.svd(stack.sum(axis=0))
    mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    if len(stack) < 2:
        return mean, 0.0
    w = log_so3(stack @ mean.T)
    return mean, float(np.degrees(np.sqrt(np.sum(w ** 2) / (3 * (len(stack) - 1)))))


#: What ``CommanderBase.check_target`` keeps clear of every joint limit unless told otherwise, rad.
DEFAULT_LIMIT_MARGIN_RAD = math.radians(0.5)


def target_window(limits: JointLimits, margin_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """The joint targets a commander accepts: ``(lower + margin, upper - margin)``, each shape
    (n_axes,), radians. One formula for the commander's own check and for plan-time checks, so
    a plan that passes is never refused by the commander for a rounding difference."""
    return (np.asarray(limits.lower_rad, dtype=float) + margin_rad,
            np.asarray(limits.upper_rad, dtype=float) - margin_rad)


class CommanderBase(DeviceBase):
    """A ``JointCommander`` whose subclass implements ``_move_internal`` and ``joint_state``.

    ``max_speed`` is the highest speed fraction the plan allows (0–1]; ``limit_margin_rad`` is
    kept clear of every joint limit; a measured state older than ``max_state_age_s`` is stale.
    ``limit_margin_for(options)`` tells a planner that margin before any commander exists.
    """

    @classmethod
    def limit_margin_for(cls, options: Mapping[str, Any] | None = None) -> float:
        """The margin (rad) a commander of this class built with keyword ``options`` keeps clear
        of every joint limit: ``options["limit_margin_rad"]`` when given, else the default of the
        class's constructor. Lets a plan refuse a target the commander would refuse mid-run."""
        opts = dict(options or {})
        if "limit_margin_rad" in opts:
            value = float(opts["limit_margin_rad"])
        else:
            param = inspect.signature(cls.__init__).parameters.get("limit_margin_rad")
            value = DEFAULT_LIMIT_MARGIN_RAD if param is None or param.default is param.empty else float(param.default)
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{cls.__name__}: limit_margin_rad must be a finite angle ≥ 0 rad, got {value!r}")
        return value

    def __init__(
        self,
        name: str,
        limits: JointLimits,
        *,
        max_speed: float = 1.0,
        limit_margin_rad: float = DEFAULT_LIMIT_MARGIN_RAD,
        max_state_age_s: float = 0.1,
        clock: Clock = time.monotonic,
    ) -> None:
        super().__init__(name, clock=clock)
        if not 0 < max_speed <= 1:
            raise ValueError(f"max_speed must be in (0, 1], got {max_speed}")
        self.limits = limits
        self.max_speed = max_speed
        self.limit_margin_rad = limit_margin_rad
        self.max_state_age_s = max_state_age_s

    def joint_state(self) -> JointState:  # pragma: no cover - overridden
        raise NotImplementedError

    def first_state(self, timeout: float) -> JointState:
        """The measured state once the controller streams (right after ``connect()`` a controller
        may not have sent yet: an FRI robot application opens its session when it is ready);
        DeviceTimeoutError naming the last reason after ``timeout`` seconds (wall time)."""
        deadline = time.monotonic() + check_timeout(timeout)
        while True:
            try:
                return self.joint_state()
            except DeviceTimeoutError:
                if time.monotonic() > deadline:
                    raise
            time.sleep(0.01)

    def check_state(self, state: JointState) -> JointState:
        """Refuse a stale, wrongly sized or non-finite measured state."""
        q = np.asarray(state.position_rad, dtype=float)
        if q.shape != (self.limits.n_axes,):
            raise LimitError(
                f"{self.name}: controller reports {q.shape[0] if q.ndim else 0} axes, "
                f"the robot model has {self.limits.n_axes}"
            )
        if not np.all(np.isfinite(q)):
            raise LimitError(f"{self.name}: measured joint state is not finite: {q}")
        age = self.clock() - state.host_time
        if age > self.max_state_age_s:
            raise NotReadyError(
                f"{self.name}: measured joint state is {age * 1e3:.0f} ms old "
                f"(allowed {self.max_state_age_s * 1e3:.0f} ms); is the controller streaming?"
            )
        return state

    def ready(self) -> JointState:
        """The measured state when a move could start now (the state a move checks, without a
        target); else the reason as NotReadyError (DeviceTimeoutError while nothing arrives). A
        driver adds its own device's conditions (drives, session, a move still ending)."""
        return self.check_state(self.joint_state())

    def check_target(self, target_rad: np.ndarray, speed: float) -> np.ndarray:
        """Validate a move before anything moves; returns the target as a float array."""
        t = np.asarray(target_rad, dtype=float)
        lim = self.limits
        if t.shape != (lim.n_axes,):
            raise LimitError(f"{self.name}: target has shape {t.shape}, expected ({lim.n_axes},)")
        if not np.all(np.isfinite(t)):
            raise LimitError(f"{self.name}: target is not finite: {t}")
        if not (isinstance(speed, (int, float)) and 0 < speed <= self.max_speed):
            raise LimitError(
                f"{self.name}: speed {speed!r} is not allowed; the plan allows (0, {self.max_speed}]"
            )
        lo, hi = target_window(lim, self.limit_margin_rad)
        bad = np.flatnonzero((t < lo) | (t > hi))
        if bad.size:
            names = lim.names or tuple(f"J{i + 1}" for i in range(lim.n_axes))
            details = ", ".join(
                f"{names[i]}={math.degrees(t[i]):.3f}° not in "
                f"[{math.degrees(lo[i]):.3f}, {math.degrees(hi[i]):.3f}]°"
                for i in bad
            )
            raise LimitError(f"{self.name}: target outside joint limits (with margin): {details}")
        return t

    def move_to(self, target_rad: np.ndarray, speed: float, timeout: float) -> None:
        target = self.check_target(target_rad, speed)
        timeout = check_timeout(timeout)
        start = self.check_state(self.joint_state())
        self._move_internal(start, target, speed, timeout)

    def _move_internal(
        self, start: JointState, target_rad: np.ndarray, speed: float, timeout: float
    ) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def wait_settled(
        self, tolerance_rad: float, window_s: float, timeout: float, *, poll_s: float = 0.004
    ) -> JointState:
        """Stability-window status (ophyd style): the window restarts whenever any axis leaves
        ``tolerance_rad`` of the window's first reading; rejects a window longer than the timeout."""
        timeout = check_timeout(timeout)
        if window_s >= timeout:
            raise ValueError(f"settle window {window_s} s must be shorter than timeout {timeout} s")
        deadline = self.clock() + timeout
        ref = self.check_state(self.joint_state())
        t0 = ref.host_time
        while True:
            now = self.clock()
            if now > deadline:
                raise DeviceTimeoutError(f"{self.name}: not settled within {timeout:.3g} s")
            state = self.check_state(self.joint_state())
            if np.max(np.abs(state.position_rad - ref.position_rad)) > tolerance_rad:
                ref, t0 = state, state.host_time
            elif state.host_time - t0 >= window_s:
                return state
            self._sleep(poll_s)

    def _sleep(self, dt: float) -> None:
        time.sleep(dt)
