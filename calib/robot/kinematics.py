"""Batched forward kinematics and its analytic derivatives.

A ``Chain`` turns a ``RobotModel`` into arrays and a flat **parameter vector** that every fitter
shares. Layout (P = 5·n + 3·m for n joints and m markers), grouped by kind so masks are simple:

    [ offset_1..n (rad) | d_1..n (mm) | a_1..n (mm) | alpha_1..n (rad) | beta_1..n (rad) |
      marker_1.xyz .. marker_m.xyz (mm, flange frame) ]

``offset_i`` is the zero-offset δ_i in the controller's convention: the DH angle is
``θ_i = theta_i + sign_i · (q_i + δ_i)``; the nominal vector has δ = 0.

Shapes: joint angles ``q`` are (..., n) radians in the controller's convention; a parameter
array is (P,) or (n_p, P). Results carry the parameter batch first, then the configuration
batch: positions (n_p, n_q, m, 3) for params (n_p, P) and q (n_q, n). No Python loop runs over
configurations or parameter sets; the only loop is over the n joints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.robot.model import RobotModel
from calib.robot.transforms import cross, homogeneous, rot_x, rot_y, rot_z

KINDS = ("offset", "d", "a", "alpha", "beta")


@dataclass(frozen=True)
class FlangeJacobian:
    """Flange pose and its derivatives with respect to every parameter.

    rotation (..., 3, 3), position (..., 3) mm; jp (..., 3, P) mm per parameter unit;
    jw (..., 3, P) rad per parameter unit (angular velocity form, base frame).
    """

    rotation: np.ndarray
    position: np.ndarray
    jp: np.ndarray
    jw: np.ndarray


class Chain:
    """Vectorised kinematics of one robot model with its tool markers."""

    def __init__(self, model: RobotModel) -> None:
        self.model = model
        j = model.joints
        self.n = len(j)
        self.m = len(model.tool.markers)
        self.theta0 = np.radians([x.theta for x in j])
        self.sign = np.array([x.sign for x in j], dtype=float)
        self.base = model.base.matrix()
        self.flange = model.flange.matrix()
        self.marker_names = model.marker_names
        nominal_markers = np.array([mk.xyz for mk in model.tool.markers], dtype=float)
        self.nominal = np.concatenate(
            [
                np.zeros(self.n),
                [x.d for x in j],
                [x.a for x in j],
                np.radians([x.alpha for x in j]),
                np.radians([x.beta for x in j]),
                nominal_markers.ravel(),
            ]
        )
        # Plain-float copies for the one-configuration path (``_walk_one``, ``_walk_links``).
        self._theta0_f = self.theta0.tolist()
        self._sign_f = self.sign.tolist()
        self._base_flat = tuple(self.base[:3, :].T.ravel().tolist())  # columns x, y, z, origin
        self._flange_f = self.flange[:3, :].tolist()
        self._nominal_links = self._links_floats(self.nominal.tolist())
        axes = model.axis_names
        self.param_names = [f"{ax}.{kind}" for kind in KINDS for ax in axes] + [
            f"{mk}.{c}" for mk in self.marker_names for c in "xyz"
        ]

    # --- parameter vector helpers -------------------------------------------------------
    @property
    def n_params(self) -> int:
        return 5 * self.n + 3 * self.m

    def index(self, kind: str, joint: int | None = None) -> np.ndarray | int:
        """Index (or indices for all joints) of a parameter kind in the vector."""
        if kind not in KINDS:
            raise ValueError(f"unknown parameter kind {kind!r}; kinds are {KINDS}")
        start = KINDS.index(kind) * self.n
        return start + joint if joint is not None else np.arange(start, start + self.n)

    def marker_slice(self) -> slice:
        return slice(5 * self.n, 5 * self.n + 3 * self.m)

    def with_offsets(self, offsets_rad: np.ndarray) -> np.ndarray:
        """Nominal vector(s) with zero-offsets replaced; offsets (..., n) → params (..., P)."""
        offsets_rad = np.asarray(offsets_rad, dtype=float)
        p = np.broadcast_to(self.nominal, offsets_rad.shape[:-1] + (self.n_params,)).copy()
        p[..., : self.n] = offsets_rad
        return p

    def _params(self, params: np.ndarray | None) -> np.ndarray:
        if params is None:
            return self.nominal
        p = np.asarray(params, dtype=float)
        if p.shape[-1] != self.n_params:
            raise ValueError(f"parameter vector has {p.shape[-1]} entries, this chain needs {self.n_params}")
        return p

    def _q(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape[-1] != self.n:
            raise ValueError(f"joint vectors have {q.shape[-1]} entries, the model has {self.n} joints")
        return q

    # --- forward kinematics ------------------------------------------------------------
    def _walk(self, q: np.ndarray, p: np.ndarray, record: bool):
        """Walk the chain with frame columns; broadcast over (params…, configs…).

        Each link ``Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)`` is applied to the frame's columns directly
        (no 3×3 products). Returns the flange columns (cx, cy, cz), position, and — when
        ``record`` — per joint: previous z axis and origin, new x axis, y axis after Rx(α), and
        new origin, each (..., 3).
        """
        n = self.n
        lead_p = p.shape[:-1]
        pe = p.reshape(lead_p + (1,) * (q.ndim - 1) + (p.shape[-1],))
        theta = self.theta0 + self.sign * (q + pe[..., :n])  # (..p, ..q, n)
        shape = theta.shape[:-1]
        ct, st = np.cos(theta), np.sin(theta)
        d, a = pe[..., n : 2 * n], pe[..., 2 * n : 3 * n]
        ca, sa = np.cos(pe[..., 3 * n : 4 * n]), np.sin(pe[..., 3 * n : 4 * n])
        cb, sb = np.cos(pe[..., 4 * n : 5 * n]), np.sin(pe[..., 4 * n : 5 * n])
        b = self.base
        cx = np.broadcast_to(b[:3, 0], shape + (3,))
        cy = np.broadcast_to(b[:3, 1], shape + (3,))
        cz = np.broadcast_to(b[:3, 2], shape + (3,))
        pos = np.broadcast_to(b[:3, 3], shape + (3,))
        rec = []
        for i in range(n):
            c_t, s_t = ct[..., i, None], st[..., i, None]
            x1 = c_t * cx + s_t * cy  # x after Rz(θ)
            y1 = c_t * cy - s_t * cx
            new_pos = pos + a[..., i, None] * x1 + d[..., i, None] * cz
            c_a, s_a = ca[..., i, None], sa[..., i, None]
            y2 = c_a * y1 + s_a * cz  # after Rx(α)
            z2 = c_a * cz - s_a * y1
            c_b, s_b = cb[..., i, None], sb[..., i, None]
            x3 = c_b * x1 - s_b * z2  # after Ry(β)
            z3 = s_b * x1 + c_b * z2
            if record:
                rec.append((cz, pos, x1, y2, new_pos))
            cx, cy, cz, pos = x3, y2, z3, new_pos
        f = self.flange
        pos = pos + f[0, 3] * cx + f[1, 3] * cy + f[2, 3] * cz
        fr = f[:3, :3]
        cx, cy, cz = (fr[0, k] * cx + fr[1, k] * cy + fr[2, k] * cz for k in range(3))
        return (cx, cy, cz), pos, rec

    def _walk_one(self, q: np.ndarray, p: np.ndarray) -> tuple[list, list, list, list]:
        """``_walk`` for one configuration (n,) and one parameter vector (P,) in plain floats:
        a single call costs microseconds, not the overhead of dozens of tiny numpy operations.
        Returns the flange's x, y, z columns and origin, each a list of 3 floats."""
        links = self._nominal_links if p is self.nominal else self._links_floats(p.tolist())
        return self._flange_floats(self._walk_links(q.tolist(), links))

    def _links_floats(self, pf: list[float], snap_right_angles: bool = False) -> list[tuple[float, ...]]:
        """Per joint of parameter list pf (P): (θ0, sign, δ, d, a, cos α, sin α, cos β, sin β) —
        what ``_walk_links`` needs, computed once for many walks with the same parameters.

        ``snap_right_angles``: a twist α within 1e-15 rad of ±90° gets cos α = 0 exactly (its
        float cosine is 6e-17), so ``_walk_links`` takes its short right-angle step; the frames
        then differ from the unsnapped walk's by ~1e-15 relative (for checks, not for Chain.fk)."""
        n, cos, sin = self.n, math.cos, math.sin
        links = []
        for i in range(n):
            ca, sa = cos(pf[3 * n + i]), sin(pf[3 * n + i])
            if snap_right_angles and abs(ca) < 1e-15:
                ca, sa = 0.0, math.copysign(1.0, sa)
            links.append((self._theta0_f[i], self._sign_f[i], pf[i], pf[n + i], pf[2 * n + i],
                          ca, sa, cos(pf[4 * n + i]), sin(pf[4 * n + i])))
        return links

    def _walk_links(self, qf: list[float], links: list[tuple[float, ...]], frame: tuple | None = None,
                    start: int = 0) -> tuple[float, ...]:
        """The frame after joints ``start`` … ``start + len(links) − 1`` as 12 floats (x, y, z
        columns, origin), from ``frame`` (the frame before joint ``start``; None: the base);
        qf holds the angles of those joints only, rad; links from ``_links_floats``."""
        xx, xy, xz, yx, yy, yz, zx, zy, zz, ox, oy, oz = frame or self._base_flat
        cos, sin = math.cos, math.sin
        for q, (th0, sign, off, d, a, ca, sa, cb, sb) in zip(qf, links[start:] if start else links):
            th = th0 + sign * (q + off)
            ct, st = cos(th), sin(th)
            # x, y turned about z by θ (x1, y1), in place
            xx, yx = ct * xx + st * yx, ct * yx - st * xx
            xy, yy = ct * xy + st * yy, ct * yy - st * xy
            xz, yz = ct * xz + st * yz, ct * yz - st * xz
            # exact zeros (a = 0, d = 0, α = 0, snapped α = ±90°) skip terms that add nothing
            if a:
                ox, oy, oz = ox + a * xx, oy + a * xy, oz + a * xz
            if d:
                ox, oy, oz = ox + d * zx, oy + d * zy, oz + d * zz
            if not ca:  # α = ±90° (``snap_right_angles``): y = ±z, z = ∓y1
                if sa > 0.0:
                    yx, yy, yz, zx, zy, zz = zx, zy, zz, -yx, -yy, -yz
                else:
                    yx, yy, yz, zx, zy, zz = -zx, -zy, -zz, yx, yy, yz
            elif sa:  # (α = 0: cos α = 1 exactly, y and z stay)
                yx, zx = ca * yx + sa * zx, ca * zx - sa * yx
                yy, zy = ca * yy + sa * zy, ca * zy - sa * yy
                yz, zz = ca * yz + sa * zz, ca * zz - sa * yz
            if sb:
                xx, zx = cb * xx - sb * zx, sb * xx + cb * zx
                xy, zy = cb * xy - sb * zy, sb * xy + cb * zy
                xz, zz = cb * xz - sb * zz, sb * xz + cb * zz
        return xx, xy, xz, yx, yy, yz, zx, zy, zz, ox, oy, oz

    def _flange_floats(self, frame: tuple[float, ...]) -> tuple[list, list, list, list]:
        """The flange's x, y, z columns and origin (lists of 3 floats) from the last joint's frame."""
        xx, xy, xz, yx, yy, yz, zx, zy, zz, ox, oy, oz = frame
        (f00, f01, f02, f03), (f10, f11, f12, f13), (f20, f21, f22, f23) = self._flange_f
        return (
            [f00 * xx + f10 * yx + f20 * zx, f00 * xy + f10 * yy + f20 * zy, f00 * xz + f10 * yz + f20 * zz],
            [f01 * xx + f11 * yx + f21 * zx, f01 * xy + f11 * yy + f21 * zy, f01 * xz + f11 * yz + f21 * zz],
            [f02 * xx + f12 * yx + f22 * zx, f02 * xy + f12 * yy + f22 * zy, f02 * xz + f12 * yz + f22 * zz],
            [ox + f03 * xx + f13 * yx + f23 * zx, oy + f03 * xy + f13 * yy + f23 * zy, oz + f03 * xz + f13 * yz + f23 * zz],
        )

    def _single(self, q: np.ndarray, params: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """(q, p) when the call is one configuration with one parameter vector, else None."""
        q = np.asarray(q, dtype=float)
        if q.ndim != 1 or (params is not None and np.ndim(params) != 1):
            return None
        return self._q(q), self._params(params)

    def flange_pose(self, q: np.ndarray, params: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Flange rotation (..., 3, 3) and position (..., 3) mm in the robot base frame."""
        one = self._single(q, params)
        if one is not None:
            cx, cy, cz, pos = self._walk_one(*one)
            return np.array([cx, cy, cz]).T, np.array(pos)
        cols, pos, _ = self._walk(self._q(q), self._params(params), record=False)
        return np.stack(cols, -1), pos

    def fk(self, q: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
        """Flange frames (..., 4, 4) in the robot base frame."""
        one = self._single(q, params)
        if one is not None:
            cx, cy, cz, pos = self._walk_one(*one)
            return np.array([[cx[0], cy[0], cz[0], pos[0]], [cx[1], cy[1], cz[1], pos[1]],
                             [cx[2], cy[2], cz[2], pos[2]], [0.0, 0.0, 0.0, 1.0]])
        rot, pos = self.flange_pose(q, params)
        t = np.zeros(pos.shape[:-1] + (4, 4))
        t[..., :3, :3] = rot
        t[..., :3, 3] = pos
        t[..., 3, 3] = 1.0
        return t

    def _markers_param(self, p: np.ndarray, ndim_out: int) -> np.ndarray:
        """Marker offsets of ``p`` shaped to broadcast against (..., m, 3) results."""
        lead_p = p.shape[:-1]
        return p[..., self.marker_slice()].reshape(lead_p + (1,) * (ndim_out - len(lead_p)) + (self.m, 3))

    def marker_positions(self, q: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
        """Every marker's position (..., m, 3) mm in the robot base frame."""
        one = self._single(q, params)
        if one is not None:
            cx, cy, cz, pos = self._walk_one(*one)
            mk = one[1][self.marker_slice()].tolist()
            return np.array([[pos[k] + mk[3 * j] * cx[k] + mk[3 * j + 1] * cy[k] + mk[3 * j + 2] * cz[k]
                              for k in range(3)] for j in range(self.m)]).reshape(self.m, 3)
        p = self._params(params)
        (cx, cy, cz), pos, _ = self._walk(self._q(q), p, record=False)
        mk = self._markers_param(p, pos.ndim - 1)
        return (
            pos[..., None, :]
            + mk[..., 0, None] * cx[..., None, :]
            + mk[..., 1, None] * cy[..., None, :]
            + mk[..., 2, None] * cz[..., None, :]
        )

    # --- derivatives -------------------------------------------------------------------
    def flange_jacobian(self, q: np.ndarray, params: np.ndarray | None = None) -> FlangeJacobian:
        """Analytic derivatives of the flange pose with respect to every parameter.

        For joint i with previous axis z and origin o, new x axis x', y axis after the twist y'',
        and new origin o': ∂p/∂δ = sign·z×(p−o), ∂p/∂d = z, ∂p/∂a = x', ∂p/∂α = x'×(p−o'),
        ∂p/∂β = y''×(p−o'); the angular parts are sign·z, 0, 0, x', y''.
        """
        cols, pos, rec = self._walk(self._q(q), self._params(params), record=True)
        z_prev, o_prev, x_new, y_new, o_new = (np.stack(v, -1) for v in zip(*rec))  # (..., 3, n)
        tip = pos[..., :, None]
        zeros = np.zeros_like(z_prev)
        no_markers = np.zeros(pos.shape + (3 * self.m,))
        sign = self.sign
        jp = np.concatenate(
            [
                cross(z_prev, tip - o_prev, axis=-2) * sign,
                z_prev,
                x_new,
                cross(x_new, tip - o_new, axis=-2),
                cross(y_new, tip - o_new, axis=-2),
                no_markers,
            ],
            -1,
        )
        jw = np.concatenate([z_prev * sign, zeros, zeros, x_new, y_new, no_markers], -1)
        return FlangeJacobian(rotation=np.stack(cols, -1), position=pos, jp=jp, jw=jw)

    def marker_jacobian(self, q: np.ndarray, params: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Marker positions (..., m, 3) mm and their derivatives (..., m, 3, P)."""
        p = self._params(params)
        fj = self.flange_jacobian(q, p)
        mk = self._markers_param(p, fj.position.ndim - 1)
        arm = np.einsum("...ij,...mj->...mi", fj.rotation, mk)  # (..., m, 3)
        positions = fj.position[..., None, :] + arm
        # d(R·mk)/dξ = ω_ξ × (R·mk) for every kinematic parameter ξ.
        jw = fj.jw[..., None, :, :]  # (..., 1, 3, P)
        j = fj.jp[..., None, :, :] + cross(jw, arm[..., :, :, None], axis=-2)
        ms = self.marker_slice()
        for k in range(self.m):
            j[..., k, :, ms.start + 3 * k : ms.start + 3 * k + 3] = fj.rotation
        return positions, j


def joint_frames(chain: Chain, q: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
    """Every DH frame, base first: (..., n+1, 4, 4) mm for q (..., n) rad and params (P,).

    Frame i follows link i's ``Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)``, θ = theta_i + sign_i (q_i + δ_i),
    as in ``Chain`` (frame n composed with the model's flange is ``Chain.fk``).
    """
    q = np.asarray(q, dtype=float)
    p = chain.nominal if params is None else np.asarray(params, dtype=float)
    n = chain.n
    theta = chain.theta0 + chain.sign * (q + p[:n])
    d, a, al, be = p[n:2 * n], p[2 * n:3 * n], p[3 * n:4 * n], p[4 * n:5 * n]
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa, cb, sb = np.cos(al), np.sin(al), np.cos(be), np.sin(be)
    link = np.zeros(theta.shape + (4, 4))
    link[..., 0, 0] = ct * cb - st * sa * sb
    link[..., 0, 1] = -st * ca
    link[..., 0, 2] = ct * sb + st * sa * cb
    link[..., 0, 3] = a * ct
    link[..., 1, 0] = st * cb + ct * sa * sb
    link[..., 1, 1] = ct * ca
    link[..., 1, 2] = st * sb - ct * sa * cb
    link[..., 1, 3] = a * st
    link[..., 2, 0] = -ca * sb
    link[..., 2, 1] = sa
    link[..., 2, 2] = ca * cb
    link[..., 2, 3] = d
    link[..., 3, 3] = 1.0
    frames = np.empty(theta.shape[:-1] + (n + 1, 4, 4))
    frames[..., 0, :, :] = chain.base
    for i in range(n):
        frames[..., i + 1, :, :] = frames[..., i, :, :] @ link[..., i, :, :]
    return frames


@dataclass(frozen=True)
class OffsetKinematics:
    """Point positions as a function of the zero-offsets alone, at fixed configurations.

    The fitters move only the zero-offsets, so everything else can be folded once per dataset.
    With φ_i = theta_i + sign_i·q_i and N_i = Tz(d) Tx(a) Rx(α) Ry(β), link i is
    Rz(φ_i) Rz(sign_i δ_i) N_i, hence for every row

        p = H_0 Rz(s_1 δ_1) H_1 Rz(s_2 δ_2) ⋯ H_{n−1} Rz(s_n δ_n) tip,

    H_0 = base·Rz(φ_1), H_i = N_i·Rz(φ_{i+1}), tip = N_n·flange·point. Evaluating it walks
    backwards applying a rotation about z (trigonometry of δ only, not of every row) and a fixed
    affine map per row — several times cheaper than ``Chain.marker_positions`` and with the same
    result to rounding.

    h: (n, 3, 4, k) components of H_0…H_{n−1} per row; tip: (3, k) mm; sign: (n,).
    """

    h: np.ndarray
    tip: np.ndarray
    sign: np.ndarray

    @property
    def n_rows(self) -> int:
        return int(self.tip.shape[1])

    #: Elements (offset vectors × rows) per block: a block's temporaries stay in the cache.
    BLOCK_ELEMENTS = 50_000

    def positions(self, offsets_rad: np.ndarray) -> np.ndarray:
        """Points in the base frame (..., k, 3) mm for offsets (..., n) rad."""
        off = np.asarray(offsets_rad, dtype=float)
        block = max(1, self.BLOCK_ELEMENTS // max(self.n_rows, 1))
        if off.ndim > 1 and off[..., 0].size > block:
            flat = off.reshape(-1, off.shape[-1])
            out = np.concatenate([self._positions(flat[i:i + block]) for i in range(0, flat.shape[0], block)])
            return out.reshape(off.shape[:-1] + out.shape[-2:])
        return self._positions(off)

    def _positions(self, off: np.ndarray) -> np.ndarray:
        ang = off * self.sign
        c = np.cos(ang)[..., None]  # (..., n, 1)
        s = np.sin(ang)[..., None]
        x, y, z = self.tip[0], self.tip[1], self.tip[2]
        for i in range(self.sign.size - 1, -1, -1):
            ci, si = c[..., i, :], s[..., i, :]
            xr = ci * x - si * y
            yr = si * x + ci * y
            h = self.h[i]
            x, y, z = (
                h[0, 0] * xr + h[0, 1] * yr + h[0, 2] * z + h[0, 3],
                h[1, 0] * xr + h[1, 1] * yr + h[1, 2] * z + h[1, 3],
                h[2, 0] * xr + h[2, 1] * yr + h[2, 2] * z + h[2, 3],
            )
        shape = np.broadcast_shapes(np.shape(x), np.shape(y), np.shape(z))
        out = np.empty(shape + (3,))
        out[..., 0], out[..., 1], out[..., 2] = x, y, z
        return out


def offset_kinematics(
    chain: Chain, q: np.ndarray, points_flange: np.ndarray, params: np.ndarray | None = None
) -> OffsetKinematics:
    """Fold ``chain`` at configurations q (k, n) rad for one flange-frame point per row (k, 3) mm.

    ``params`` (P,) supplies every non-offset parameter (default nominal); its offsets are ignored
    — pass them to ``OffsetKinematics.positions``.
    """
    q = chain._q(np.atleast_2d(q))
    p = chain._params(params)
    if p.ndim != 1:
        raise ValueError("offset_kinematics takes one parameter vector (P,), not a batch")
    pts = np.broadcast_to(np.asarray(points_flange, dtype=float), (q.shape[0], 3))
    n = chain.n
    phi = chain.theta0 + chain.sign * q  # (k, n)
    d, a = p[n : 2 * n], p[2 * n : 3 * n]
    links = homogeneous(rot_x(p[3 * n : 4 * n]) @ rot_y(p[4 * n : 5 * n]), np.stack([a, np.zeros(n), d], -1))  # (n, 4, 4)
    rz = homogeneous(rot_z(phi), np.zeros(3))  # (k, n, 4, 4)
    h = np.empty((n, q.shape[0], 4, 4))
    h[0] = chain.base @ rz[:, 0]
    for i in range(1, n):
        h[i] = links[i - 1] @ rz[:, i]
    last = links[n - 1] @ chain.flange
    tip = pts @ last[:3, :3].T + last[:3, 3]  # (k, 3)
    return OffsetKinematics(
        h=np.ascontiguousarray(np.moveaxis(h[:, :, :3, :], 1, -1)), tip=np.ascontiguousarray(tip.T), sign=chain.sign.copy()
    )
