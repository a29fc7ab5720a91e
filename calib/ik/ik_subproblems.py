"""Screw axes of a chain and the Paden–Kahan style subproblems the analytic IK solvers share.

Any serial chain of revolute joints (DH or modified DH, any sign convention and joint offsets)
can be written as a product of exponentials:

    T(q) = exp(ξ_1 q_1) · … · exp(ξ_n q_n) · T(0)

where ξ_i is joint i's axis (unit direction ω_i and a point p_i, robot base frame, mm) at the
controller's zero ``q = 0`` *in the controller's sign convention*, so ``q`` here is exactly the
angle the pendant shows. ``ScrewAxes.from_chain`` reads ω_i, p_i and T(0) off
``Chain.flange_jacobian`` at q = 0, so the solvers inherit every convention of the model
without re-deriving any DH algebra.

All functions broadcast over leading dimensions; angles in rad, lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.robot.kinematics import Chain

#: Two unit vectors count as perpendicular / parallel when |cos| resp. |sin| is below this.
AXIS_TOLERANCE = 1e-9
#: Lines count as intersecting when they pass within this distance (mm).
POINT_TOLERANCE_MM = 1e-6


@dataclass(frozen=True)
class ScrewAxes:
    """Joint axes of a chain at q = 0 (controller convention).

    omega (n, 3) unit directions; points (n, 3) mm, the point of each axis closest to the base
    origin; home (4, 4) flange frame at q = 0; home_inv its inverse.
    """

    omega: np.ndarray
    points: np.ndarray
    home: np.ndarray
    home_inv: np.ndarray

    @classmethod
    def from_chain(cls, chain: Chain, params: np.ndarray | None = None) -> "ScrewAxes":
        """Screw axes of ``chain`` for parameter vector ``params`` (P,) (nominal when None)."""
        q0 = np.zeros(chain.n)
        fj = chain.flange_jacobian(q0, params)
        omega = fj.jw[:, : chain.n].T.copy()  # derivative of orientation wrt q_i: sign_i · z_{i-1}
        jp = fj.jp[:, : chain.n].T
        tip = fj.position
        # jp_i = ω_i × (tip − o_i)  ⇒  ω_i × o_i = ω_i × tip − jp_i; closest point = ω × (ω × o) · (−1)
        moment = cross(omega, tip) - jp
        points = -cross(omega, moment)
        home = chain.fk(q0, params)
        home_inv = np.linalg.inv(home)
        return cls(omega=omega, points=points, home=home, home_inv=home_inv)


def unit(v: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) scaled to unit length (zero vectors stay zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product over the last axis (3-vectors)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of 3-vectors (..., 3), broadcasting; cheaper than ``np.cross`` for small batches."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    x = a1 * b2 - a2 * b1
    out = np.empty(np.broadcast_shapes(np.shape(x), np.shape(a)[:-1], np.shape(b)[:-1]) + (3,))
    out[..., 0] = x
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def rotation(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about unit ``axis`` (..., 3) by ``angle`` (...) rad."""
    axis = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    t = 1.0 - c
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    out = np.empty(np.broadcast_shapes(angle.shape, axis.shape[:-1]) + (3, 3))
    out[..., 0, 0] = c + x * x * t
    out[..., 0, 1] = x * y * t - z * s
    out[..., 0, 2] = x * z * t + y * s
    out[..., 1, 0] = y * x * t + z * s
    out[..., 1, 1] = c + y * y * t
    out[..., 1, 2] = y * z * t - x * s
    out[..., 2, 0] = z * x * t - y * s
    out[..., 2, 1] = z * y * t + x * s
    out[..., 2, 2] = c + z * z * t
    return out


