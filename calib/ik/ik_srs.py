"""Closed-form IK of 7R S-R-S arms (KUKA LBR iiwa) at a given arm angle, vectorised.

The class (checked numerically on the model's own chain, ``SrsGeometry.from_axes``): axes 1-2-3
meet in the shoulder point S with 1 ⟂ 2 ⟂ 3, axes 5-6-7 meet in the wrist point W with
5 ⟂ 6 ⟂ 7, and axis 4 (the elbow) passes through neither.

Following Shimizu et al. (2008), in product-of-exponentials form (``calib.ik.ik_subproblems``):

1. wrist point ``W = T · T(0)⁻¹ · W0``; the elbow angle A4 follows from |W − S| alone
   (subproblem 3) — two roots, **GC4** = sign of A4 relative to the stretched angle;
2. reference shoulder rotation ``R_ref``: the A1, A2 (with A3 at the angle that makes the elbow
   axis parallel to axis 2 — A3 = 0 for the iiwa) that carry the elbow-bent arm onto W, taking
   the root whose shoulder faces the wrist point. Its elbow lies in the plane
   through axis 1 and S–W: the **reference plane** (arm angle ψ = 0);
3. the shoulder rotation at arm angle ψ is ``R_s = Rot(ŝw, ψ) · R_ref`` — the elbow swung by ψ
   about the S→W line (right-hand rule) — decomposed into A1, A2, A3 over the spherical
   shoulder: two roots, **GC2** = sign of A2 relative to its singular angle;
4. the rest of the orientation decomposed into A5, A6, A7 over the spherical wrist: two roots,
   **GC6** = sign of A6 relative to its singular angle.

For the iiwa all three singular angles are 0, so GCk = sign(A_k) as in Shimizu's paper.
Branch index b = 4·[GC2 < 0] + 2·[GC4 < 0] + [GC6 < 0]; label ``"GC2=+1 GC4=-1 GC6=+1"``.

Singular cases flagged: wrist point on axis 1 (reference plane undefined — ψ is then measured
from the plane A1 = 0), elbow stretched (ψ has no effect), A2 or A6 at its singular angle
(A1 ± A3 resp. A5 ± A7 determined only as a sum or difference).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.ik.ik_spherical_wrist import REACH_SLACK, SINGULAR_TOLERANCE, RawSolutions
from calib.robot.transforms import skew
from calib.ik.ik_subproblems import (
    AXIS_TOLERANCE,
    POINT_TOLERANCE_MM,
    ScrewAxes,
    SphericalTriple,
    circle_distance_equation,
    common_point,
    cross,
    dot,
    line_distance,
    perp,
    rotate,
    rotation,
    solve_cosine,
    subproblem1,
    unit,
)

N_BRANCHES = 8


def branch_labels() -> list[str]:
    """Label per branch index b = 4·[GC2 < 0] + 2·[GC4 < 0] + [GC6 < 0]."""
    return [f"GC2={g2} GC4={g4} GC6={g6}" for g2 in ("+1", "-1") for g4 in ("+1", "-1") for g6 in ("+1", "-1")]


@dataclass(frozen=True)
class SrsGeometry:
    """Everything the 7R solver needs, derived from the chain's screw axes at q = 0."""

    axes: ScrewAxes
    names: tuple[str, ...]
    shoulder: np.ndarray  # S (3,), mm
    wrist_point: np.ndarray  # W0 (3,), mm, at q = 0
    facing: np.ndarray  # f0 (3,): the direction the shoulder faces at A1 = 0, ⟂ axis 1
    reach: tuple[float, float]  # |S − W| band, mm
    q3_ref: float  # the A3 that makes the elbow axis parallel to axis 2 (0 for the iiwa)
    shoulder_triple: SphericalTriple
    wrist_triple: SphericalTriple

    @classmethod
    def from_axes(cls, axes: ScrewAxes, names: tuple[str, ...], model_name: str) -> "SrsGeometry":
        """Check the structure and precompute; raise ``ValueError`` naming what fails."""
        w, p = axes.omega, axes.points
        if len(w) != 7:
            raise ValueError(f"{model_name}: the S-R-S solver needs 7 joints, the model has {len(w)}")
        a = names

        def fail(what: str) -> ValueError:
            return ValueError(
                f"{model_name} is not a 7R S-R-S arm ({what}); the analytic solver needs {a[0]}, {a[1]}, {a[2]} "
                f"meeting in one point with {a[0]} ⟂ {a[1]} ⟂ {a[2]}, the same for {a[4]}, {a[5]}, {a[6]}, "
                f"and {a[3]} passing through neither point"
            )

        for i, j in ((0, 1), (1, 2), (4, 5), (5, 6)):
            c = abs(dot(w[i], w[j]))
            if c > AXIS_TOLERANCE:
                raise fail(f"{a[i]} and {a[j]} are at {np.degrees(np.arccos(min(c, 1.0))):.6f}°, not 90°")
        s, miss_s = common_point(p[0:3], w[0:3])
        if not miss_s <= POINT_TOLERANCE_MM:
            raise fail(f"{a[0]}, {a[1]}, {a[2]} miss a common point by {miss_s:.3g} mm")
        w0, miss_w = common_point(p[4:7], w[4:7])
        if not miss_w <= POINT_TOLERANCE_MM:
            raise fail(f"{a[4]}, {a[5]}, {a[6]} miss a common point by {miss_w:.3g} mm")
        d_s, d_w = line_distance(p[3], w[3], s), line_distance(p[3], w[3], w0)
        if min(d_s, d_w) < 1e-6:
            raise fail(f"{a[3]} passes through the shoulder or wrist point")

        n12 = cross(w[0], w[1])
        ex = np.array([1.0, 0.0, 0.0])
        sigma = 1.0 if dot(n12, ex) > 1e-9 else -1.0 if dot(n12, ex) < -1e-9 else (1.0 if n12[1] >= 0 else -1.0)
        # Reference A3: the elbow axis turned parallel to ±axis 2 (Shimizu's θ3 = 0), the
        # smaller turn of the two, so models with other A3 conventions share the arm angle.
        turns = [float(subproblem1(w[2], w[3], sgn * w[1])[0]) for sgn in (1.0, -1.0)]
        q3_ref = min(turns, key=abs)
        xa, ya = dot(w[3], w0 - p[3]), dot(w[3], s - p[3])
        rx, ry = np.linalg.norm(perp(w[3], w0 - p[3])), np.linalg.norm(perp(w[3], s - p[3]))
        return cls(
            axes=axes,
            names=tuple(names),
            shoulder=s,
            wrist_point=w0,
            facing=sigma * unit(n12),
            reach=(float(np.hypot(abs(rx - ry), xa - ya)), float(np.hypot(rx + ry, xa - ya))),
            q3_ref=q3_ref,
            shoulder_triple=SphericalTriple.of(w[0], w[1], w[2]),
            wrist_triple=SphericalTriple.of(w[4], w[5], w[6]),
        )

    # ----------------------------------------------------------------------------------------
    def _elbow(self, poses: np.ndarray):
        ax = self.axes
        w, p = ax.omega, ax.points
        t_rel = poses @ ax.home_inv
        wp = np.einsum("...ij,j->...i", t_rel[..., :3, :3], self.wrist_point) + t_rel[..., :3, 3]
        v = wp - self.shoulder
        a4, b4, d4 = circle_distance_equation(w[3], p[3], self.wrist_point, self.shoulder, np.linalg.norm(v, axis=-1))
        return t_rel, v, solve_cosine(a4, b4, d4)

    def _reference(self, q4: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """R_ref (..., 3, 3) for elbow angle q4 (...) and S→W vector v (..., 3); and |v⟂ axis 1|."""
        w, p = self.axes.omega, self.axes.points
        u = rotate(w[3], q4, self.wrist_point - p[3]) + p[3] - self.shoulder
        u = rotate(w[2], np.asarray(self.q3_ref), u)  # A3 at its reference angle
        w1, w2 = w[0], w[1]
        # subproblem 2 with w1 ⟂ w2: z = α w1 + β w2 ± γ (w1 × w2), Rot(w2,b)u = z, Rot(w1,a)z = v
        alpha, beta = dot(v, w1), dot(u, w2)
        gamma = np.sqrt(np.maximum(dot(u, u) - alpha**2 - beta**2, 0.0))
        n12 = cross(w1, w2)
        best_a = best_b = None
        best_face = None
        for sgn in (1.0, -1.0):
            z = alpha[..., None] * w1 + beta[..., None] * w2 + (sgn * gamma)[..., None] * n12
            b, _ = subproblem1(w2, u, z)
            a, _ = subproblem1(w1, z, v)
            face = dot(rotate(w1, a, np.broadcast_to(self.facing, v.shape)), v)
            if best_a is None:
                best_a, best_b, best_face = a, b, face
            else:
                take = face > best_face
                best_a, best_b = np.where(take, a, best_a), np.where(take, b, best_b)
        r_ref = rotation(w1, best_a) @ rotation(w2, best_b) @ rotation(w[2], np.asarray(self.q3_ref))
        return r_ref, np.linalg.norm(perp(w1, v), axis=-1)

    def reachable(self, poses: np.ndarray, reach_slack: float = REACH_SLACK) -> np.ndarray:
        """(k,) bool: the wrist point of each flange pose (k, 4, 4) is within the elbow's reach —
        ``solve``'s reach test alone (it does not depend on the arm angle)."""
        _, _, el = self._elbow(poses)
        return np.abs(el.ratio) <= 1.0 + reach_slack

    def solve(self, poses: np.ndarray, psi: np.ndarray, reach_slack: float = REACH_SLACK) -> RawSolutions:
        """All 8 global configurations for flange poses (k, 4, 4) mm at arm angles ψ (k,) rad.

        ``reach_slack``: relative excess over the elbow equation still accepted (clamped).
        """
        w = self.axes.omega
        names = self.names
        k = poses.shape[0]
        t_rel, v, el = self._elbow(poses)
        out_of_reach = np.abs(el.ratio) > 1.0 + reach_slack
        # GC4 = sign of sin(q4 − stretched), stretched = folded + π. The roots are folded ± β
        # (β ∈ [0, π]); sin(±β − π) = ∓sin β, so the "−" root is GC4 = +1. (k, 2): GC4 = +1, −1
        q4_pair = np.stack([el.minus, el.plus], 1)
        q4 = q4_pair.reshape(-1)
        vv = np.repeat(v, 2, axis=0)
        r_ref, off_axis = self._reference(q4, vv)
        r_s = rotation(unit(vv), np.repeat(psi, 2)) @ r_ref
        sh, sh_dist = self.shoulder_triple.decompose(r_s)  # (2, 2k, 3)
        r4 = rotation(w[3], q4)
        r_rel = np.repeat(t_rel[:, :3, :3], 2, axis=0)
        q_list = []
        wr_dist = []
        for g2 in range(2):
            r1234 = rotation(w[0], sh[g2, :, 0]) @ rotation(w[1], sh[g2, :, 1]) @ rotation(w[2], sh[g2, :, 2]) @ r4
            wr, dist = self.wrist_triple.decompose(np.swapaxes(r1234, -1, -2) @ r_rel)  # (2, 2k, 3)
            wr_dist.append(dist)
            for g6 in range(2):
                q_list.append(np.concatenate([sh[g2], q4[:, None], wr[g6]], -1))  # (2k, 7)
        q = np.stack(q_list, 0).reshape(2, 2, k, 2, 7)  # (g2, g6, k, g4, 7)
        q = np.transpose(q, (2, 0, 3, 1, 4)).reshape(k, N_BRANCHES, 7)
        q = np.pi - np.mod(np.pi - q, 2 * np.pi)
        valid = np.broadcast_to(~out_of_reach[:, None], (k, N_BRANCHES)) & np.all(np.isfinite(q), axis=-1)

        unreachable = [""] * k
        singular = [""] * k
        dist_sw = np.linalg.norm(v, axis=-1)
        for i in np.flatnonzero(out_of_reach):
            unreachable[i] = (
                f"out of reach: the wrist point is {dist_sw[i]:.3f} mm from the shoulder point; "
                f"this arm reaches {self.reach[0]:.3f}…{self.reach[1]:.3f} mm"
            )
        el_sing = el.sin_beta < SINGULAR_TOLERANCE
        ref_sing = off_axis.reshape(k, 2)[:, 0] < SINGULAR_TOLERANCE
        sh_sing = (sh_dist < SINGULAR_TOLERANCE).reshape(k, 2).any(axis=1)
        wr_sing = ((wr_dist[0] < SINGULAR_TOLERANCE) | (wr_dist[1] < SINGULAR_TOLERANCE)).reshape(k, 2).any(axis=1)
        for i in np.flatnonzero((el_sing | ref_sing | sh_sing | wr_sing) & ~out_of_reach):
            parts = []
            if ref_sing[i]:
                parts.append(
                    f"the wrist point is on axis {names[0]}: the arm-angle reference plane is undefined, "
                    f"ψ is measured from {names[0]} = 0"
                )
            if el_sing[i]:
                parts.append(f"elbow singular: {names[3]} stretched, the arm angle has no effect")
            if sh_sing[i]:
                parts.append(
                    f"shoulder singular: {names[1]} at its singular angle, {names[0]} and {names[2]} are determined "
                    f"only as a sum (or difference); the solutions returned are representatives"
                )
            if wr_sing[i]:
                parts.append(
                    f"wrist singular: {names[5]} at its singular angle, {names[4]} and {names[6]} are determined "
                    f"only as a sum (or difference); the solutions returned are representatives"
                )
            singular[i] = "; ".join(parts)
        return RawSolutions(q=q, valid=valid, unreachable=unreachable, singular=singular)

    def limit_crossings(self, poses: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """Every arm angle ψ (rad) at which some joint of some configuration may cross a limit.

        Shimizu et al.'s observation, in this module's notation: the shoulder rotation
        ``R_s(ψ) = Rot(ŝw, ψ)·R_ref = A sin ψ + B cos ψ + C`` and so is the wrist rotation
        ``R_w(ψ) = R4ᵀ R_s(ψ)ᵀ R_rel``. For three intersecting axes a1 ⟂ a2 ⟂ a3 and
        R = Rot(a1,t1)Rot(a2,t2)Rot(a3,t3):

        - cos(t2 − t2_aligned) = a1ᵀ R a3,
        - tan t1 = ±(a2ᵀ R a3) / ∓(−(a1 × a2)ᵀ R a3),  tan t3 = (a1ᵀ R a2) / (a1ᵀ R (a3 × a2)),

        so "joint = limit L" is one equation ``a sin ψ + b cos ψ + c = 0`` with two roots. This
        returns all of them for both limits of joints 1–3 and 5–7, both elbow roots, plus the
        shoulder/wrist singular arm angles (t2 = aligned or aligned + π) where t1 and t3 jump.
        Some roots are spurious (the other half-turn of the tangent): harmless, the caller
        tests feasibility between consecutive candidates.

        poses (k, 4, 4) mm; lower, upper (7,) rad (controller convention). Returns ψ (k, M) rad
        in (−π, π], NaN where an equation has no real root (all NaN for a pose out of reach).
        """
        w = self.axes.omega
        kp = poses.shape[0]
        t_rel, v, el = self._elbow(poses)
        reach = np.abs(el.ratio) <= 1.0 + REACH_SLACK  # (k,)
        q4 = np.stack([el.plus, el.minus], 1)  # (k, 2)
        vv = np.broadcast_to(v[:, None, :], (kp, 2, 3))
        r_ref, _ = self._reference(q4, vv)  # (k, 2, 3, 3)
        k = skew(unit(vv))
        k2 = k @ k
        # Rot(v̂, ψ) = I + sin ψ K + (1 − cos ψ) K²
        a_s, b_s, c_s = k @ r_ref, -k2 @ r_ref, r_ref + k2 @ r_ref
        m = np.swapaxes(rotation(w[3], q4), -1, -2)  # R4ᵀ
        rel = t_rel[:, None, :3, :3]
        a_w, b_w, c_w = (m @ np.swapaxes(x, -1, -2) @ rel for x in (a_s, b_s, c_s))
        lims_lo, lims_hi = np.pi - np.mod(np.pi - lower, 2 * np.pi), np.pi - np.mod(np.pi - upper, 2 * np.pi)
        # Every equation a sin ψ + b cos ψ + c = 0 stacked, (M, k, 2) each, and solved in one call.
        eq_a, eq_b, eq_c = [], [], []
        for mats, triple, (j1, j2, j3) in (
            ((a_s, b_s, c_s), self.shoulder_triple, (0, 1, 2)),
            ((a_w, b_w, c_w), self.wrist_triple, (4, 5, 6)),
        ):
            a1, a2, a3 = triple.a1, triple.a2, triple.a3
            # uᵀ R x for R = A s + B c + C: (3 parts A, B, C, 5 pairs, k, 2)
            u = np.stack([a1, a2, -cross(a1, a2), a1, a1])
            x = np.stack([a3, a3, a3, a2, cross(a3, a2)])
            coef = np.stack([np.einsum("ei,...ij,ej->e...", u, mat, x) for mat in mats])
            f2, n1, d1, n3, d3 = (coef[:, e] for e in range(5))
            shifts = [np.cos(lim - triple.aligned) for lim in (lims_lo[j2], lims_hi[j2])] + [1.0, -1.0]  # limits, singular ψ
            for shift in shifts:
                eq_a.append(f2[0])
                eq_b.append(f2[1])
                eq_c.append(f2[2] - shift)
            for n_, d_, j in ((n1, d1, j1), (n3, d3, j3)):
                for lim in (lims_lo[j], lims_hi[j]):
                    cl, sl = np.cos(lim), np.sin(lim)
                    eq_a.append(n_[0] * cl - d_[0] * sl)
                    eq_b.append(n_[1] * cl - d_[1] * sl)
                    eq_c.append(n_[2] * cl - d_[2] * sl)
        sol = solve_cosine(np.stack(eq_b), np.stack(eq_a), -np.stack(eq_c))
        ok = (np.abs(sol.ratio) <= 1.0 + 1e-12) & reach[:, None]
        out = np.where(ok, np.stack([sol.plus, sol.minus]), np.nan)  # (2, M, k, 2)
        out = np.moveaxis(out, 2, 0).reshape(kp, -1)  # (k, M)
        return np.pi - np.mod(np.pi - out, 2 * np.pi)

    def arm_angle(self, q: np.ndarray) -> np.ndarray:
        """Arm angle ψ (...) rad of joint vectors q (..., 7) rad — the inverse of ``solve``'s ψ."""
        w = self.axes.omega
        q = np.asarray(q, dtype=float)
        r_s = rotation(w[0], q[..., 0]) @ rotation(w[1], q[..., 1]) @ rotation(w[2], q[..., 2])
        p = self.axes.points
        u = rotate(w[3], q[..., 3], self.wrist_point - p[3]) + p[3] - self.shoulder
        v = np.einsum("...ij,...j->...i", r_s, u)
        r_ref, _ = self._reference(q[..., 3], v)
        rel = r_s @ np.swapaxes(r_ref, -1, -2)  # rotation about v̂ by ψ
        axis = unit(v)
        # any vector ⟂ v̂: pick the better-conditioned of two candidates
        c1 = perp(axis, np.broadcast_to(w[0], axis.shape))
        c2 = perp(axis, np.broadcast_to(w[1], axis.shape))
        n1, n2 = np.linalg.norm(c1, axis=-1), np.linalg.norm(c2, axis=-1)
        x = unit(np.where((n1 >= n2)[..., None], c1, c2))
        y = np.einsum("...ij,...j->...i", rel, x)
        return np.arctan2(dot(axis, cross(x, y)), dot(x, y))
