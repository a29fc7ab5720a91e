"""One pose of the 6R spherical-wrist IK in plain Python floats (``calib.ik.solve_all``'s fast path).

``calib.ik_spherical_wrist.WristArmGeometry.solve`` is vectorised over poses; for one pose its
time goes into a few hundred numpy calls on 3-vectors. ``WristArmScalar.solve`` repeats the same
closed form (same equations, same branch order b = 4·shoulder + 2·elbow + wrist) with the
``math`` module on tuples, and only for the plain case: it returns ``None`` — "use the
vectorised path" — whenever the pose is out of reach or within ``FALLBACK_MARGIN`` of a
singularity, so messages, representatives and duplicate handling there stay the vectorised
solver's alone. Away from singularities the 8 branches are distinct by far more than
``calib.ik.DUPLICATE_TOLERANCE_RAD`` (each pair differs in a root pair φ ± β with sin β above
the margin), so no duplicate test is needed.

Vectors are 3-tuples (mm or unit), angles rad.
"""

from __future__ import annotations

import math

from calib.ik_spherical_wrist import WristArmGeometry

#: Poses nearer than this to a singularity (rad, or mm for the shoulder) or to the reach boundary
#: (relative) are left to the vectorised solver. 100× its ``SINGULAR_TOLERANCE``: rounding
#: differences between the two paths can never put a pose on different sides of that flag.
FALLBACK_MARGIN = 1e-4

Vec = tuple[float, float, float]


def _t(v) -> Vec:
    return (float(v[0]), float(v[1]), float(v[2]))


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _perp(w: Vec, v: Vec) -> Vec:
    k = _dot(w, v)
    return (v[0] - k * w[0], v[1] - k * w[1], v[2] - k * w[2])


def _rotate(w: Vec, angle: float, v: Vec) -> Vec:
    """Rodrigues: v rotated about unit w by angle."""
    c, s = math.cos(angle), math.sin(angle)
    x = _cross(w, v)
    k = _dot(w, v) * (1.0 - c)
    return (v[0] * c + x[0] * s + w[0] * k, v[1] * c + x[1] * s + w[1] * k, v[2] * c + x[2] * s + w[2] * k)


def _angle_about(w: Vec, p: Vec, q: Vec) -> float:
    """Subproblem 1: the angle rotating p onto q about unit w (components ⟂ w)."""
    pp, qq = _perp(w, p), _perp(w, q)
    return math.atan2(_dot(w, _cross(pp, qq)), _dot(pp, qq))


def _roots(a: float, b: float, d: float) -> tuple[float, float, float, float]:
    """``a cos t + b sin t = d`` → (plus, minus, r, ratio = d / r); plus/minus are NaN when
    |ratio| > 1 (no real root) and the ratio is infinite when r = 0."""
    r = math.hypot(a, b)
    if r <= 1e-300:
        return math.nan, math.nan, r, math.inf
    ratio = d / r
    if abs(ratio) > 1.0:
        return math.nan, math.nan, r, ratio
    phi = math.atan2(b, a)
    beta = math.acos(ratio)
    return phi + beta, phi - beta, r, ratio


def _mat_t_vec(m: tuple[Vec, Vec, Vec], v: Vec) -> Vec:
    """mᵀ v for m given as rows."""
    return (
        m[0][0] * v[0] + m[1][0] * v[1] + m[2][0] * v[2],
        m[0][1] * v[0] + m[1][1] * v[1] + m[2][1] * v[2],
        m[0][2] * v[0] + m[1][2] * v[1] + m[2][2] * v[2],
    )


def _rot_rows(w: Vec, angle: float) -> tuple[Vec, Vec, Vec]:
    """Rotation matrix about unit w by angle, as rows."""
    c, s = math.cos(angle), math.sin(angle)
    t = 1.0 - c
    x, y, z = w
    return (
        (c + x * x * t, x * y * t - z * s, x * z * t + y * s),
        (y * x * t + z * s, c + y * y * t, y * z * t - x * s),
        (z * x * t - y * s, z * y * t + x * s, c + z * z * t),
    )


def _mat_mul(a: tuple[Vec, Vec, Vec], b: tuple[Vec, Vec, Vec]) -> tuple[Vec, Vec, Vec]:
    cols = tuple(zip(*b))
    return tuple(tuple(_dot(row, col) for col in cols) for row in a)  # type: ignore[return-value]


def _wrap(a: float) -> float:
    return math.pi - (math.pi - a) % (2 * math.pi)


