"""One pose of the 6R spherical-wrist IK in plain Python floats (``calib.ik.ik.solve_all``'s fast path).

``calib.ik.ik_spherical_wrist.WristArmGeometry.solve`` is vectorised over poses; for one pose its
time goes into a few hundred numpy calls on 3-vectors. ``WristArmScalar.solve`` repeats the same
closed form (same equations, same branch order b = 4·shoulder + 2·elbow + wrist; the wrist
flip comes from the noflip solution by a half-turn identity) with the ``math`` module on tuples, and only for the plain case: it returns ``None`` — "use the
vectorised path" — whenever the pose is out of reach or near a singularity (``FALLBACK_MARGIN``,
``RATIO_MARGIN``) or a joint lands within 1e-9 rad of ±π, so messages, representatives and duplicate handling there stay the vectorised
solver's alone. Away from singularities the 8 branches are distinct by far more than
``calib.ik.ik.DUPLICATE_TOLERANCE_RAD`` (each pair differs in a root pair φ ± β with sin β above
the margin), so no duplicate test is needed.

Vectors are 3-tuples (mm or unit), angles rad.
"""

from __future__ import annotations

import math

from calib.ik.ik_spherical_wrist import WristArmGeometry
from calib.ik.ik_srs import SrsGeometry
from calib.ik.ik_subproblems import SphericalTriple

#: Poses nearer than this to a singularity (rad, or mm for the shoulder) are left to the
#: vectorised solver. 100× its ``SINGULAR_TOLERANCE``: rounding differences between the two
#: paths can never put a pose on different sides of that flag.
FALLBACK_MARGIN = 1e-4
#: The same for a root pair's ratio |d / r| (1 where the roots coincide): within this of 1 is
#: left to the vectorised solver (sin β < 4.5e-5, far above the flag's 1e-6; its reach test
#: allows 1e-12).
RATIO_MARGIN = 1e-9

#: A wrapped angle this close to ±π (rad) sends the pose to the vectorised solver.
_NEAR_PI = math.pi - 1e-9
_PI, _TWO_PI = math.pi, 2.0 * math.pi


def _wrap(a: float) -> float:
    """a wrapped to (−π, π] (left as it is when already there)."""
    return a if -_PI < a <= _PI else _PI - (_PI - a) % _TWO_PI

Vec = tuple[float, float, float]


def _t(v) -> Vec:
    return (float(v[0]), float(v[1]), float(v[2]))


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _apply(rows: tuple[Vec, Vec, Vec], v: Vec) -> Vec:
    """The matrix with rows ``rows`` times v."""
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = rows
    v0, v1, v2 = v
    return (a0 * v0 + a1 * v1 + a2 * v2, b0 * v0 + b1 * v1 + b2 * v2, c0 * v0 + c1 * v1 + c2 * v2)


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _perp(w: Vec, v: Vec) -> Vec:
    k = _dot(w, v)
    return (v[0] - k * w[0], v[1] - k * w[1], v[2] - k * w[2])


def _rotate(w: Vec, angle: float, v: Vec) -> Vec:
    """Rodrigues: v rotated about unit w by angle (written out: this runs ~30 times a pose)."""
    c, s = math.cos(angle), math.sin(angle)
    w0, w1, w2 = w
    v0, v1, v2 = v
    k = (w0 * v0 + w1 * v1 + w2 * v2) * (1.0 - c)
    return (
        v0 * c + (w1 * v2 - w2 * v1) * s + w0 * k,
        v1 * c + (w2 * v0 - w0 * v2) * s + w1 * k,
        v2 * c + (w0 * v1 - w1 * v0) * s + w2 * k,
    )


def _angle_about(w: Vec, p: Vec, q: Vec) -> float:
    """Subproblem 1: the angle rotating p onto q about unit w (components ⟂ w)."""
    w0, w1, w2 = w
    kp = w0 * p[0] + w1 * p[1] + w2 * p[2]
    kq = w0 * q[0] + w1 * q[1] + w2 * q[2]
    p0, p1, p2 = p[0] - kp * w0, p[1] - kp * w1, p[2] - kp * w2
    q0, q1, q2 = q[0] - kq * w0, q[1] - kq * w1, q[2] - kq * w2
    return math.atan2(
        w0 * (p1 * q2 - p2 * q1) + w1 * (p2 * q0 - p0 * q2) + w2 * (p0 * q1 - p1 * q0), p0 * q0 + p1 * q1 + p2 * q2
    )


