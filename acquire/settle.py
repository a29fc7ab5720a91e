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
    state = commander.wait_settled(tolerance_rad, window_s, timeout)
    t_robot = clock()
    ref_q = np.asarray(state.position_rad, dtype=float)
    windows: dict[tuple[str, str], StabilityWindow] = {}
    for sensor, markers, noise in sensors:
        for m in markers:
            windows[(sensor.name, m)] = StabilityWindow(sensor_stable_mm + 4.0 * max(noise, 0.0), window_s)
    robot_restarts = 0
    held = {k: False for k in windows}
    while not all(held.values()):
        now = clock()
        if now > deadline:
            waiting = ", ".join(f"{s}/{m}" for (s, m), ok in held.items() if not ok)
            raise DeviceTimeoutError(f"sensor readings not stable within {timeout:.3g} s ({waiting})")
        q = np.asarray(commander.joint_state().position_rad, dtype=float)
        if np.max(np.abs(q - ref_q)) > tolerance_rad:
            # the robot moved again: every window starts over
            robot_restarts += 1
            ref_q = q
            for w in windows.values():
                w.reset()
            held = {k: False for k in windows}
        for sensor, markers, _ in sensors:
            wanted = set(markers)
            samples = sensor.read(min(read_timeout_s, max(deadline - clock(), 1e-3)))
            if on_reading is not None:
                on_reading(sensor.name, samples)
            for s in samples:
                if s.marker not in wanted:
                    continue
                if not s.visible:
                    raise TargetLostError(f"{sensor.name}: marker {s.marker!r} is not visible")
                held[(sensor.name, s.marker)] = windows[(sensor.name, s.marker)].update(s.host_time, s.position_mm)
    t_end = clock()
    restarts = {f"{s}/{m}": w.restarts for (s, m), w in windows.items()}
    restarts["robot"] = robot_restarts
    return SettleResult(t_end - t_start, t_robot - t_start, t_end - t_robot, restarts, ref_q)