def rotate(axis: np.ndarray, angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rodrigues: ``v`` (..., 3) rotated about unit ``axis`` (..., 3) by ``angle`` (...)."""
    c = np.cos(angle)[..., None]
    s = np.sin(angle)[..., None]
    return v * c + cross(axis, v) * s + axis * (dot(axis, v)[..., None] * (1.0 - c))


def perp(axis: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Component of ``v`` perpendicular to unit ``axis``."""
    return v - axis * dot(axis, v)[..., None]


def subproblem1(axis: np.ndarray, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle rotating ``p`` onto ``q`` about unit ``axis`` (components ⟂ axis), and its conditioning.

    Returns (angle (...) rad, |p⟂|·|q⟂| (...)); the angle is meaningless (0) when that product
    is ~0, i.e. when p or q lies on the axis.
    """
    pp, qq = perp(axis, p), perp(axis, q)
    angle = np.arctan2(dot(axis, cross(pp, qq)), dot(pp, qq))
    return angle, np.sqrt(dot(pp, pp) * dot(qq, qq))


@dataclass(frozen=True)
class CosineSolution:
    """Both roots of ``A cos t + B sin t = D``: t = φ ± β, φ = atan2(B, A), β = acos(D / r).

    plus, minus (...) rad; ratio = D / r before clipping (|ratio| > 1: no real root);
    r = hypot(A, B); sin_beta = sin β ≥ 0 (0 where the two roots coincide).
    """

    plus: np.ndarray
    minus: np.ndarray
    phi: np.ndarray
    ratio: np.ndarray
    r: np.ndarray
    sin_beta: np.ndarray


def solve_cosine(a: np.ndarray, b: np.ndarray, d: np.ndarray, tiny: float = 1e-300) -> CosineSolution:
    """Roots of ``a·cos t + b·sin t = d`` (vectorised); see ``CosineSolution``."""
    r = np.hypot(a, b)
    phi = np.arctan2(b, a)
    ratio = np.where(r > tiny, d / np.where(r > tiny, r, 1.0), np.where(np.abs(d) > tiny, np.inf, 0.0))
    clipped = np.clip(ratio, -1.0, 1.0)
    beta = np.arccos(clipped)
    return CosineSolution(
        plus=phi + beta, minus=phi - beta, phi=phi, ratio=ratio, r=r, sin_beta=np.sqrt(np.maximum(1.0 - clipped**2, 0.0))
    )


def circle_distance_equation(
    axis: np.ndarray, axis_point: np.ndarray, moving: np.ndarray, fixed: np.ndarray, distance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients of subproblem 3: |Rot(axis, t)·(moving − c) + c − fixed| = distance.

    ``c`` = ``axis_point``; ``moving`` and ``fixed`` are points (..., 3) mm, ``distance`` (...).
    Returns (A, B, D) of ``A cos t + B sin t = D`` for ``solve_cosine``.
    """
    x = moving - axis_point
    y = fixed - axis_point
    xp, yp = perp(axis, x), perp(axis, y)
    xa, ya = dot(axis, x), dot(axis, y)
    k = (dot(x, x) + dot(y, y) - distance**2) / 2.0 - xa * ya
    return dot(xp, yp), dot(cross(axis, xp), yp), k


def common_point(points: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares meeting point of lines (m, 3) and the largest distance of it to any line (mm)."""
    eye = np.eye(3)
    projectors = eye - directions[:, :, None] * directions[:, None, :]
    lhs = projectors.sum(axis=0)
    rhs = np.einsum("mij,mj->i", projectors, points)
    if np.linalg.cond(lhs) > 1e12:
        return np.full(3, np.nan), float("inf")
    x = np.linalg.solve(lhs, rhs)
    miss = np.linalg.norm(np.einsum("mij,mj->mi", projectors, x - points), axis=-1)
    return x, float(miss.max())


def line_distance(p_a: np.ndarray, w_a: np.ndarray, point: np.ndarray) -> float:
    """Distance (mm) of ``point`` from the line through ``p_a`` with unit direction ``w_a``."""
    return float(np.linalg.norm(perp(w_a, point - p_a)))


@dataclass(frozen=True)
class SphericalTriple:
    """Geometry of three consecutive intersecting axes a1 ⟂ a2 ⟂ a3 (unit, (3,) each).

    ``aligned`` is the middle angle at which a3 is carried onto +a1 (the singular value: the
    outer angles then only matter through their sum, or their difference if a3 → −a1).
    """

    a1: np.ndarray
    a2: np.ndarray
    a3: np.ndarray
    aligned: float

    @classmethod
    def of(cls, a1: np.ndarray, a2: np.ndarray, a3: np.ndarray) -> "SphericalTriple":
        angle, _ = subproblem1(a2, a3, a1)
        return cls(a1=a1, a2=a2, a3=a3, aligned=float(angle))

    def decompose(self, r: np.ndarray, exact_singular: float = 1e-13) -> tuple[np.ndarray, np.ndarray]:
        """All (t1, t2, t3) with Rot(a1,t1)·Rot(a2,t2)·Rot(a3,t3) = r for rotations r (..., 3, 3).

        Returns angles (2, ..., 3) rad — branch 0 has sin(t2 − aligned) ≥ 0, branch 1 ≤ 0 — and
        |sin(t2 − aligned)| (...) , the distance from the singularity. Where that is below
        ``exact_singular`` t1 is set to 0 (any t1 works; t3 absorbs it).
        """
        a1, a2, a3 = self.a1, self.a2, self.a3
        target = r @ a3  # (..., 3) = Rot(a1,t1)·Rot(a2,t2)·a3
        alpha = dot(target, a1)  # a1 ⟂ a2 ⟂ a3 ⇒ z = α·a1 ± γ·(a1 × a2)
        # γ = sin of the angle between target and a1, accurate near 0 (unlike sqrt(1 − α²))
        perp_t = cross(a1, target)
        gamma = np.sqrt(dot(perp_t, perp_t))
        n12 = cross(a1, a2)
        out = []
        for sgn in (-1.0, 1.0):  # z = α a1 − γ n12 gives sin(t2 − aligned) = +γ
            z = alpha[..., None] * a1 + (sgn * gamma)[..., None] * n12
            t2, _ = subproblem1(a2, a3, z)
            t1, cond = subproblem1(a1, z, target)
            t1 = np.where(cond > exact_singular**2, t1, 0.0)
            # t3 from a vector ⟂ a3: Rot(a3, t3)·a2 = (Rot(a1,t1)Rot(a2,t2))ᵀ · r · a2
            r12 = rotation(a1, t1) @ rotation(a2, t2)
            back = np.einsum("...ji,...j->...i", r12, r @ a2)
            t3, _ = subproblem1(a3, a2, back)
            out.append(np.stack([t1, t2, t3], -1))
        return np.stack(out, 0), gamma
