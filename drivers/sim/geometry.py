"""Line-of-sight geometry of the simulated cell: capsules, segment distances, acceptance cones.

Everything broadcasts over leading dimensions and runs without Python loops over points,
configurations or capsules, so a planner can ask about thousands of configurations at once.
Lengths in mm, angles in radians.

A **capsule** is the set of points within ``radius`` of the segment ``a``–``b`` (a cylinder
with hemispherical caps); it stands in for one link of the arm. A sight line from a sensor to
a marker is **blocked** when the open segment between them comes closer than the radius to a
capsule's axis.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", u, v)


def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross products of vectors (..., 3) and (..., 3), broadcast; faster than ``np.cross`` on
    the small arrays of one configuration."""
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    return np.stack(
        [
            u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1],
            u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
            u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0],
        ],
        -1,
    )


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (mm) from points ``p`` to segments ``a``–``b``; all (..., 3), broadcast → (...).

    A zero-length segment is a point.
    """
    p, a, b = (np.asarray(x, dtype=float) for x in (p, a, b))
    ab = b - a
    den = _dot(ab, ab)
    t = np.clip(_dot(p - a, ab) / np.where(den > _EPS, den, 1.0), 0.0, 1.0)
    t = np.where(den > _EPS, t, 0.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def segment_segment_distance(
    p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray
) -> np.ndarray:
    """Shortest distance (mm) between segments ``p0``–``p1`` and ``q0``–``q1``.

    All inputs (..., 3), broadcast against each other; result (...). Handles parallel and
    zero-length segments (Ericson, *Real-Time Collision Detection*, §5.1.9, vectorised).
    """
    p0, p1, q0, q1 = (np.asarray(x, dtype=float) for x in (p0, p1, q0, q1))
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = _dot(d1, d1)
    e = _dot(d2, d2)
    f = _dot(d2, r)
    c = _dot(d1, r)
    b = _dot(d1, d2)
    a_ok = a > _EPS
    e_ok = e > _EPS
    a_safe = np.where(a_ok, a, 1.0)
    e_safe = np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    # General case: closest points of the infinite lines, s clamped to the first segment
    # (s = 0 for parallel lines, where any s is as good).
    s = np.where(denom > _EPS * np.maximum(a * e, 1.0), np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / e_safe
    # t outside [0, 1]: clamp t and recompute s for that end of the second segment.
    s = np.where(t < 0.0, np.clip(-c / a_safe, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    # Degenerate segments.
    s = np.where(a_ok, np.where(e_ok, s, np.clip(-c / a_safe, 0.0, 1.0)), 0.0)
    t = np.where(e_ok, np.where(a_ok, t, np.clip(f / e_safe, 0.0, 1.0)), 0.0)
    closest_p = p0 + s[..., None] * d1
    closest_q = q0 + t[..., None] * d2
    return np.linalg.norm(closest_p - closest_q, axis=-1)


def sight_blockers(
    sensor: np.ndarray,
    targets: np.ndarray,
    cap_a: np.ndarray,
    cap_b: np.ndarray,
    radii: np.ndarray,
) -> np.ndarray:
    """Which capsules block the sight line from the sensor to each target.

    sensor: (..., 3) sensor origin. targets: (..., m, 3) marker positions. cap_a, cap_b:
    (..., c, 3) capsule axis end points; radii: (c,) or (..., c) mm. All in one frame.

    Returns (..., m, c) bool: True where capsule c comes closer than its radius to the segment
    sensor → target m. A capsule that already contains the target (the marker sits on or in
    that body) is never counted as blocking it: the marker's acceptance cone, not the body it
    is mounted on, decides whether it faces the sensor.
    """
    sensor = np.asarray(sensor, dtype=float)[..., None, None, :]  # (..., 1, 1, 3)
    targets = np.asarray(targets, dtype=float)[..., :, None, :]  # (..., m, 1, 3)
    a = np.asarray(cap_a, dtype=float)[..., None, :, :]  # (..., 1, c, 3)
    b = np.asarray(cap_b, dtype=float)[..., None, :, :]
    radii = np.asarray(radii, dtype=float)[..., None, :]  # (..., 1, c)
    dist = segment_segment_distance(sensor, targets, a, b)
    inside = point_segment_distance(targets, a, b) <= radii
    return (dist < radii) & ~inside


def line_of_sight(
    sensor: np.ndarray,
    targets: np.ndarray,
    cap_a: np.ndarray,
    cap_b: np.ndarray,
    radii: np.ndarray,
) -> np.ndarray:
    """(..., m) bool: True where no capsule blocks the sight line; shapes as ``sight_blockers``."""
    return ~np.any(sight_blockers(sensor, targets, cap_a, cap_b, radii), axis=-1)


def angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, π]) between vectors (..., 3) and (..., 3); broadcasts."""
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    cross_norm = np.linalg.norm(cross(u, v), axis=-1)
    return np.arctan2(cross_norm, _dot(u, v))


def within_cone(axis: np.ndarray, direction: np.ndarray, half_angle_rad: np.ndarray | float) -> np.ndarray:
    """(...) bool: ``direction`` lies within ``half_angle_rad`` of ``axis`` (both (..., 3)).

    A half-angle of π (or more) accepts every direction. Used for a retroreflector's or an
    infrared marker's acceptance cone (axis = marker normal, direction = marker → sensor) and
    for a camera's field of view (axis = optical axis, direction = sensor → marker).
    """
    return angle_between(axis, direction) <= np.asarray(half_angle_rad, dtype=float)


def look_at_frame(origin: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Pose (4, 4) of a sensor at ``origin`` whose +z looks at ``target`` (both (3,), mm).

    +x is horizontal (perpendicular to ``up`` and the view direction), +y = z × x points
    "down" in the image like a camera's. Raises ValueError when the view direction is
    parallel to ``up`` or ``origin`` equals ``target``.
    """
    origin = np.asarray(origin, dtype=float)
    z = np.asarray(target, dtype=float) - origin
    norm = np.linalg.norm(z)
    if norm < 1e-9:
        raise ValueError(f"a sensor cannot look at its own origin {origin.tolist()}")
    z = z / norm
    x = cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"view direction {z.tolist()} is parallel to up {list(up)}; give the pose as a frame instead")
    x = x / np.linalg.norm(x)
    y = cross(z, x)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = x, y, z, origin
    return t
