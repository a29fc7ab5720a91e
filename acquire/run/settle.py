"""Settling as a status: the robot still AND every sensor's readings stable over a window.

ophyd's stable-subscription idea: a condition must hold for ``window_s`` without a break; the
window restarts whenever a reading leaves the tolerance of the window's reference; a window
longer than the timeout is refused up front. Nothing here sleeps a fixed time.

``StabilityWindow`` is the pure logic (feed it time-stamped vectors); ``wait_settled`` runs it
on a commander (``commander.wait_settled``: robot still) and then on the sensors' readings with
the robot still watched, all on an injected clock (simulated seconds under ``--fake``).

Units: joint angles rad, positions mm, times s.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from drivers.base import check_timeout
from drivers.errors import DeviceTimeoutError, TargetLostError

log = logging.getLogger(__name__)


class StabilityWindow:
    """Holds once every reading of a window stays within ``tolerance`` (max-abs per component)
    of the window's running mean, for at least ``window_s`` seconds.

    ``update(t, value)`` returns True once held. A reading outside the tolerance restarts the
    window at that reading (``restarts`` counts them). value: shape (k,), any unit matching
    ``tolerance``.
    """

    def __init__(self, tolerance: float, window_s: float) -> None:
        if not (math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"tolerance must be a positive number, got {tolerance!r}")
        if not (math.isfinite(window_s) and window_s >= 0):
            raise ValueError(f"window_s must be a non-negative number of seconds, got {window_s!r}")
        self.tolerance = float(tolerance)
        self.window_s = float(window_s)
        self.restarts = 0
        self._t0: float | None = None
        self._sum: np.ndarray | None = None
        self._n = 0

    def reset(self) -> None:
        self._t0, self._sum, self._n = None, None, 0

    @property
    def mean(self) -> np.ndarray | None:
        return None if self._sum is None else self._sum / self._n

    def update(self, t: float, value) -> bool:
        v = np.asarray(value, dtype=float).reshape(-1)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"reading is not finite: {v}")
        if self._sum is not None and np.max(np.abs(v - self._sum / self._n)) > self.tolerance:
            self.restarts += 1
            self._t0, self._sum, self._n = None, None, 0
        if self._sum is None:
            self._t0, self._sum, self._n = t, v.copy(), 1
        else:
            self._sum += v
            self._n += 1
        return t - self._t0 >= self.window_s

    def held_for(self, t: float) -> float:
        return 0.0 if self._t0 is None else t - self._t0


@dataclass(frozen=True)
class SettleResult:
    """How settling went: seconds spent (clock), window restarts per stream, final joint state."""

    seconds: float
    robot_seconds: float
    sensor_seconds: float
    restarts: dict[str, int]
    position_rad: np.ndarray


def wait_settled(
    commander,
    sensors: Sequence[tuple[object, Sequence[str], float]],
    *,
    tolerance_rad: float,
    window_s: float,
    sensor_stable_mm: float,
    timeout: float,
    clock: Callable[[], float],
    read_timeout_s: float = 1.0,
    on_reading: Callable[[str, list], None] | None = None,
) -> SettleResult:
    """Return once the robot is still and every sensor's markers are stable.

    The robot's window (``commander.wait_settled``) and the sensors' windows run at the same
    time (the sensors on a helper thread), so a settled configuration costs one window, not
    two; after the robot is still, the sensor loop keeps watching the joints and restarts every
    window if the robot moves again.

    sensors: (sensor, marker names, expected per-axis noise σ in mm) for each sensor; a
    marker's window allows ``sensor_stable_mm + 4 σ`` per axis, so noise alone does not
    restart it. Raises DeviceTimeoutError after ``timeout`` (clock seconds) and
    TargetLostError when a marker is reported invisible (the caller suspends). ValueError for
    a window not shorter than the timeout. ``on_reading(sensor name, samples)`` sees every
    reading (for the log and the bus).
    """
    timeout = check_timeout(timeout)
    if not window_s < timeout:
        raise ValueError(f"settle window {window_s} s must be shorter than the timeout {timeout} s")
    if not sensor_stable_mm > 0:
        raise ValueError(f"sensor_stable_mm must be positive, got {sensor_stable_mm!r}")
    t_start = clock()
    deadline = t_start + timeout
    watch = _SensorWatch(sensors, window_s, sensor_stable_mm, deadline, clock, read_timeout_s, on_reading)
    thread = threading.Thread(target=watch.run, name="settle-sensors", daemon=True)
    thread.start()
    try:
        state = commander.wait_settled(tolerance_rad, window_s, timeout)
    except BaseException:
        watch.halt.set()
        thread.join(timeout=read_timeout_s + 1.0)
        raise
    t_robot = clock()
    watch.robot_still(commander, np.asarray(state.position_rad, dtype=float), tolerance_rad)
    thread.join(timeout=max(deadline - clock(), 0.0) + read_timeout_s + 1.0)
    if thread.is_alive():
        watch.halt.set()
        raise DeviceTimeoutError(f"sensor readings not stable within {timeout:.3g} s")
    if watch.error is not None:
        raise watch.error
    t_end = clock()
    restarts = {f"{s}/{m}": w.restarts for (s, m), w in watch.windows.items()}
    restarts["robot"] = watch.robot_restarts
    return SettleResult(t_end - t_start, t_robot - t_start, max(t_end - t_robot, 0.0), restarts, watch.ref_q)


class _SensorWatch:
    """The sensors' side of ``wait_settled``, run on a helper thread."""

    def __init__(self, sensors, window_s, stable_mm, deadline, clock, read_timeout_s, on_reading) -> None:
        self.sensors = list(sensors)
        self.deadline, self.clock, self.read_timeout_s, self.on_reading = deadline, clock, read_timeout_s, on_reading
        self.windows = {(sensor.name, m): StabilityWindow(stable_mm + 4.0 * max(noise, 0.0), window_s)
                        for sensor, markers, noise in self.sensors for m in markers}
        self.held = {k: False for k in self.windows}
        self.halt = threading.Event()
        self.error: BaseException | None = None
        self.robot_restarts = 0
        self.ref_q: np.ndarray | None = None
        self._commander = None
        self._tol = 0.0
        self._still = threading.Event()

    def robot_still(self, commander, q: np.ndarray, tolerance_rad: float) -> None:
        self._commander, self.ref_q, self._tol = commander, q, tolerance_rad
        self._still.set()

    def run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            self.error = exc

    def _loop(self) -> None:
        while not self.halt.is_set():
            if self._still.is_set() and all(self.held.values()):
                return
            if self.clock() > self.deadline:
                waiting = ", ".join(f"{s}/{m}" for (s, m), ok in self.held.items() if not ok) or "robot"
                raise DeviceTimeoutError(f"sensor readings not stable in time ({waiting})")
            if self._still.is_set():
                q = np.asarray(self._commander.joint_state().position_rad, dtype=float)
                if np.max(np.abs(q - self.ref_q)) > self._tol:
                    # the robot moved again: every window starts over
                    self.robot_restarts += 1
                    self.ref_q = q
                    for w in self.windows.values():
                        w.reset()
                    self.held = {k: False for k in self.windows}
            if not self.windows:
                if self._still.is_set():
                    return
                self.halt.wait(0.001)
                continue
            for sensor, markers, _ in self.sensors:
                wanted = set(markers)
                samples = sensor.read(min(self.read_timeout_s, max(self.deadline - self.clock(), 1e-3)))
                if self.on_reading is not None:
                    self.on_reading(sensor.name, samples)
                for smp in samples:
                    if smp.marker not in wanted:
                        continue
                    if not smp.visible:
                        raise TargetLostError(f"{sensor.name}: marker {smp.marker!r} is not visible")
                    key = (sensor.name, smp.marker)
                    self.held[key] = self.windows[key].update(smp.host_time, smp.position_mm)