#: An axis whose other two components are below this (and the third ±1 to it) is taken as a
#: coordinate axis: DH axes at home are, up to cos 90° = 6e-17.
_COORDINATE_AXIS_TOLERANCE = 1e-15


def _axis_ops(w: Vec):
    """(rotate(angle, v), angle_about(p, q)): ``_rotate`` and ``_angle_about`` about the unit
    axis w, written out for w = ±x, ±y, ±z (a third of the general formulas' arithmetic)."""
    k = max(range(3), key=lambda i: abs(w[i]))
    sign = math.copysign(1.0, w[k])
    if abs(w[k] - sign) > _COORDINATE_AXIS_TOLERANCE or max(abs(w[(k + 1) % 3]), abs(w[(k + 2) % 3])) > _COORDINATE_AXIS_TOLERANCE:
        return (lambda angle, v: _rotate(w, angle, v)), (lambda p, q: _angle_about(w, p, q))
    cos, sin, atan2 = math.cos, math.sin, math.atan2
    if k == 0:

        def rotate(angle: float, v: Vec) -> Vec:
            c, s = cos(angle), sign * sin(angle)
            return (v[0], c * v[1] - s * v[2], s * v[1] + c * v[2])

        def angle_about(p: Vec, q: Vec) -> float:
            return atan2(sign * (p[1] * q[2] - p[2] * q[1]), p[1] * q[1] + p[2] * q[2])

    elif k == 1:

        def rotate(angle: float, v: Vec) -> Vec:
            c, s = cos(angle), sign * sin(angle)
            return (c * v[0] + s * v[2], v[1], c * v[2] - s * v[0])

        def angle_about(p: Vec, q: Vec) -> float:
            return atan2(sign * (p[2] * q[0] - p[0] * q[2]), p[2] * q[2] + p[0] * q[0])

    else:

        def rotate(angle: float, v: Vec) -> Vec:
            c, s = cos(angle), sign * sin(angle)
            return (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])

        def angle_about(p: Vec, q: Vec) -> float:
            return atan2(sign * (p[0] * q[1] - p[1] * q[0]), p[0] * q[0] + p[1] * q[1])

    return rotate, angle_about


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


class _Triple:
    """``calib.ik.ik_subproblems.SphericalTriple`` as floats: three intersecting axes a1 ⟂ a2 ⟂ a3."""

    def __init__(self, triple: SphericalTriple, turn: tuple[Vec, float] | None = None) -> None:
        """``turn`` = (w, angle): the triple with its axes turned by Rot(w, angle) = Q, whose
        ``decompose(Q·x, Q·y)`` gives the angles the unturned one gives for (x, y) (the
        subproblems only use dot and cross products, which a rotation of every vector keeps)."""
        axes = [_t(triple.a1), _t(triple.a2), _t(triple.a3)]
        if turn is not None:
            axes = [_rotate(turn[0], turn[1], a) for a in axes]
        self.a1, self.a2, self.a3 = axes
        (self.rot1, self.ang1), (self.rot2, self.ang2), (_, self.ang3) = (_axis_ops(a) for a in axes)
        self.n12 = _cross(self.a1, self.a2)
        self.aligned = float(triple.aligned)

    def decompose(self, target: Vec, r_a2: Vec) -> list[tuple[float, float, float]] | None:
        """Both (t1, t2, t3) with Rot(a1,t1)Rot(a2,t2)Rot(a3,t3) = R (branch 0: sin(t2 − aligned)
        > 0), given target = R·a3 and r_a2 = R·a2; None within ``FALLBACK_MARGIN`` of the singularity."""
        a1, a2, a3 = self.a1, self.a2, self.a3
        alpha = _dot(target, a1)
        pt = _cross(a1, target)
        gamma = math.sqrt(_dot(pt, pt))
        if gamma < FALLBACK_MARGIN:
            return None
        n = self.n12
        # branch 0: z = α a1 − γ (a1 × a2), so sin(t2 − aligned) = +γ
        z = (alpha * a1[0] - gamma * n[0], alpha * a1[1] - gamma * n[1], alpha * a1[2] - gamma * n[2])
        t2 = self.ang2(a3, z)
        t1 = self.ang1(z, target)
        # t3 from a vector ⟂ a3: Rot(a3, t3)·a2 = (Rot(a1,t1)Rot(a2,t2))ᵀ · R·a2
        t3 = self.ang3(a2, self.rot2(-t2, self.rot1(-t1, r_a2)))
        # branch 1: Rot(a1,π)·Rot(a3,π) = Rot(a2, 2·aligned) (half-turns about two axes ⟂ a2)
        # turns branch 0 into (t1 + π, 2·aligned − t2, t3 + π), here wrapped to (−π, π] (t1 ± π, t3 ± π)
        return [(t1, t2, t3), (t1 - _PI if t1 > 0.0 else t1 + _PI, _wrap(2.0 * self.aligned - t2), t3 - _PI if t3 > 0.0 else t3 + _PI)]


