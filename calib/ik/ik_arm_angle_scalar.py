"""One pose's feasible 7R arm angles in plain Python floats (``calib.ik.ik.solve_all``'s fast path
for ``arm_angle=None``).

``calib.ik.ik_srs.SrsGeometry.limit_crossings`` and ``calib.ik.ik._intervals_many`` are vectorised
over poses; for one pose their time goes into a few hundred numpy calls on 3-vectors and a full
solve at every gap between crossings. ``SrsArmAngleScalar.pose`` repeats the same closed form
with the ``math`` module (Shimizu et al. 2008, in the notation of ``calib.ik.ik_srs``):

- for each elbow root q4 and each spherical triple (shoulder A1–A3, wrist A5–A7) the five
  scalars the triple's angles are read from — ``f2 = a1ᵀRa3 = cos(t2 − aligned)``,
  ``n1 = a2ᵀRa3`` and ``d1 = −(a1 × a2)ᵀRa3`` (``t1 = atan2(n1, d1)``), ``n3 = a1ᵀRa2`` and
  ``d3 = a1ᵀR(a3 × a2)`` (``t3 = atan2(n3, d3)``), the other branch being
  ``(t1 + π, 2·aligned − t2, t3 + π)`` — are sinusoids ``a sin ψ + b cos ψ + c`` of the arm
  angle, as ``R_s(ψ) = Rot(ŝw, ψ)·R_ref`` and ``R_w(ψ) = R4ᵀ·R_s(ψ)ᵀ·R_rel``;
- a joint of the triple meets a limit (or t2 the singular angle, where t1 and t3 jump) at the
  roots of one such sinusoid: the equations and roots of ``limit_crossings``;
- between consecutive roots of its own equations a triple's feasibility cannot change: it is
  read once per such gap from the five scalars (no rotation matrix, no full solve);
- some configuration is feasible where, for an elbow root within limits, some shoulder branch
  and some wrist branch are: the union over the 8 configurations that ``calib.ik.ik`` merges.

``PoseArmAngles`` holds the roots where that union's feasibility changes, the feasibility of
each gap between them (what ``calib.ik.ik._gap_intervals`` turns into intervals, as for the
vectorised path) and, for the arm angle picked from them, the configurations read off the same
sinusoids.

Only the plain case: ``pose`` and ``PoseArmAngles.configurations`` return None — "use the
vectorised path" — out of reach or near a singularity (``calib.ik.ik_scalar``'s margins), near a
tangency (a root pair within ``RATIO_MARGIN``), with two roots within ``CUT_MARGIN`` of each
other or of ±π, or a joint within ``LIMIT_MARGIN_RAD`` of a limit where feasibility is read;
rounding differences between the two paths then never change which gaps are feasible. One
exception by construction: equations that coincide for the model (A2's and A6's limits
symmetric about the singular angle, as on the iiwa: ``cos(lo − aligned) = cos(hi − aligned)``)
are solved once, where the vectorised path finds the same root twice a few 1e-16 rad apart.

Angles rad, vectors 3-tuples (mm or unit).
"""

from __future__ import annotations

import math

from calib.ik.ik_scalar import FALLBACK_MARGIN, RATIO_MARGIN, SrsScalar, Vec, _cross, _dot, _roots, _rotate
from calib.ik.ik_srs import SrsGeometry

#: Two distinct crossings nearer than this (rad, on the circle), or one this near ±π, send the
#: pose to the vectorised path: which side of them a gap lies on is decided by rounding there.
CUT_MARGIN = 1e-9
#: A joint this near (rad) an edge of its feasible window where feasibility is read sends the
#: pose to the vectorised path (as ``calib.ik.ik._ONE_POSE_LIMIT_MARGIN_RAD`` does for rows).
LIMIT_MARGIN_RAD = 1e-9
#: Equations whose constants agree to this are one equation (see the module docstring).
_SAME_EQUATION = 1e-12

_TWO_PI = 2.0 * math.pi
_NEAR_PI = math.pi - CUT_MARGIN

#: A sinusoid a sin ψ + b cos ψ + c, as (a, b, c).
Sinusoid = tuple[float, float, float]
#: A joint's window of feasible wrapped angles (rad) as (lo + margin, hi − margin, lo − margin,
#: hi + margin): clearly inside between the first two, undecided out to the last two.
Window = tuple[float, float, float, float]


class _Undecided(Exception):
    """Internal: the float path cannot decide; the public methods return None."""


def _wrap(a: float) -> float:
    return math.pi - (math.pi - a) % _TWO_PI


