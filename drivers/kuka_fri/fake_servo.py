"""The fake Sunrise's joints: a second-order position servo, and the checks Sunrise makes of a
client's set-points before it takes them (``FakeSunrise`` in ``fake.py`` uses both)."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from drivers.protocols import JointLimits

N_JOINTS = 7


class JointServo:
    """Seven joints that follow a set-point through a second-order servo.

    ``q`` (7,) rad: actual position; ``qd`` (7,) rad/s: actual velocity; ``setpoint`` (7,) rad:
    what the controller commands (the interpolator's position plus the client's overlay);
    ``guide`` (7,) rad: an operator's hand pushing the arm, the servo settles at set-point +
    guide; ``compliant``: joint-impedance mode since a hand touched the arm; ``brakes_held``:
    the joints stay put whatever the set-point (a brake that does not release).
    """

    def __init__(self, q0_rad: np.ndarray, frequency_hz: float, damping: float) -> None:
        q0 = np.asarray(q0_rad, dtype=float).copy()
        if q0.shape != (N_JOINTS,):
            raise ValueError(f"initial_position_rad must have shape ({N_JOINTS},), got {q0.shape}")
        self.q = q0
        self.qd = np.zeros(N_JOINTS)
        self.setpoint = q0.copy()
        self.guide = np.zeros(N_JOINTS)
        self.compliant = False
        self.brakes_held = False
        self._omega = 2 * math.pi * frequency_hz
        self._zeta = damping

    def push(self, displacement_rad: np.ndarray) -> None:
        """A hand displaces the arm by ``displacement_rad`` (7,) from its set-point; zeros let go."""
        d = np.asarray(displacement_rad, dtype=float)
        if d.shape != (N_JOINTS,) or not np.all(np.isfinite(d)):
            raise ValueError(f"displacement must be {N_JOINTS} finite angles (rad), got {d!r}")
        self.guide = d.copy()
        self.compliant = self.compliant or bool(np.any(d))

    def unguided(self) -> np.ndarray:
        """Where the arm would be without the hand on it, (7,) rad: what a client must start from."""
        return self.q - self.guide

    def hold_here(self) -> None:
        """The set-point becomes where the arm is (a hand on the arm does not move it)."""
        self.setpoint = self.unguided()

    def halt(self) -> None:
        """Brakes catch the joints: the velocity is zero."""
        self.qd[:] = 0.0

    def step(self, dt_s: float, powered: bool) -> None:
        """Advance ``dt_s`` seconds: semi-implicit Euler in 0.5 ms sub-steps (stable for
        ω·h ≪ 1). Unpowered or braked joints do not move."""
        if self.brakes_held or not powered:
            self.halt()
            return
        n_sub = max(1, int(math.ceil(dt_s / 0.0005)))
        h = dt_s / n_sub
        w, z = self._omega, self._zeta
        for _ in range(n_sub):
            acc = w * w * (self.setpoint + self.guide - self.q) - 2 * z * w * self.qd
            self.qd += acc * h
            self.q += self.qd * h


def set_point_violation(
    cmd: np.ndarray, previous: np.ndarray, dt_s: float, limits: Optional[JointLimits], speed_tolerance: float
) -> Optional[str]:
    """Why Sunrise would refuse the set-point ``cmd`` (7,) rad that follows ``previous`` (7,) rad
    after ``dt_s`` seconds, or None: outside the joint limits, or faster than their speeds
    (relative ``speed_tolerance``). ``limits`` None checks only that it is finite."""
    if not np.all(np.isfinite(cmd)):
        return f"non-finite command {cmd}"
    if limits is None:
        return None
    out = (cmd < limits.lower_rad) | (cmd > limits.upper_rad)
    if np.any(out):
        return f"command outside joint limits on axes {np.flatnonzero(out) + 1}"
    speed = np.abs(cmd - previous) / dt_s
    if np.any(speed > limits.max_velocity_rad_s * (1 + speed_tolerance)):
        i = int(np.argmax(speed / limits.max_velocity_rad_s))
        return f"commanded speed {speed[i]:.4g} rad/s on A{i + 1} above {limits.max_velocity_rad_s[i]:.4g} rad/s"
    return None