def _wrap_row(row: list[float]) -> list[float] | None:
    """Angles wrapped to (−π, π] (the solvers wrap as they go: usually there already); None if
    one lands within 1e-9 of ±π, where the two paths may round it to either end."""
    if max(row) < _NEAR_PI and min(row) > -_NEAR_PI:
        return row
    out = [_wrap(a) for a in row]
    if max(out) > _NEAR_PI or min(out) < -_NEAR_PI:
        return None
    return out


class WristArmScalar:
    """``WristArmGeometry`` as plain floats, for one pose at a time."""

    #: branches 2i and 2i + 1 (wrist noflip, flip) share A1..A3
    shared_joints = 3

    def __init__(self, g: WristArmGeometry) -> None:
        w, p = g.axes.omega, g.axes.points
        self.w = [_t(x) for x in w]
        self.p = [_t(x) for x in p]
        self.ops = [_axis_ops(x) for x in self.w[:3]]  # (rotate, angle_about) about A1..A3
        hi = g.axes.home_inv
        c0 = _t(g.wrist_centre)
        # the wrist centre as the home-inverse carries it: c = R_pose · c0h + p_pose
        self.c0h = _t(hi[:3, :3] @ g.wrist_centre + hi[:3, 3])
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
        self.wrist = _Triple(tr)
        # R_home⁻¹·a2 and R_home⁻¹·a3: R_rel·a = R_pose·(R_home⁻¹·a)
        self.home_inv_a2, self.home_inv_a3 = _t(hi[:3, :3] @ tr.a2), _t(hi[:3, :3] @ tr.a3)

    def solve(self, rot: tuple[Vec, Vec, Vec], pos: Vec) -> list[list[float] | None] | None:
        """The 8 branches for the flange pose ``rot`` (rows) and ``pos`` (mm), wrapped to (−π, π];
        an entry is None where the branch does not exist (its elbow is out of reach). Returns None
        when the pose needs the vectorised solver (see the module docstring)."""
        w1 = self.w[1]
        (rot0, _), (rot1, ang1), (rot2, _) = self.ops
        p0, p1, p2 = self.p[0], self.p[1], self.p[2]
        c0h, ha2, ha3 = self.c0h, self.home_inv_a2, self.home_inv_a3
        # the relative rotation R_rel = rot · R_home⁻¹ is only needed applied to the wrist's a2, a3
        rel_a2, rel_a3 = _apply(rot, ha2), _apply(rot, ha3)
        # --- A1 --- (v: wrist centre from the point on axis 1)
        c = _apply(rot, c0h)
        v = (c[0] + pos[0] - p0[0], c[1] + pos[1] - p0[1], c[2] + pos[2] - p0[2])
        sh = _roots(_dot(v, w1), _dot(v, self.n12), self.lateral)
        # out of reach, or near it, or the wrist centre (near) the shoulder's singular surface
        if abs(sh[3]) > 1.0 - RATIO_MARGIN or sh[2] * math.sqrt(1.0 - sh[3] ** 2) < FALLBACK_MARGIN:
            return None
        q1_pair = (_wrap(sh[1]), _wrap(sh[0])) if self.facing_sign > 0 else (_wrap(sh[0]), _wrap(sh[1]))
        out: list[list[float] | None] = []
        any_arm = False
        for q1 in q1_pair:
            # --- A3 --- (the wrist centre with A1 undone, seen from axis 2)
            cr = rot0(-q1, v)
            to_c1 = (cr[0] + p0[0] - p1[0], cr[1] + p0[1] - p1[1], cr[2] + p0[2] - p1[2])
            d = _perp(w1, to_c1)
            el = _roots(self.el_a, self.el_b, self.el_k - _dot(d, d) / 2.0)
            if abs(el[3]) > 1.0 + RATIO_MARGIN:
                out.extend([None] * 4)  # this shoulder root's elbow cannot reach: its branches are absent
                continue
            if abs(el[3]) > 1.0 - RATIO_MARGIN:
                return None  # elbow (near) stretched or folded, or at the reach boundary
            any_arm = True
            q3_pair = (_wrap(el[0]), _wrap(el[1])) if self.elbow_up_sign > 0 else (_wrap(el[1]), _wrap(el[0]))
            # R123ᵀ·x = Rot(w3, −q3) Rot(w2, −q2) Rot(w1, −q1) x: the first turn is shared
            b_a3, b_a2 = rot0(-q1, rel_a3), rot0(-q1, rel_a2)
            for q3 in q3_pair:
                # --- A2 ---
                mv = rot2(q3, self.c0_from_p2)
                moved = (mv[0] + p2[0] - p1[0], mv[1] + p2[1] - p1[1], mv[2] + p2[2] - p1[2])
                q2 = ang1(moved, to_c1)
                # --- A4..A6 --- on the wrist rotation R123ᵀ·R_rel, through its images of a3 and a2
                target = rot2(-q3, rot1(-q2, b_a3))
                r_a2 = rot2(-q3, rot1(-q2, b_a2))
                wrist = self.wrist.decompose(target, r_a2)
                if wrist is None:
                    return None
                for t4, t5, t6 in wrist:
                    row = _wrap_row([q1, q2, q3, t4, t5, t6])
                    if row is None:
                        return None
                    out.append(row)
        return out if any_arm else None


