"""Jerk-limited, time-optimal, synchronised joint trajectories (shared by the RSI and FRI
commanders).

Every axis follows a piecewise-constant-jerk ("7-segment S-curve") profile from rest to rest:
jerk up, constant acceleration, jerk down, cruise, and the mirror image. Position, velocity and
acceleration are continuous; jerk is bounded. Each axis' profile is time-optimal under its
velocity, acceleration and jerk limits; all axes are then stretched to the duration of the
slowest by lowering their peak velocity (same acceleration and jerk limits), so every axis
starts and ends together and no axis ever exceeds its limits. ``duration`` is analytic.

The model gives no jerk limit, so by default the jerk phases take a quarter of the time an axis
needs to reach full speed: ``max_jerk = 4 a² / v``. With the speed override ``s`` (see
``scaled_limits``) velocity, acceleration and jerk scale as ``s``, ``s²``, ``s³``: the motion at
``s`` is exactly the motion at full speed played ``1/s`` times slower.

``JointTrajectory.stop`` plans a time-optimal jerk-limited stop from any current position,
velocity and acceleration (for a controlled stop mid-motion).

Units: radians, seconds. Shapes: ``n`` axes; ``sample`` accepts a scalar time or shape (m,).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["JointTrajectory", "motion_time", "scaled_limits", "default_jerk"]

#: Fraction of the time-to-full-speed spent in each jerk phase when no jerk limit is given.
DEFAULT_JERK_RAMP_FRACTION = 0.25


def _as_limits(name: str, value, n: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{name} must be finite and positive, got {value!r}")
    return arr


def default_jerk(max_velocity_rad_s, max_acceleration_rad_s2) -> np.ndarray:
    """Default jerk limit (rad/s³): jerk phases last a quarter of ``v/a``, i.e. ``4 a² / v``."""
    v = _as_limits("max_velocity_rad_s", max_velocity_rad_s)
    a = _as_limits("max_acceleration_rad_s2", max_acceleration_rad_s2)
    return a * a / (DEFAULT_JERK_RAMP_FRACTION * v)


def scaled_limits(max_velocity_rad_s, max_acceleration_rad_s2, speed: float, max_jerk_rad_s3=None):
    """Limits for a speed override ``speed`` in (0, 1]: (v·s, a·s², j·s³), each shape (n,).

    Scaling this way makes the trajectory a pure time-stretch of the full-speed one.
    """
    if not (isinstance(speed, (int, float)) and 0 < speed <= 1):
        raise ValueError(f"speed must be a fraction in (0, 1], got {speed!r}")
    v = _as_limits("max_velocity_rad_s", max_velocity_rad_s)
    a = _as_limits("max_acceleration_rad_s2", max_acceleration_rad_s2)
    j = default_jerk(v, a) if max_jerk_rad_s3 is None else _as_limits("max_jerk_rad_s3", max_jerk_rad_s3)
    return v * speed, a * speed**2, j * speed**3


def _accel_phase(vp, a, j):
    """From rest to peak velocity ``vp`` under (a, j): (t_jerk, t_const_acc, peak_acc)."""
    reach = vp * j >= a * a  # the acceleration limit is reached
    with np.errstate(invalid="ignore", divide="ignore"):
        ap = np.where(reach, a, np.sqrt(vp * j))
        tj = ap / j
        ta = np.where(reach, vp / a - a / j, 0.0)
    return tj, np.maximum(ta, 0.0), ap


def _time_optimal(d, v, a, j):
    """Rest-to-rest minimum time for distances ``d >= 0`` (any broadcastable shape).

    Returns (T, peak velocity reached).
    """
    d, v, a, j = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (d, v, a, j)))
    tj, ta, _ = _accel_phase(v, a, j)
    t_acc = 2 * tj + ta
    cruise = d >= v * t_acc
    # Velocity limit not reached: peak velocity from the distance.
    vp1 = 0.5 * (-(a * a / j) + np.sqrt((a * a / j) ** 2 + 4 * a * d))  # a reached
    vp2 = np.cbrt(d * d * j / 4.0)  # a not reached
    vp_short = np.where(vp1 * j >= a * a, vp1, vp2)
    vp = np.where(cruise, v, np.minimum(vp_short, v))
    tj, ta, _ = _accel_phase(vp, a, j)
    t_acc = 2 * tj + ta
    with np.errstate(invalid="ignore", divide="ignore"):
        T = np.where(d > 0, t_acc + np.where(vp > 0, d / vp, 0.0), 0.0)
    return T, vp


def motion_time(start_rad, target_rad, max_velocity_rad_s, max_acceleration_rad_s2, max_jerk_rad_s3=None):
    """Duration (s) of the synchronised move from ``start_rad`` to ``target_rad``.

    start_rad, target_rad: shape (..., n), radians, broadcast against each other; limits
    shape (n,). Returns shape (...) (a float for 1-D input). Closed form, no iteration.
    """
    d = np.abs(np.asarray(target_rad, dtype=float) - np.asarray(start_rad, dtype=float))
    v = _as_limits("max_velocity_rad_s", max_velocity_rad_s)
    a = _as_limits("max_acceleration_rad_s2", max_acceleration_rad_s2)
    j = default_jerk(v, a) if max_jerk_rad_s3 is None else _as_limits("max_jerk_rad_s3", max_jerk_rad_s3)
    T, _ = _time_optimal(d, v, a, j)
    out = np.max(T, axis=-1) if T.ndim else T
    return float(out) if np.ndim(out) == 0 else out


def _peak_velocity_for_duration(d, v, a, j, T):
    """Per axis, the peak velocity (<= time-optimal one) that makes the move last exactly T.

    The duration ``t_acc(vp) + d/vp`` decreases monotonically in vp up to the time-optimal peak,
    so a bisection is exact to rounding; it runs once per plan.
    """
    _, hi = _time_optimal(d, v, a, j)
    lo = np.zeros_like(hi)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        tj, ta, _ = _accel_phase(mid, a, j)
        with np.errstate(divide="ignore", invalid="ignore"):
            dur = 2 * tj + ta + np.where(mid > 0, d / mid, np.inf)
        too_slow = dur > T
        lo = np.where(too_slow, mid, lo)
        hi = np.where(too_slow, hi, mid)
    return hi  # hi always gives a duration <= T, i.e. never slower than requested


class JointTrajectory:
    """Piecewise-constant-jerk motion of n axes, sampled analytically.

    Holds, per axis, segment durations and jerks (shape (n, K)) from an initial state
    (position, velocity, acceleration, each shape (n,)). After its own end an axis holds
    its final position with zero velocity and acceleration.
    """

    def __init__(self, start_rad, durations, jerks, velocity0=None, acceleration0=None) -> None:
        p0 = np.asarray(start_rad, dtype=float).reshape(-1)
        dur = np.asarray(durations, dtype=float)
        jk = np.asarray(jerks, dtype=float)
        n = p0.shape[0]
        if dur.shape != jk.shape or dur.ndim != 2 or dur.shape[0] != n:
            raise ValueError(f"durations {dur.shape} and jerks {jk.shape} must both be ({n}, K)")
        if np.any(dur < 0) or not np.all(np.isfinite(dur)):
            raise ValueError("segment durations must be finite and non-negative")
        v0 = np.zeros(n) if velocity0 is None else np.asarray(velocity0, dtype=float).reshape(n)
        a0 = np.zeros(n) if acceleration0 is None else np.asarray(acceleration0, dtype=float).reshape(n)
        K = dur.shape[1]
        bounds = np.zeros((n, K + 1))
        bounds[:, 1:] = np.cumsum(dur, axis=1)
        P = np.empty((n, K + 1))
        V = np.empty((n, K + 1))
        A = np.empty((n, K + 1))
        P[:, 0], V[:, 0], A[:, 0] = p0, v0, a0
        for k in range(K):
            h = dur[:, k]
            P[:, k + 1] = P[:, k] + V[:, k] * h + A[:, k] * h**2 / 2 + jk[:, k] * h**3 / 6
            V[:, k + 1] = V[:, k] + A[:, k] * h + jk[:, k] * h**2 / 2
            A[:, k + 1] = A[:, k] + jk[:, k] * h
        self.n_axes = n
        self._bounds = bounds
        self._jerk = jk
        self._P, self._V, self._A = P, V, A
        self.axis_durations = bounds[:, -1].copy()
        #: Seconds until every axis has reached its end.
        self.duration = float(bounds[:, -1].max()) if n else 0.0
        self.start_rad = p0.copy()
        self.end_rad = P[:, -1].copy()

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def plan(
        cls,
        start_rad,
        target_rad,
        max_velocity_rad_s,
        max_acceleration_rad_s2,
        max_jerk_rad_s3=None,
    ) -> "JointTrajectory":
        """Rest-to-rest move, time-optimal for the slowest axis, all axes synchronised.

        start_rad, target_rad, limits: shape (n,), radians and rad/s, rad/s², rad/s³.
        """
        q0 = np.asarray(start_rad, dtype=float).reshape(-1)
        q1 = np.asarray(target_rad, dtype=float).reshape(-1)
        n = q0.shape[0]
        if q1.shape != (n,):
            raise ValueError(f"target has shape {q1.shape}, start has ({n},)")
        if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(q1))):
            raise ValueError(f"start and target must be finite, got {q0} and {q1}")
        v = np.broadcast_to(_as_limits("max_velocity_rad_s", max_velocity_rad_s), (n,))
        a = np.broadcast_to(_as_limits("max_acceleration_rad_s2", max_acceleration_rad_s2), (n,))
        j = default_jerk(v, a) if max_jerk_rad_s3 is None else _as_limits("max_jerk_rad_s3", max_jerk_rad_s3)
        j = np.broadcast_to(j, (n,))
        delta = q1 - q0
        d = np.abs(delta)
        sign = np.sign(delta)
        T_axes, _ = _time_optimal(d, v, a, j)
        T = float(T_axes.max()) if n else 0.0
        vp = _peak_velocity_for_duration(d, v, a, j, T) if T > 0 else np.zeros(n)
        tj, ta, _ = _accel_phase(vp, a, j)
        moving = d > 0
        tj = np.where(moving, tj, 0.0)
        ta = np.where(moving, ta, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = np.where(moving, np.maximum(d / vp - (2 * tj + ta), 0.0), 0.0)
        durations = np.stack([tj, ta, tj, tc, tj, ta, tj], axis=1)
        pattern = np.array([1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0])
        jerks = (sign * j)[:, None] * pattern[None, :]
        traj = cls(q0, durations, jerks)
        traj.end_rad = q1.copy()  # exact target (the integrated end differs by rounding only)
        traj._P[:, -1] = q1
        return traj

    @classmethod
    def stop(
        cls,
        position_rad,
        velocity_rad_s,
        acceleration_rad_s2,
        max_velocity_rad_s,
        max_acceleration_rad_s2,
        max_jerk_rad_s3=None,
    ) -> "JointTrajectory":
        """Time-optimal jerk-limited stop of every axis from its current state (shape (n,) each).

        Never exceeds the acceleration limit, nor the velocity limit when the current velocity
        is within it (the jerk is raised if needed to avoid overshooting it while the current
        acceleration is ramped down).
        """
        p = np.asarray(position_rad, dtype=float).reshape(-1)
        n = p.shape[0]
        vel = np.asarray(velocity_rad_s, dtype=float).reshape(n)
        acc = np.asarray(acceleration_rad_s2, dtype=float).reshape(n)
        vmax = np.broadcast_to(_as_limits("max_velocity_rad_s", max_velocity_rad_s), (n,))
        amax = np.broadcast_to(_as_limits("max_acceleration_rad_s2", max_acceleration_rad_s2), (n,))
        jmax = default_jerk(vmax, amax) if max_jerk_rad_s3 is None else _as_limits("max_jerk_rad_s3", max_jerk_rad_s3)
        jmax = np.broadcast_to(jmax, (n,))
        segs = [_stop_segments(float(vel[i]), float(acc[i]), float(vmax[i]), float(amax[i]), float(jmax[i])) for i in range(n)]
        K = max(1, max(len(s) for s in segs))
        durations = np.zeros((n, K))
        jerks = np.zeros((n, K))
        for i, s in enumerate(segs):
            for k, (jk, h) in enumerate(s):
                durations[i, k], jerks[i, k] = h, jk
        return cls(p, durations, jerks, vel, acc)

    # -- evaluation ---------------------------------------------------------------------------

    def sample(self, t):
        """Position, velocity, acceleration at time(s) ``t`` (s, from the trajectory's start).

        Scalar t → three arrays of shape (n,); t of shape (m,) → shape (m, n). Times before 0
        give the start state, after an axis' end its final position at rest.
        """
        t_arr = np.asarray(t, dtype=float)
        scalar = t_arr.ndim == 0
        tt = np.atleast_1d(t_arr)[:, None]  # (m, 1)
        tt = np.clip(tt, 0.0, self.axis_durations[None, :])  # (m, n)
        inner = self._bounds[:, 1:-1]  # (n, K-1)
        idx = (tt[:, :, None] >= inner[None, :, :]).sum(axis=2)  # (m, n) segment index
        ax = np.arange(self.n_axes)[None, :]
        h = tt - self._bounds[ax, idx]
        P, V, A, J = self._P[ax, idx], self._V[ax, idx], self._A[ax, idx], self._jerk[ax, idx]
        pos = P + V * h + A * h**2 / 2 + J * h**3 / 6
        vel = V + A * h + J * h**2 / 2
        acc = A + J * h
        done = tt >= self.axis_durations[None, :]
        if np.any(done):
            pos = np.where(done, self._P[:, -1][None, :], pos)
            vel = np.where(done, self._V[:, -1][None, :], vel)
            acc = np.where(done, self._A[:, -1][None, :], acc)
        if scalar:
            return pos[0], vel[0], acc[0]
        return pos, vel, acc

    def __repr__(self) -> str:
        return f"JointTrajectory(n_axes={self.n_axes}, duration={self.duration:.4f} s)"


def _stop_segments(v0: float, a0: float, vmax: float, amax: float, j: float, depth: int = 0):
    """(jerk, duration) segments bringing one axis from (v0, a0) to rest; see ``stop``."""
    if v0 < 0 or (v0 == 0 and a0 < 0):
        return [(-jk, h) for jk, h in _stop_segments(-v0, -a0, vmax, amax, j, depth)]
    if v0 == 0 and a0 == 0:
        return []
    segs: list[tuple[float, float]] = []
    if a0 > 0 and v0 + a0 * a0 / (2 * j) > vmax > v0:
        j = a0 * a0 / (2 * (vmax - v0))  # ramp the acceleration down fast enough not to overshoot
    if a0 < 0 and v0 < a0 * a0 / (2 * j) and depth < 2:
        # Already braking harder than needed: ramp the acceleration to zero (velocity crosses
        # zero), then stop the small reverse motion.
        h = -a0 / j
        v1 = v0 + a0 * h + j * h * h / 2
        return [(j, h)] + _stop_segments(v1, 0.0, vmax, amax, j, depth + 1)
    ap = math.sqrt(max(j * v0 + a0 * a0 / 2, 0.0))
    if ap <= amax:
        segs = [(-j, max((a0 + ap) / j, 0.0)), (j, ap / j)]
    else:
        t1 = max((a0 + amax) / j, 0.0)
        t2 = max((v0 + (a0 * a0 - amax * amax) / (2 * j) - amax * amax / (2 * j)) / amax, 0.0)
        segs = [(-j, t1), (0.0, t2), (j, amax / j)]
    return segs