class WristArmScalar:
    """``WristArmGeometry`` as plain floats, for one pose at a time."""

    def __init__(self, g: WristArmGeometry) -> None:
        w, p = g.axes.omega, g.axes.points
        self.w = [_t(x) for x in w]
        self.p = [_t(x) for x in p]
        hi = g.axes.home_inv
        self.home_inv_rot = tuple(_t(hi[i, :3]) for i in range(3))
        c0 = _t(g.wrist_centre)
        self.c0 = c0
        # the wrist centre as the home-inverse carries it: c = R_pose · c0h + p_pose
        self.c0h = tuple(float(_dot(self.home_inv_rot[i], c0) + hi[i, 3]) for i in range(3))
        self.n12 = _cross(self.w[0], self.w[1])
        self.lateral = float(g.lateral)
        self.facing_sign = float(g.facing_sign)
        self.elbow_up_sign = float(g.elbow_up_sign)
        # subproblem 3 about axis 3 (A cos t + B sin t = K − dist²/2), constants of the geometry
        w2, p1, p2 = self.w[2], self.p[1], self.p[2]
        x = (c0[0] - p2[0], c0[1] - p2[1], c0[2] - p2[2])
        y = (p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2])
        xp, yp = _perp(w2, x), _perp(w2, y)
        xa, ya = _dot(w2, x), _dot(w2, y)
        self.el_a = _dot(xp, yp)
        self.el_b = _dot(_cross(w2, xp), yp)
        self.el_k = (_dot(x, x) + _dot(y, y)) / 2.0 - xa * ya - 0.5 * (xa - ya) ** 2
        self.c0_from_p2 = x
        tr = g.wrist
        self.a1, self.a2, self.a3 = _t(tr.a1), _t(tr.a2), _t(tr.a3)
        self.wn12 = _cross(self.a1, self.a2)

    def solve(self, rot: tuple[Vec, Vec, Vec], pos: Vec) -> list[list[float] | None] | None:
        """The 8 branches for the flange pose ``rot`` (rows) and ``pos`` (mm), wrapped to (−π, π];
        an entry is None where the branch does not exist (its elbow is out of reach). Returns None
        when the pose needs the vectorised solver (see the module docstring)."""
        w, p = self.w, self.p
        r_rel = _mat_mul(rot, self.home_inv_rot)
        c = tuple(_dot(rot[i], self.c0h) + pos[i] for i in range(3))
        # --- A1 ---
        v = (c[0] - p[0][0], c[1] - p[0][1], c[2] - p[0][2])
        sh = _roots(_dot(v, w[1]), _dot(v, self.n12), self.lateral)
        # out of reach, or near it, or the wrist centre (near) the shoulder's singular surface
        if abs(sh[3]) > 1.0 - FALLBACK_MARGIN or sh[2] * math.sqrt(1.0 - sh[3] ** 2) < FALLBACK_MARGIN:
            return None
        q1_pair = (sh[1], sh[0]) if self.facing_sign > 0 else (sh[0], sh[1])
        out: list[list[float] | None] = []
        w0, w1, w2, p0, p1, p2 = w[0], w[1], w[2], p[0], p[1], p[2]
        any_arm = False
        for q1 in q1_pair:
            # --- A3 ---
            cr = _rotate(w0, -q1, v)
            c1 = (cr[0] + p0[0], cr[1] + p0[1], cr[2] + p0[2])
            to_c1 = (c1[0] - p1[0], c1[1] - p1[1], c1[2] - p1[2])
            d = _perp(w1, to_c1)
            el = _roots(self.el_a, self.el_b, self.el_k - _dot(d, d) / 2.0)
            if abs(el[3]) > 1.0 + FALLBACK_MARGIN:
                out.extend([None] * 4)  # this shoulder root's elbow cannot reach: its branches are absent
                continue
            if abs(el[3]) > 1.0 - FALLBACK_MARGIN:
                return None  # elbow (near) stretched or folded, or at the reach boundary
            any_arm = True
            q3_pair = (el[0], el[1]) if self.elbow_up_sign > 0 else (el[1], el[0])
            for q3 in q3_pair:
                # --- A2 ---
                mv = _rotate(w2, q3, self.c0_from_p2)
                moved = (mv[0] + p2[0] - p1[0], mv[1] + p2[1] - p1[1], mv[2] + p2[2] - p1[2])
                q2 = _angle_about(w1, moved, to_c1)
                # --- A4..A6 ---
                r123 = _mat_mul(_mat_mul(_rot_rows(w0, q1), _rot_rows(w1, q2)), _rot_rows(w2, q3))
                wrist = self._decompose(r123, r_rel)
                if wrist is None:
                    return None
                for t4, t5, t6 in wrist:
                    out.append([_wrap(q1), _wrap(q2), _wrap(q3), _wrap(t4), _wrap(t5), _wrap(t6)])
        return out if any_arm else None

    def _decompose(self, r123: tuple[Vec, Vec, Vec], r_rel: tuple[Vec, Vec, Vec]):
        """Both (t4, t5, t6) with Rot(a1,t4)Rot(a2,t5)Rot(a3,t6) = r123ᵀ·r_rel (noflip first),
        or None near the wrist singularity."""
        a1, a2, a3 = self.a1, self.a2, self.a3
        # r = r123ᵀ r_rel; r·a and friends without forming r
        target = _mat_t_vec(r123, tuple(_dot(row, a3) for row in r_rel))
        r_a2 = _mat_t_vec(r123, tuple(_dot(row, a2) for row in r_rel))
        alpha = _dot(target, a1)
        pt = _cross(a1, target)
        gamma = math.sqrt(_dot(pt, pt))
        if gamma < FALLBACK_MARGIN:
            return None
        n = self.wn12
        out = []
        for sgn in (-1.0, 1.0):
            g = sgn * gamma
            z = (alpha * a1[0] + g * n[0], alpha * a1[1] + g * n[1], alpha * a1[2] + g * n[2])
            t2 = _angle_about(a2, a3, z)
            t1 = _angle_about(a1, z, target)
            r12 = _mat_mul(_rot_rows(a1, t1), _rot_rows(a2, t2))
            t3 = _angle_about(a3, a2, _mat_t_vec(r12, r_a2))
            out.append((t1, t2, t3))
        return out