class SrsScalar:
    """``SrsGeometry`` as plain floats, for one pose at a given arm angle (same equations and
    branch order b = 4·[GC2 < 0] + 2·[GC4 < 0] + [GC6 < 0] as ``SrsGeometry.solve``)."""

    #: branches 2i and 2i + 1 (GC6 = ±1) share A1..A4
    shared_joints = 4

    def __init__(self, g: SrsGeometry) -> None:
        w, p = g.axes.omega, g.axes.points
        self.w = [_t(x) for x in w]
        hi = g.axes.home_inv
        self.w0h = _t(hi[:3, :3] @ g.wrist_point + hi[:3, 3])  # wrist point: W = R_pose · w0h + p_pose
        self.shoulder = _t(g.shoulder)
        self.facing = _t(g.facing)
        self.q3_ref = float(g.q3_ref)
        self.p4 = _t(p[3])
        self.wp_from_p4 = _t(g.wrist_point - p[3])
        # subproblem 3 about axis 4: A cos q4 + B sin q4 = K − |W − S|²/2
        w3 = self.w[3]
        x, y = self.wp_from_p4, _t(g.shoulder - p[3])
        xp, yp = _perp(w3, x), _perp(w3, y)
        self.el_a = _dot(xp, yp)
        self.el_b = _dot(_cross(w3, xp), yp)
        self.el_k = (_dot(x, x) + _dot(y, y)) / 2.0 - _dot(w3, x) * _dot(w3, y)
        self.n12 = _cross(self.w[0], self.w[1])
        self.shoulder_triple = _Triple(g.shoulder_triple)
        self.home_inv_a2 = _t(hi[:3, :3] @ g.wrist_triple.a2)
        self.home_inv_a3 = _t(hi[:3, :3] @ g.wrist_triple.a3)
        # The reference shoulder ends in the fixed Rot(ω3, q3_ref) = Q; folded into constants:
        # Q·Rot(ω4, q4)·x = Rot(Q·ω4, q4)·Q·x, the shoulder axes' images Q·a, and the wrist
        # triple turned by Q, ``wrist_triple_q`` (it decomposes Q·(R_s R4)ᵀ·R_rel, so Qᵀ is never applied).
        w2, q3 = self.w[2], self.q3_ref
        self.w3_ref = _rotate(w2, q3, w3)
        self.wp_ref = _rotate(w2, q3, self.wp_from_p4)
        self.p4_ref = _rotate(w2, q3, (self.p4[0] - self.shoulder[0], self.p4[1] - self.shoulder[1], self.p4[2] - self.shoulder[2]))
        self.sa2_ref = _rotate(w2, q3, self.shoulder_triple.a2)
        self.sa3_ref = _rotate(w2, q3, self.shoulder_triple.a3)
        self.wrist_triple = _Triple(g.wrist_triple)
        self.wrist_triple_q = _Triple(g.wrist_triple, turn=(w2, q3))
        self.ops = [_axis_ops(x) for x in (self.w[0], self.w[1], self.w3_ref)]  # about A1, A2, Q·A4

    def _reference(self, q4: float, v: Vec, alpha: float | None = None) -> tuple[float, float] | None:
        """(a, b): the A1, A2 of the reference shoulder rotation R_ref = Rot(ω1,a)Rot(ω2,b)Rot(ω3,q3_ref)
        for elbow angle q4 and S→W vector v (alpha = v·ω1 if known), the root whose shoulder
        faces W; None when the two roots face it (nearly) alike."""
        w0, w1 = self.w[0], self.w[1]
        if alpha is None:
            alpha = _dot(v, w0)
        (rot0, ang0), (_, ang1), (rot3, _) = self.ops
        ur, c = rot3(q4, self.wp_ref), self.p4_ref
        u = (ur[0] + c[0], ur[1] + c[1], ur[2] + c[2])  # Rot(ω3, q3_ref)·(W − S) at A1 = A2 = 0
        beta = _dot(u, w1)
        gamma = math.sqrt(max(_dot(u, u) - alpha * alpha - beta * beta, 0.0))
        n = self.n12
        roots = []
        for sgn in (1.0, -1.0):
            g = sgn * gamma
            z = (alpha * w0[0] + beta * w1[0] + g * n[0], alpha * w0[1] + beta * w1[1] + g * n[1],
                 alpha * w0[2] + beta * w1[2] + g * n[2])
            a = ang0(z, v)
            roots.append((_dot(rot0(a, self.facing), v), a, z))
        (face0, a0, z0), (face1, a1, z1) = roots
        if abs(face1 - face0) < FALLBACK_MARGIN:
            return None
        a, z = (a1, z1) if face1 > face0 else (a0, z0)
        return a, ang1(u, z)

    def solve(self, rot: tuple[Vec, Vec, Vec], pos: Vec, psi: float) -> list[list[float]] | None:
        """The 8 global configurations for the flange pose ``rot`` (rows) and ``pos`` (mm) at arm
        angle ``psi`` rad, wrapped to (−π, π]; None when the pose needs the vectorised solver: out
        of reach, or near the elbow, shoulder or wrist singularity or the wrist point near axis 1."""
        w0 = self.w[0]
        (rot0, _), (rot1, _), (rot3, _) = self.ops
        s = self.shoulder
        wp = _apply(rot, self.w0h)
        v = (wp[0] + pos[0] - s[0], wp[1] + pos[1] - s[1], wp[2] + pos[2] - s[2])
        vv = _dot(v, v)
        el = _roots(self.el_a, self.el_b, self.el_k - vv / 2.0)
        if abs(el[3]) > 1.0 - RATIO_MARGIN:
            return None  # out of reach, or the elbow (near) stretched
        off = _perp(w0, v)
        if _dot(off, off) < FALLBACK_MARGIN**2:
            return None  # the wrist point (near) axis 1: the reference plane is undefined
        alpha = _dot(v, w0)
        norm_v = math.sqrt(vv)
        axis = (v[0] / norm_v, v[1] / norm_v, v[2] / norm_v)
        ha2, ha3 = self.home_inv_a2, self.home_inv_a3
        # Rot(v̂, −ψ)·R_rel·a for the wrist's a2, a3 (the first turn of (R_s R4)ᵀ, the same for both elbow roots)
        rel_a2, rel_a3 = _rotate(axis, -psi, _apply(rot, ha2)), _rotate(axis, -psi, _apply(rot, ha3))
        sa2, sa3 = self.sa2_ref, self.sa3_ref
        out: list[list[float] | None] = [None] * 8
        for g4, q4 in enumerate((_wrap(el[1]), _wrap(el[0]))):  # GC4 = +1: the "−" root
            ref = self._reference(q4, v, alpha)
            if ref is None:
                return None
            a, b = ref
            # R_s = Rot(v̂, ψ)·R_ref: the shoulder triple's images R_s·a3, R_s·a2
            s3 = _rotate(axis, psi, rot0(a, rot1(b, sa3)))
            s2 = _rotate(axis, psi, rot0(a, rot1(b, sa2)))
            shoulder = self.shoulder_triple.decompose(s3, s2)
            # the wrist rotation (R_s R4)ᵀ·R_rel is the same for both shoulder roots: one decomposition,
            # of Q·(R_s R4)ᵀ·R_rel = Rot(Q·ω4, −q4)·Rot(ω2, −b)·Rot(ω1, −a)·Rot(v̂, −ψ)·R_rel (triple turned by Q)
            m3 = rot3(-q4, rot1(-b, rot0(-a, rel_a3)))
            m2 = rot3(-q4, rot1(-b, rot0(-a, rel_a2)))
            wrist = self.wrist_triple_q.decompose(m3, m2)
            if shoulder is None or wrist is None:
                return None
            for g2, (t1, t2, t3) in enumerate(shoulder):
                for g6, (t5, t6, t7) in enumerate(wrist):
                    row = _wrap_row([t1, t2, t3, q4, t5, t6, t7])
                    if row is None:
                        return None
                    out[4 * g2 + 2 * g4 + g6] = row
        return out