def _sinusoid(k: Vec, a: Vec, b: Vec) -> Sinusoid:
    """(Rot(k, ψ)·a)·b = sin ψ (k × a)·b + cos ψ (a·b − (k·a)(k·b)) + (k·a)(k·b), unit k
    (written out: this runs 20 times a pose)."""
    k0, k1, k2 = k
    a0, a1, a2 = a
    b0, b1, b2 = b
    c = (k0 * a0 + k1 * a1 + k2 * a2) * (k0 * b0 + k1 * b1 + k2 * b2)
    return (
        (k1 * a2 - k2 * a1) * b0 + (k2 * a0 - k0 * a2) * b1 + (k0 * a1 - k1 * a0) * b2,
        a0 * b0 + a1 * b1 + a2 * b2 - c,
        c,
    )


def _at(x: Sinusoid, s: float, c: float) -> float:
    """The sinusoid's value where sin ψ = s, cos ψ = c."""
    return x[0] * s + x[1] * c + x[2]


def _windows(breaks: list[float], fits: list[list]) -> list[Window]:
    """The wrapped angles (−π, π] a joint may take, from ``calib.ik.ik._fitting_steps``' breaks
    and per-stretch fitting ±360° steps (±inf at the ends; adjacent feasible stretches are one
    window)."""
    edges = [-math.inf, *breaks, math.inf]
    out: list[list[float]] = []
    for i, fit in enumerate(fits):
        if not fit:
            continue
        if out and out[-1][1] == edges[i]:
            out[-1][1] = edges[i + 1]
        else:
            out.append([edges[i], edges[i + 1]])
    m = LIMIT_MARGIN_RAD
    return [(lo + m, hi - m, lo - m, hi + m) for lo, hi in out]


def _inside(x: float, windows: list[Window]) -> bool:
    """Whether the wrapped angle x (rad) lies in a window; raises ``_Undecided`` within
    ``LIMIT_MARGIN_RAD`` of a window's edge."""
    for inner_lo, inner_hi, outer_lo, outer_hi in windows:
        if inner_lo < x < inner_hi:
            return True
        if outer_lo <= x <= outer_hi:
            raise _Undecided
    return False


