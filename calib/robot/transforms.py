"""Rigid transforms: 4×4 homogeneous matrices, rotations, ZYX Euler angles.

Names follow pytransform3d's ``A2B`` habit: ``base2sensor`` maps a point expressed in the base
frame to the same point expressed in the sensor frame, ``p_sensor = base2sensor @ p_base``.
All functions broadcast over leading dimensions. Lengths in mm, angles in rad.
"""

from __future__ import annotations

import numpy as np


def rot_x(a: np.ndarray | float) -> np.ndarray:
    """Rotation about x by ``a`` rad; shape (..., 3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(a: np.ndarray | float) -> np.ndarray:
    """Rotation about y by ``a`` rad; shape (..., 3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(a: np.ndarray | float) -> np.ndarray:
    """Rotation about z by ``a`` rad; shape (..., 3, 3)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def euler_zyx_to_matrix(yaw: np.ndarray | float, pitch: np.ndarray | float, roll: np.ndarray | float) -> np.ndarray:
    """R = Rz(yaw) · Ry(pitch) · Rx(roll) (ZYX Euler, KUKA's A, B, C); shape (..., 3, 3).

    Written out rather than multiplied: samplers call this once per step.
    """
    yaw, pitch, roll = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (yaw, pitch, roll)))
    ca, sa, cb, sb, cg, sg = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    r = np.empty(yaw.shape + (3, 3))
    r[..., 0, 0], r[..., 0, 1], r[..., 0, 2] = ca * cb, ca * sb * sg - sa * cg, ca * sb * cg + sa * sg
    r[..., 1, 0], r[..., 1, 1], r[..., 1, 2] = sa * cb, sa * sb * sg + ca * cg, sa * sb * cg - ca * sg
    r[..., 2, 0], r[..., 2, 1], r[..., 2, 2] = -sb, cb * sg, cb * cg
    return r


def matrix_to_euler_zyx(r: np.ndarray) -> np.ndarray:
    """Inverse of ``euler_zyx_to_matrix``: (..., 3, 3) → (..., 3) as (yaw, pitch, roll) rad.

    At gimbal lock (|pitch| = π/2) roll is set to 0 and yaw carries the whole rotation.
    """
    r = np.asarray(r, dtype=float)
    pitch = np.arcsin(np.clip(-r[..., 2, 0], -1.0, 1.0))
    cp = np.cos(pitch)
    lock = cp < 1e-12
    yaw = np.where(lock, np.arctan2(-r[..., 0, 1], r[..., 1, 1]), np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    roll = np.where(lock, 0.0, np.arctan2(r[..., 2, 1], r[..., 2, 2]))
    return np.stack([yaw, pitch, roll], axis=-1)


def homogeneous(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Build (..., 4, 4) from rotation (..., 3, 3) and translation (..., 3)."""
    rotation = np.asarray(rotation, dtype=float)
    translation = np.asarray(translation, dtype=float)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    t = np.zeros(shape + (4, 4))
    t[..., :3, :3] = rotation
    t[..., :3, 3] = translation
    t[..., 3, 3] = 1.0
    return t


def invert(t: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    r = np.swapaxes(t[..., :3, :3], -1, -2)
    return homogeneous(r, -np.einsum("...ij,...j->...i", r, t[..., :3, 3]))


def apply(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply transforms (..., 4, 4) to points (..., 3); broadcasts."""
    return np.einsum("...ij,...j->...i", t[..., :3, :3], points) + t[..., :3, 3]


def pose_to_matrix(xyz_mm: np.ndarray, zyx_rad: np.ndarray) -> np.ndarray:
    """(..., 3) position and (..., 3) ZYX Euler (yaw, pitch, roll) → (..., 4, 4)."""
    zyx_rad = np.asarray(zyx_rad, dtype=float)
    return homogeneous(euler_zyx_to_matrix(zyx_rad[..., 0], zyx_rad[..., 1], zyx_rad[..., 2]), xyz_mm)


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotations (..., 3, 3), robust near 0 and π."""
    r = np.asarray(r, dtype=float)
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    axis_sin = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    sin = np.linalg.norm(axis_sin, axis=-1) / 2.0
    return np.arctan2(sin, np.clip(cos, -1.0, 1.0))


def cross(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
    """a × b with the vectors along ``axis`` (a negative axis; length 3), broadcast as ``np.cross``
    — which moves both axes last and back on every call: on the fit's Jacobians (thousands of calls
    on (k, 3, P) arrays) that bookkeeping cost more than the products."""
    if axis >= 0:
        raise ValueError(f"cross takes a negative axis, given {axis}")
    tail = (slice(None),) * (-axis - 1)
    a0, a1, a2 = (a[(Ellipsis, i) + tail] for i in range(3))
    b0, b1, b2 = (b[(Ellipsis, i) + tail] for i in range(3))
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=axis)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros_like(v[..., 0])
    return np.stack(
        [np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1), np.stack([-v[..., 1], v[..., 0], z], -1)],
        -2,
    )


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = skew(w)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def log_so3(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotations (..., 3, 3); valid for angles < π."""
    r = np.asarray(r, dtype=float)
    angle = rotation_angle(r)
    v = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    small = angle < 1e-8
    scale = np.where(small, 0.5, angle / (2.0 * np.sin(np.where(small, 1.0, angle))))
    return v * scale[..., None]


def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) given **scalar first**
    (w, x, y, z; Hamilton convention, active: the matrix rotates vectors, R·v = q v q*).
    The quaternion is normalised first; q and −q give the same matrix."""
    q = np.asarray(wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), scalar first (w, x, y, z) with w ≥ 0, of rotations (..., 3, 3):
    the inverse of ``quat_to_matrix`` (Shepperd's method, robust at every angle)."""
    r = np.asarray(r, dtype=float)
    tr = np.trace(r, axis1=-2, axis2=-1)
    cand = np.stack([
        np.stack([1 + tr, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1),
        np.stack([r[..., 2, 1] - r[..., 1, 2], 1 + 2 * r[..., 0, 0] - tr, r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0]], -1),
        np.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0], 1 + 2 * r[..., 1, 1] - tr, r[..., 1, 2] + r[..., 2, 1]], -1),
        np.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1], 1 + 2 * r[..., 2, 2] - tr], -1),
    ], -2)  # (..., 4, 4): row k is 4·q_k·q, largest for the largest |q_k|
    k = np.argmax(np.stack([1 + tr, 1 + 2 * r[..., 0, 0] - tr, 1 + 2 * r[..., 1, 1] - tr, 1 + 2 * r[..., 2, 2] - tr], -1), -1)
    q = np.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """J_l(w) (..., 3, 3): exp(w + dw) ≈ exp(J_l(w)·dw) · exp(w)."""
    w = np.asarray(w, dtype=float)
    t = np.linalg.norm(w, axis=-1)[..., None, None]
    k = skew(w)
    small = t < 1e-6
    s = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t**2 / 24.0, (1.0 - np.cos(s)) / s**2)
    b = np.where(small, 1.0 / 6.0 - t**2 / 120.0, (s - np.sin(s)) / s**3)
    return np.eye(3) + a * k + b * (k @ k)


def so3_left_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """J_l(w)⁻¹ (..., 3, 3), for angles below π: log(exp(dv)·exp(w)) ≈ w + J_l(w)⁻¹·dv."""
    w = np.asarray(w, dtype=float)
    t = np.linalg.norm(w, axis=-1)[..., None, None]
    k = skew(w)
    small = t < 1e-6
    s = np.where(small, 1.0, t)
    c = np.where(small, 1.0 / 12.0 + t**2 / 720.0, 1.0 / s**2 - (1.0 + np.cos(s)) / (2.0 * s * np.sin(s)))
    return np.eye(3) - 0.5 * k + c * (k @ k)
