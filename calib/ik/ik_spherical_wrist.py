"""Closed-form IK of 6R arms with a spherical wrist: all 8 branches, vectorised over poses.

The class (checked numerically on the model's own chain, ``WristArmGeometry.from_axes``):
axis 1 ⟂ axis 2, axis 2 ∥ axis 3, axes 4-5-6 meet in one point (the wrist centre) with
4 ⟂ 5 ⟂ 6. Offsets are allowed anywhere else (KUKA's a1/a3, Stäubli's 20 mm shoulder offset d3,
OPW's b), so the KR 6 (OPW) and the TX60 (mdh) are both members.

Decoupling (product-of-exponentials form, see ``calib.ik.ik_subproblems``):

1. wrist centre ``c = T · T(0)⁻¹ · c0`` (c0: wrist centre at q = 0);
2. A1: rotating about axes 2 and 3 keeps the component of the wrist centre along axis 2
   fixed, so ``(Rot(ω1, q1)·ω2)·(c − p1) = ω2·(c0 − p1)`` — ``A cos q1 + B sin q1 = D``, two
   roots (**shoulder** front/back). No real root: the wrist centre is closer to axis 1 than the
   lateral offset allows (out of reach). Wrist centre on axis 1 with no lateral offset: any A1
   works (shoulder singularity).
3. A3: the distance from axis 2 to the wrist centre depends on q3 only (subproblem 3), two
   roots (**elbow** up/down); no real root: out of reach (too far or too close).
4. A2: subproblem 1 about axis 2.
5. A4, A5, A6: the remaining rotation decomposed over three intersecting axes, two roots
   (**wrist** noflip/flip). At the wrist singularity only A4 ± A6 is determined.

Branch labels (fixed per branch index, so they never swap across a singularity):

- ``shoulder=front``: the wrist centre is on the side of axis 1 the arm faces, where "faces"
  is the direction ±(ω1 × ω2) that points to +x of the robot base at q = 0, turned by A1
  (KUKA status bit 0 = 0 for the KR 6).
- ``elbow=up``: the elbow is bent so that, with the shoulder in front, axis 3 lies above the
  line from axis 2 to the wrist centre (a property of A3 alone; KUKA status bit 1).
- ``wrist=noflip``: ``sin(q5 − q5_singular) > 0`` where ``q5_singular`` is the A5 that lines
  axis 6 up with axis 4 (for KUKA: A5 > 0, status bit 2 = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
)

N_BRANCHES = 8
#: Distance from a singularity (rad, or mm for the shoulder) below which a pose is flagged.
SINGULAR_TOLERANCE = 1e-6
#: Slack on the reach equations before a pose is called out of reach (relative).
REACH_SLACK = 1e-12


def branch_labels() -> list[str]:
    """Label per branch index b = 4·shoulder + 2·elbow + wrist (bit 0 = front / up / noflip)."""
    out = []
    for s in ("front", "back"):
        for e in ("up", "down"):
            for w in ("noflip", "flip"):
                out.append(f"shoulder={s} elbow={e} wrist={w}")
    return out


@dataclass(frozen=True)
class RawSolutions:
    """Candidate joint vectors before FK verification and limit filtering.

    q (k, 8, n) rad (wrapped to (−π, π]); valid (k, 8) — the branch exists;
    unreachable (k,) message or "" per pose; singular (k,) message or "" per pose.
    """

    q: np.ndarray
    valid: np.ndarray
    unreachable: list[str]
    singular: list[str]


@dataclass(frozen=True)
class WristArmGeometry:
    """Everything the 6R solver needs, derived from the chain's screw axes at q = 0."""

    axes: ScrewAxes
    names: tuple[str, ...]
    wrist_centre: np.ndarray  # c0 (3,), mm
    lateral: float  # ω2·(c0 − p1), mm: the shoulder's lateral offset
    facing_sign: float  # σ with f0 = σ·(ω1 × ω2) facing +x of the base at q = 0
    elbow_up_sign: float  # +1 if the "+" root of the A3 equation is elbow up
    reach: tuple[float, float]  # reachable distance band of the wrist centre from axis 2, mm
    wrist: SphericalTriple

    @classmethod
    def from_axes(cls, axes: ScrewAxes, names: tuple[str, ...], model_name: str) -> "WristArmGeometry":
        """Check the structure and precompute; raise ``ValueError`` naming what fails."""
        w, p = axes.omega, axes.points
        if len(w) != 6:
            raise ValueError(f"{model_name}: a spherical-wrist solver needs 6 joints, the model has {len(w)}")
        a = names

        def fail(what: str) -> ValueError:
            return ValueError(
                f"{model_name} is not a 6R arm with a spherical wrist ({what}); the analytic solver needs "
                f"{a[0]} ⟂ {a[1]}, {a[1]} ∥ {a[2]}, and {a[3]}, {a[4]}, {a[5]} meeting in one point with "
                f"{a[3]} ⟂ {a[4]} ⟂ {a[5]}"
            )

        cos12 = abs(dot(w[0], w[1]))
        if cos12 > AXIS_TOLERANCE:
            raise fail(f"{a[0]} and {a[1]} are at {np.degrees(np.arccos(min(cos12, 1.0))):.6f}°, not 90°")
        sin23 = np.linalg.norm(cross(w[1], w[2]))
        if sin23 > AXIS_TOLERANCE:
            raise fail(f"{a[1]} and {a[2]} are at {np.degrees(np.arcsin(min(sin23, 1.0))):.6f}°, not parallel")
        for i, j in ((3, 4), (4, 5)):
            c = abs(dot(w[i], w[j]))
            if c > AXIS_TOLERANCE:
                raise fail(f"{a[i]} and {a[j]} are at {np.degrees(np.arccos(min(c, 1.0))):.6f}°, not 90°")
        c0, miss = common_point(p[3:6], w[3:6])
        if not miss <= POINT_TOLERANCE_MM:
            raise fail(f"{a[3]}, {a[4]}, {a[5]} miss a common point by {miss:.3g} mm")
        if line_distance(p[2], w[2], c0) < 1e-6 or line_distance(p[1], w[1], p[2]) < 1e-6:
            raise fail("the upper arm or forearm has zero length")

        n12 = cross(w[0], w[1])
        ex = np.array([1.0, 0.0, 0.0])
        sigma = 1.0 if dot(n12, ex) > 1e-9 else -1.0 if dot(n12, ex) < -1e-9 else (1.0 if n12[1] >= 0 else -1.0)
        # Elbow sign: bend A3 by +90° from the folded angle (q1 = q2 = 0) and see whether the
        # elbow (axis 3) is above the shoulder–wrist line as seen with the arm facing forward.
        a_, b_, _ = circle_distance_equation(w[2], p[2], c0, p[1], np.asarray(0.0))
        folded = float(np.arctan2(b_, a_))
        cw = rotate(w[2], np.asarray(folded + np.pi / 2), c0 - p[2]) + p[2]
        s = p[1] + w[1] * dot(w[1], cw - p[1])  # axis 2 in the arm plane through the wrist centre
        e = p[2] + w[2] * dot(w[2], cw - p[2])  # axis 3 in that plane
        up0 = w[0] if w[0][2] >= 0 else -w[0]
        m0 = cross(sigma * n12, up0)
        elbow_up_sign = 1.0 if dot(cross(cw - s, e - s), m0) > 0 else -1.0
        upper = line_distance(p[1], w[1], p[2])
        fore = line_distance(p[2], w[2], c0)
        return cls(
            axes=axes,
            names=tuple(names),
            wrist_centre=c0,
            lateral=float(dot(w[1], c0 - p[0])),
            facing_sign=sigma,
            elbow_up_sign=elbow_up_sign,
            reach=(abs(upper - fore), upper + fore),
            wrist=SphericalTriple.of(w[3], w[4], w[5]),
        )

    # ----------------------------------------------------------------------------------------
    def solve(self, poses: np.ndarray, reach_slack: float = REACH_SLACK) -> RawSolutions:
        """All 8 branches for flange poses (k, 4, 4) mm; see ``RawSolutions``.

        ``reach_slack``: relative excess over the reach equations still accepted (clamped to the
        boundary) — for starting points that a later polish on a perturbed model refines.
        """
        ax = self.axes
        w, p = ax.omega, ax.points
        k = poses.shape[0]
        names = self.names
        t_rel = poses @ ax.home_inv  # maps the q = 0 flange to the target: Π exp(ξ q)
        c = np.einsum("kij,j->ki", t_rel[:, :3, :3], self.wrist_centre) + t_rel[:, :3, 3]

        # --- A1 -----------------------------------------------------------------------------
        v = c - p[0]
        n12 = cross(w[0], w[1])
        a1c, b1c = v @ w[1], v @ n12
        # wrist centre on axis 1 (no lateral offset): A1 is free; representatives front A1 = 0, back A1 = π
        on_axis = np.hypot(a1c, b1c) < 1e-9
        a1c = np.where(on_axis, 0.0, a1c)
        b1c = np.where(on_axis, self.facing_sign, b1c)
        lat = np.where(on_axis & (abs(self.lateral) < 1e-9), 0.0, self.lateral)
        sh = solve_cosine(a1c, b1c, lat)
        # front root: f·v > 0 with f = σ·Rot(ω1,q1)(ω1×ω2) = σ(cos q1 (ω1×ω2) − sin q1 ω2), so
        # f·v = σ r sin(φ − q1) with q1 = φ ± β: the front root is q1 = φ − σβ
        if self.facing_sign > 0:
            q1_pair = np.stack([sh.minus, sh.plus], 1)  # (k, 2): front, back
        else:
            q1_pair = np.stack([sh.plus, sh.minus], 1)
        sh_out = np.abs(sh.ratio) > 1.0 + reach_slack
        sh_dist = np.where(on_axis, 0.0, sh.r * sh.sin_beta)  # wrist centre to the singular surface, mm

        # --- A3 (per shoulder root) -----------------------------------------------------------
        q1f = q1_pair.reshape(-1)  # (2k,)
        cc = np.repeat(c, 2, axis=0)
        c1 = rotate(w[0], -q1f, cc - p[0]) + p[0]  # wrist centre with A1 undone
        dist2 = np.linalg.norm(perp(w[1], c1 - p[1]), axis=-1)
        a3, b3, d3 = circle_distance_equation(w[2], p[2], self.wrist_centre, p[1], dist2)
        # solve on the distance perpendicular to the axis: drop the (fixed) axial part
        d3 = d3 - 0.5 * (dot(w[2], self.wrist_centre - p[2]) - dot(w[2], p[1] - p[2])) ** 2
        el = solve_cosine(a3, b3, d3)
        if self.elbow_up_sign > 0:
            q3_pair = np.stack([el.plus, el.minus], 1)  # (2k, 2): up, down
        else:
            q3_pair = np.stack([el.minus, el.plus], 1)
        el_out = np.abs(el.ratio) > 1.0 + reach_slack

        # --- A2 ------------------------------------------------------------------------------
        q1e = np.repeat(q1f, 2)  # (4k,)
        q3e = q3_pair.reshape(-1)
        c1e = np.repeat(c1, 2, axis=0)
        moved = rotate(w[2], q3e, self.wrist_centre - p[2]) + p[2]
        q2e, _ = subproblem1(w[1], moved - p[1], c1e - p[1])

        # --- A4..A6 ----------------------------------------------------------------------------
        r123 = rotation(w[0], q1e) @ rotation(w[1], q2e) @ rotation(w[2], q3e)
        r_rel = np.repeat(t_rel[:, :3, :3], 4, axis=0)
        r_wrist = np.swapaxes(r123, -1, -2) @ r_rel  # = Rot(ω4,q4)Rot(ω5,q5)Rot(ω6,q6)
        wr, wrist_dist = self.wrist.decompose(r_wrist)  # (2, 4k, 3)

        arm = np.stack([q1e, q2e, q3e], -1)  # (4k, 3)
        q = np.concatenate([np.broadcast_to(arm, (2,) + arm.shape), wr], -1)  # (2, 4k, 6)
        q = np.moveaxis(q, 0, 1).reshape(k, N_BRANCHES, 6)  # branch = 4s + 2e + w
        q = np.pi - np.mod(np.pi - q, 2 * np.pi)
        valid = np.repeat(~sh_out, 4)[:, None] & np.repeat(~el_out, 2)[:, None]
        valid = np.broadcast_to(valid, (4 * k, 2)).reshape(k, N_BRANCHES).copy()
        valid &= np.all(np.isfinite(q), axis=-1)

        unreachable = [""] * k
        singular = [""] * k
        el_out_k = el_out.reshape(k, 2)
        for i in np.flatnonzero(sh_out | el_out_k.all(axis=1)):
            if sh_out[i]:
                unreachable[i] = (
                    f"out of reach: the wrist centre is {sh.r[i]:.3f} mm from axis {names[0]}, but this arm's "
                    f"lateral offset puts it at least {abs(self.lateral):.3f} mm away"
                )
            else:
                d = dist2.reshape(k, 2)[i]
                unreachable[i] = (
                    f"out of reach: the wrist centre is {d.min():.3f} mm from axis {names[1]}"
                    + (f" ({d.max():.3f} mm reaching over the back)" if abs(d[0] - d[1]) > 1e-9 else "")
                    + f"; the arm reaches {self.reach[0]:.3f}…{self.reach[1]:.3f} mm"
                )
        el_sing = (el.sin_beta < SINGULAR_TOLERANCE) & ~el_out
        wr_sing = wrist_dist < SINGULAR_TOLERANCE
        sh_sing = (sh_dist < SINGULAR_TOLERANCE) & ~sh_out
        el_sing_k = el_sing.reshape(k, 2).any(axis=1)
        wr_valid = np.repeat(~el_out, 2) & np.repeat(np.repeat(~sh_out, 2), 2)
        wr_sing_k = (wr_sing & wr_valid).reshape(k, 4).any(axis=1)
        reachable = np.array([not u for u in unreachable], dtype=bool)
        for i in np.flatnonzero((sh_sing | el_sing_k | wr_sing_k) & reachable):
            parts = []
            if sh_sing[i]:
                parts.append(
                    f"shoulder singular: the wrist centre is on the singular surface around axis {names[0]} "
                    f"({sh_dist[i]:.2e} mm away), the front and back {names[0]} roots coincide or {names[0]} is free"
                )
            if el_sing_k[i]:
                parts.append(f"elbow singular: the arm is stretched or folded, the elbow-up and -down {names[2]} roots coincide")
            if wr_sing_k[i]:
                j = np.flatnonzero((wr_sing & wr_valid).reshape(k, 4)[i])[0]
                wr_i = wr[:, 4 * i + j, :]
                same = np.cos(wr_i[0, 1] - self.wrist.aligned) > 0
                combo = f"{names[3]} + {names[5]}" if same else f"{names[3]} − {names[5]}"
                parts.append(
                    f"wrist singular: {names[4]} is {wrist_dist[4 * i + j]:.2e} rad from the singular angle, "
                    f"{names[3]} and {names[5]} are determined only as the {'sum' if same else 'difference'} {combo}; "
                    f"the solutions returned are representatives"
                )
            singular[i] = "; ".join(parts)
        return RawSolutions(q=q, valid=valid, unreachable=unreachable, singular=singular)