class _Triple:
    """One spherical triple's joint limits: per joint its windows; the limit equations as
    constants of the model — the values f2 takes at the middle joint's limits and at the
    singular angles (±1), (cos, sin) of each outer joint's limits — coinciding ones kept once."""

    def __init__(self, aligned: float, lower: list[float], upper: list[float], windows: list[list[Window]]) -> None:
        self.aligned = aligned
        self.windows = windows
        self.f2_values: list[float] = []
        for x in (math.cos(_wrap(lower[1]) - aligned), math.cos(_wrap(upper[1]) - aligned), 1.0, -1.0):
            if all(abs(x - y) > _SAME_EQUATION for y in self.f2_values):
                self.f2_values.append(x)
        self.outer_limits: list[list[tuple[float, float]]] = []  # first, third joint
        for j in (0, 2):
            lims: list[tuple[float, float]] = []
            for lim in (_wrap(lower[j]), _wrap(upper[j])):
                cl, sl = math.cos(lim), math.sin(lim)
                # the equation is "t = lim (mod π)": limits half a turn apart give one
                if all(abs(cl * ys - sl * yc) > _SAME_EQUATION for yc, ys in lims):
                    lims.append((cl, sl))
            self.outer_limits.append(lims)

    def crossings(self, f2: Sinusoid, n1: Sinusoid, d1: Sinusoid, n3: Sinusoid, d3: Sinusoid) -> list[float]:
        """Sorted distinct arm angles ψ (rad, wrapped) where a joint of the triple may meet a
        limit, or t2 the singular angle; raises ``_Undecided`` near a tangency, a degenerate
        equation or ±π."""
        eqs = [(f2[0], f2[1], f2[2] - x) for x in self.f2_values]
        for (n, d), lims in zip(((n1, d1), (n3, d3)), self.outer_limits):
            for cl, sl in lims:  # t = lim ⇔ n cos(lim) − d sin(lim) = 0
                eqs.append((n[0] * cl - d[0] * sl, n[1] * cl - d[1] * sl, n[2] * cl - d[2] * sl))
        out = set()
        for a, b, c in eqs:
            plus, minus, r, ratio = _roots(b, a, -c)  # b cos ψ + a sin ψ = −c
            if r < FALLBACK_MARGIN or abs(abs(ratio) - 1.0) < RATIO_MARGIN:
                raise _Undecided
            if abs(ratio) < 1.0:
                for root in (_wrap(plus), _wrap(minus)):
                    if abs(root) > _NEAR_PI:
                        raise _Undecided
                    out.add(root)
        return sorted(out)

    def gap_feasibility(self, cuts: list[float], sins: tuple[Sinusoid, ...]) -> list[bool]:
        """Per gap between the sorted crossings ``cuts`` (the last through ±π; one gap if there
        is none), whether either branch is within limits, read at the gap's middle from the
        sinusoids (f2, n1, d1, n3, d3). A joint is read only while its branch is still in
        question (written out: this runs ~25 times a pose)."""
        w1, w2, w3 = self.windows
        al = self.aligned
        (fa, fb, fc), (n1a, n1b, n1c), (d1a, d1b, d1c), (n3a, n3b, n3c), (d3a, d3b, d3c) = sins
        out = []
        for m in [0.5 * (lo + hi) for lo, hi in zip(cuts, [*cuts[1:], cuts[0] + _TWO_PI])] if cuts else [0.0]:
            s, c = math.sin(m), math.cos(m)
            x = fa * s + fb * c + fc
            beta = math.acos(1.0 if x > 1.0 else -1.0 if x < -1.0 else x)
            t2, t2_flip = al + beta, al - beta  # wrapped below: aligned ∈ (−π, π], β ∈ [0, π]
            ok0 = _inside(t2 - _TWO_PI if t2 > math.pi else t2, w2)
            ok1 = _inside(t2_flip + _TWO_PI if t2_flip <= -math.pi else t2_flip, w2)
            if ok0 or ok1:
                t1 = math.atan2(n1a * s + n1b * c + n1c, d1a * s + d1b * c + d1c)
                ok0 = ok0 and _inside(t1, w1)
                ok1 = ok1 and _inside(t1 - math.pi if t1 > 0.0 else t1 + math.pi, w1)
            if ok0 or ok1:
                t3 = math.atan2(n3a * s + n3b * c + n3c, d3a * s + d3b * c + d3c)
                ok0 = ok0 and _inside(t3, w3)
                ok1 = ok1 and _inside(t3 - math.pi if t3 > 0.0 else t3 + math.pi, w3)
            out.append(ok0 or ok1)
        return out

    @staticmethod
    def regular(s: float, c: float, f2: Sinusoid, n1: Sinusoid, d1: Sinusoid, n3: Sinusoid, d3: Sinusoid) -> tuple[float, float]:
        """(n1, d1) where sin ψ = s, cos ψ = c; raises ``_Undecided`` within ``FALLBACK_MARGIN``
        of the singularity (|sin(t2 − aligned)| = hypot(n1, d1); ``calib.ik.ik_scalar``'s hand-over)."""
        y1, x1 = _at(n1, s, c), _at(d1, s, c)
        if math.hypot(y1, x1) < FALLBACK_MARGIN:
            raise _Undecided
        return y1, x1

    def branches(self, s: float, c: float, f2: Sinusoid, n1: Sinusoid, d1: Sinusoid, n3: Sinusoid, d3: Sinusoid):
        """Both branches (t1, t2, t3), wrapped, where sin ψ = s, cos ψ = c, each None if a joint
        is outside its limits; raises ``_Undecided`` as ``regular`` and ``_inside_row``."""
        t1 = math.atan2(*self.regular(s, c, f2, n1, d1, n3, d3))
        t3 = math.atan2(_at(n3, s, c), _at(d3, s, c))
        beta = math.acos(min(1.0, max(-1.0, _at(f2, s, c))))
        al = self.aligned
        return (
            _inside_row([t1, _wrap(al + beta), t3], self.windows),
            _inside_row([_wrap(t1 + math.pi), _wrap(al - beta), _wrap(t3 + math.pi)], self.windows),
        )


def _inside_row(angles: list[float], windows: list[list[Window]]) -> list[float] | None:
    """The wrapped angles if each lies in its joint's windows, else None; raises ``_Undecided``
    near a window's edge or, inside, within ``LIMIT_MARGIN_RAD`` of ±π (the two paths may wrap
    such an angle to either end)."""
    for x, w in zip(angles, windows):
        if not _inside(x, w):
            return None
    if max(angles) > math.pi - LIMIT_MARGIN_RAD or min(angles) < -math.pi + LIMIT_MARGIN_RAD:
        raise _Undecided
    return angles


class SrsArmAngleScalar:
    """``SrsGeometry.limit_crossings`` and the gap feasibility of ``calib.ik.ik._intervals_many``
    as plain floats, for one pose at a time."""

    def __init__(self, g: SrsGeometry, scalar: SrsScalar, lower: list[float], upper: list[float], steps) -> None:
        """g, scalar: the model's closed form; lower, upper (7,) joint limits rad; steps: per
        joint the ±360° steps that fit (``calib.ik.ik._fitting_steps``)."""
        self.scalar = scalar
        windows = [_windows(breaks, fits) for breaks, fits in steps]
        self.elbow_windows = windows[3]
        self.shoulder = _Triple(float(g.shoulder_triple.aligned), lower[0:3], upper[0:3], windows[0:3])
        self.wrist = _Triple(float(g.wrist_triple.aligned), lower[4:7], upper[4:7], windows[4:7])
        st, wt = scalar.shoulder_triple, scalar.wrist_triple
        # shoulder scalars uᵀ·R_s·x: u ∈ {a1, a2, a1 × a2} fixed, x ∈ {a3, a2, a3 × a2} turned by
        # R_ref = Rot(ω1, a)·Rot(ω2, b)·Rot(ω3, q3_ref), whose last factor is fixed too
        # (rotations carry cross products along: R·(a × b) = R·a × R·b)
        self.shoulder_u = (st.a1, st.a2, st.n12)
        self.shoulder_x = tuple(_rotate(scalar.w[2], scalar.q3_ref, x) for x in (st.a3, st.a2))
        # wrist scalars uᵀ·R4ᵀ·R_sᵀ·R_rel·x = (R_s·R4·u)·(R_rel·x), u ∈ {a1, a2, a1 × a2},
        # x ∈ {a3, a2, a3 × a2}; R_rel·x = R_pose·(R_home⁻¹·x)
        self.wrist_u = (wt.a1, wt.a2)
        self.wrist_x_home = (scalar.home_inv_a3, scalar.home_inv_a2)

    def pose(self, rot: tuple[Vec, Vec, Vec], pos: Vec) -> PoseArmAngles | None:
        """The feasible arm-angle gaps of the flange pose ``rot`` (rows) and ``pos`` (mm), or None
        when the pose needs the vectorised path (see the module docstring)."""
        try:
            return self._pose(rot, pos)
        except _Undecided:
            return None

    def _pose(self, rot, pos) -> PoseArmAngles:
        sc = self.scalar
        r0, r1, r2 = rot
        s, wh = sc.shoulder, sc.w0h
        v = (_dot(r0, wh) + pos[0] - s[0], _dot(r1, wh) + pos[1] - s[1], _dot(r2, wh) + pos[2] - s[2])
        vv = _dot(v, v)
        el = _roots(sc.el_a, sc.el_b, sc.el_k - vv / 2.0)
        if abs(el[3]) > 1.0 - RATIO_MARGIN:
            raise _Undecided  # out of reach, or the elbow (near) stretched
        off = _cross(sc.w[0], v)
        if _dot(off, off) < FALLBACK_MARGIN**2:
            raise _Undecided  # the wrist point (near) axis 1: the reference plane is undefined
        norm_v = math.sqrt(vv)
        frame = (v, (v[0] / norm_v, v[1] / norm_v, v[2] / norm_v), rot)
        q4s = (el[1], el[0])  # GC4 = +1: the "−" root
        sinusoids: list = [None, None]  # per elbow root within limits: (shoulder's, wrist's)
        # per triple of an elbow root within limits (shoulder, wrist, shoulder, wrist, …): whether
        # either branch is feasible in its gap through ±π, and the crossings where that changes
        state: list[bool] = []
        changes: dict[float, list[tuple[int, bool]]] = {}
        every: set[float] = set()
        for g4, q4 in enumerate(q4s):
            if not _inside(_wrap(q4), self.elbow_windows):
                continue
            sinusoids[g4] = self._sinusoids(q4, *frame)
            for triple, sins in zip((self.shoulder, self.wrist), sinusoids[g4]):
                cuts = triple.crossings(*sins)
                every.update(cuts)
                feas = triple.gap_feasibility(cuts, sins)
                for cut, before, after in zip(cuts, [feas[-1], *feas], feas):
                    if before != after:
                        changes.setdefault(cut, []).append((len(state), after))
                state.append(feas[-1])
        every_sorted = sorted(every)
        for lo, hi in zip(every_sorted, [*every_sorted[1:], every_sorted[0] + _TWO_PI] if every else []):
            if hi - lo < CUT_MARGIN:
                raise _Undecided
        # Sweep the crossings where some triple's feasibility changes (the others never split a
        # run of feasible gaps, so the intervals are the same): a gap is feasible where both
        # triples of an elbow root are.
        cuts = sorted(changes)
        feasible = []
        for cut in cuts or [None]:
            for t, after in changes.get(cut, ()):
                state[t] = after
            feasible.append(any(state[t] and state[t + 1] for t in range(0, len(state), 2)))
        return PoseArmAngles(self, cuts, feasible, q4s, sinusoids, frame)

    def _sinusoids(self, q4: float, v: Vec, axis: Vec, rot) -> tuple[tuple[Sinusoid, ...], tuple[Sinusoid, ...]]:
        """The five sinusoids (f2, n1, d1, n3, d3) of the shoulder and of the wrist for elbow
        angle q4, S→W vector v (unit: axis) and flange rotation rows rot; raises
        ``_Undecided`` where the reference shoulder rotation is (nearly) ambiguous
        (``SrsScalar._reference``)."""
        ref = self.scalar._reference(q4, v)
        if ref is None:
            raise _Undecided
        a, b = ref
        w0, w1, w2, w3 = self.scalar.w[0], self.scalar.w[1], self.scalar.w[2], self.scalar.w[3]
        x3, x2 = (_rotate(w0, a, _rotate(w1, b, x)) for x in self.shoulder_x)  # R_ref·x
        x32 = _cross(x3, x2)
        u1, u2, u12 = self.shoulder_u
        shoulder = (
            _sinusoid(axis, x3, u1), _sinusoid(axis, x3, u2), _neg(_sinusoid(axis, x3, u12)),
            _sinusoid(axis, x2, u1), _sinusoid(axis, x32, u1),
        )
        r0, r1, r2 = rot
        y3, y2 = ((_dot(r0, x), _dot(r1, x), _dot(r2, x)) for x in self.wrist_x_home)  # R_rel·x
        y32 = _cross(y3, y2)
        q3_ref = self.scalar.q3_ref
        v1, v2 = (_rotate(w0, a, _rotate(w1, b, _rotate(w2, q3_ref, _rotate(w3, q4, u)))) for u in self.wrist_u)
        v12 = _cross(v1, v2)
        wrist = (
            _sinusoid(axis, v1, y3), _sinusoid(axis, v2, y3), _neg(_sinusoid(axis, v12, y3)),
            _sinusoid(axis, v1, y2), _sinusoid(axis, v1, y32),
        )
        return shoulder, wrist


def _neg(x: Sinusoid) -> Sinusoid:
    return -x[0], -x[1], -x[2]


class PoseArmAngles:
    """One pose's feasible arm angles (``SrsArmAngleScalar.pose``).

    cuts: the sorted crossings (rad, in (−π, π]) where feasibility changes; feasible: per gap,
    whether some configuration is within limits there — gap g runs from cuts[g] to the next
    crossing (the last through ±π; with no crossing, one gap: the whole circle).
    """

    def __init__(self, owner: SrsArmAngleScalar, cuts: list[float], feasible: list[bool], q4s, sinusoids, frame) -> None:
        self.cuts = cuts
        self.feasible = feasible
        self._owner, self._q4s, self._sinusoids, self._frame = owner, q4s, sinusoids, frame

    def configurations(self, psi: float) -> list[list[float] | None] | None:
        """The configurations at arm angle ``psi`` (rad) in the form of ``SrsScalar.solve`` (8
        entries in its branch order, rows wrapped to (−π, π]), read off the sinusoids, each None
        where a joint is outside its limits. None when the pose needs the vectorised path: near
        the shoulder or wrist singularity (for either elbow root), or a joint within
        ``LIMIT_MARGIN_RAD`` of a limit or (where the limits reach it) of ±π."""
        try:
            return self._configurations(psi)
        except _Undecided:
            return None

    def _configurations(self, psi: float) -> list[list[float] | None]:
        owner = self._owner
        s, c = math.sin(psi), math.cos(psi)
        out: list[list[float] | None] = [None] * 8
        for g4, q4 in enumerate(self._q4s):
            sins = self._sinusoids[g4]
            if sins is None:  # no row within limits, but a singularity here still flags the pose
                for x in owner._sinusoids(q4, *self._frame):
                    _Triple.regular(s, c, *x)
                continue
            shoulder, wrist = (triple.branches(s, c, *x) for triple, x in zip((owner.shoulder, owner.wrist), sins))
            for g2, sh in enumerate(shoulder):
                for g6, wr in enumerate(wrist):
                    if sh is not None and wr is not None:
                        out[4 * g2 + 2 * g4 + g6] = [*sh, _wrap(q4), *wr]
        return out
