"""Attitude rows of the zero-offset posterior (``calib.fit.posterior.OffsetPosterior``).

Where the dataset carries a measured orientation (``Dataset.rot``: a 6-DoF target's frame
``R_sensor←target``), each such row adds the residual

    e = log(R_measured · R_predicted⁻¹)        (rad, sensor frame; a rotation vector, never Euler)

with R_predicted = T*_s · base2sensor0_s · exp(ω_sag) · R_flange(q + δ; links) · R_target, weighted by
w = σ_position / σ_attitude (mm/rad; the data's median ``std_mm`` over the row's ``att_std_rad``, or
√L of ``IdentOptions.orientation_weight`` where the data state no spreads), so that a weighted
attitude row counts like a position row against the sensor's σ. The rows enter the posterior as
extra rows of three coordinates each; σ, the priors and every method are unchanged.

**The target's frame on the flange**, R_target, per frame marker:
- known (the model gives the marker's ``rpy_deg``): held at it — then the attitude determines the
  last joint's offset even from one marker on the last axis;
- unknown: **profiled** — for every parameter vector the frame is set to its weighted chordal
  mean ``argmax_F Σ w² tr(Fᵀ A_iᵀ R_meas,i)``, A_i = sensor rotation · flange rotation, and the
  Jacobian is the variable-projection one (the frame's three columns projected out), so the
  curvature carries the frame's uncertainty: a turn of the target about the last axis cannot be
  told from that axis's offset, and the attitude rows then say nothing about that offset.

**Compliance**: a joint yielding by Δθ_i = sign_i k_i τ_i turns the flange by ω_sag = Σ z_i Δθ_i
(base frame), to the same first order as the positions' sag (``calib.robot.gravity``).
"""

from __future__ import annotations

import math

import numpy as np

from calib.fit.offset_expansion import EXPANSION_TOLERANCE_MM
from calib.measure.dataset import Dataset
from calib.robot.kinematics import Chain
from calib.robot.transforms import euler_zyx_to_matrix, exp_so3, log_so3, so3_left_jacobian_inv

#: mm² per rad², the weight² of an attitude row when the data state no spreads (as
#: ``calib.fit.identification.IdentOptions.orientation_weight``).
DEFAULT_ORIENTATION_WEIGHT = 100.0


def _polar(m: np.ndarray) -> np.ndarray:
    """The rotation nearest (..., 3, 3) matrices m (chordal mean), batched."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


class AttitudeRows:
    """The attitude rows of one dataset. ``sensors``: sorted sensor names; ``b2s0``: (S, 4, 4)."""

    def __init__(self, chain: Chain, data: Dataset, sensors: list[str], b2s0: np.ndarray,
                 sag_gain: np.ndarray | None = None, sag_params: np.ndarray | None = None, *,
                 shared: dict | None = None) -> None:
        """``sag_gain``: (k, n) joint-angle change per µrad/(N·m) (sign·τ·1e-6) when compliance is
        fitted; ``sag_params``: the chain vector (P,) the sag is taken at (None: nominal);
        ``shared``: the posteriors' shared dict (``OffsetPosterior``): the sag levers computed once."""
        self.chain = chain
        rot = np.asarray(data.rot, dtype=float)
        self.rows = np.flatnonzero(np.isfinite(rot).all(axis=(1, 2)))  # dataset rows with an orientation
        self.k = self.rows.size
        self.q = data.q_rad[self.rows]
        self.r_meas = rot[self.rows]
        self.sensor_index = np.array([sensors.index(s) for s in data.sensor[self.rows]], dtype=int)
        self.b2s0_r = b2s0[:, :3, :3]
        sp = float(np.nanmedian(data.std_mm)) if np.isfinite(data.std_mm).any() else math.nan
        att = data.att_std_rad[self.rows] if data.att_std_rad is not None else np.full(self.k, np.nan)
        good = np.isfinite(att) & (att > 0)
        if math.isfinite(sp) and sp > 0 and good.any():
            att = np.where(good, att, np.median(att[good]))
            self.weight = sp / att  # (ko,) mm per rad
            self.weight_info = {"how": "σ_position / σ_attitude of each row (the data's spreads)",
                                "sigma_position_mm": sp, "median_mm_per_rad": float(np.median(self.weight))}
        else:
            self.weight = np.full(self.k, math.sqrt(DEFAULT_ORIENTATION_WEIGHT))
            self.weight_info = {"how": f"√L with L = {DEFAULT_ORIENTATION_WEIGHT:g} mm² (the data state no spreads)",
                                "median_mm_per_rad": math.sqrt(DEFAULT_ORIENTATION_WEIGHT)}
        markers = data.marker[self.rows]
        self.frame_markers = sorted(set(markers.tolist()))
        self.frame_index = np.array([self.frame_markers.index(m) for m in markers], dtype=int)
        frames, known = [], []
        for m in self.frame_markers:
            rpy = chain.model.tool.markers[chain.model.marker_index(m)].rpy_deg
            known.append(rpy is not None)
            frames.append(euler_zyx_to_matrix(*np.radians([rpy[2], rpy[1], rpy[0]])) if rpy is not None else np.eye(3))
        self.frame0 = np.array(frames).reshape(-1, 3, 3)
        self.known = np.array(known, dtype=bool)
        self._expansion = None  # (``expand``)
        self.sag_w = None
        if sag_gain is not None:
            if shared is not None and "attitude_sag_w" in shared:
                self.sag_w = shared["attitude_sag_w"]
            else:
                ref = chain.nominal if sag_params is None else sag_params
                jw = chain.flange_jacobian(self.q, ref).jw[..., : chain.n]  # (ko, 3, n)
                self.sag_w = jw * sag_gain[self.rows][:, None, :]  # rad per µrad/(N·m)
                if shared is not None:
                    shared["attitude_sag_w"] = self.sag_w

    # --- the expansion (``OffsetPosterior.expand``) ------------------------------------------
    def expand(self, post, full: np.ndarray | None) -> None:
        """While ``post`` predicts by its expansion, predict the flange rotations to first order about
        the full vector ``full`` (its mode): R_f(x) ≈ exp([Σ_c ω_c (x_c − x_mode,c)]) R_f(x_mode), ω_c
        the flange's angular Jacobian (base frame) of each offset and link entry at the mode (the
        tool does not turn the flange) — one product per batch instead of a walk of the chain; the
        neglected terms are second order in the deviations (1e-7 rad for 4e-4 rad). Each batch is
        checked against the walk at its two proposals farthest from the mode (``_expanded_flange``).
        None: back to walking."""
        if full is None:
            self._expansion = None
            return
        params = post.chain_params(full)
        links = np.flatnonzero(~post.is_tool) if post.L else np.zeros(0, dtype=int)
        cols = np.r_[np.arange(post.n), post.n + 6 * post.S + links]  # entries of the full vector
        jw = self.chain.flange_jacobian(self.q, params).jw[..., np.r_[np.arange(post.n), post.link_idx[links]]]
        r0, _ = self.chain.flange_pose(self.q, params)
        self._expansion = (cols, full[cols].copy(), np.ascontiguousarray(jw), r0)

    def _expanded_flange(self, post, full: np.ndarray) -> np.ndarray:
        """Flange rotations (..., ko, 3, 3) by the expansion; where the two proposals of the batch
        farthest from the mode differ from the walk by more than ``EXPANSION_TOLERANCE_MM`` (weighted
        as the residuals are), the batch is walked instead."""
        cols, ref, jw, r0 = self._expansion
        lead = full.shape[:-1]
        flat = full.reshape(-1, full.shape[-1])
        dx = flat[:, cols] - ref  # (b, c)
        out = exp_so3(np.einsum("kjc,bc->bkj", jw, dx)) @ r0  # (b, ko, 3, 3)
        far = np.unique(np.argsort(np.abs(dx[:, : post.n]).sum(axis=-1))[-2:])
        walked, _ = self.chain.flange_pose(self.q, post.chain_params(flat[far]))
        angle = np.linalg.norm(log_so3(walked @ np.swapaxes(out[far], -1, -2)), axis=-1)  # (far, ko) rad
        err = float((self.weight * angle).max()) if far.size else 0.0
        check = post.expansion_check
        check["attitude_max_error_mm"] = max(check.get("attitude_max_error_mm", 0.0), err)
        if err > EXPANSION_TOLERANCE_MM:
            check["attitude_walked_batches"] = check.get("attitude_walked_batches", 0) + 1
            out, _ = self.chain.flange_pose(self.q, post.chain_params(flat))
        return out.reshape(lead + out.shape[-3:])

    # --- prediction ----------------------------------------------------------------------
    def _sensor_flange(self, post, full: np.ndarray) -> np.ndarray:
        """A = sensor-from-base rotation · flange rotation, (..., ko, 3, 3)."""
        walked = post.flange_rotation(full)  # the positions' walk at the same vector(s), if it was one
        if walked is not None:
            r_f = walked[..., self.rows, :, :]
        elif post.expanding and self._expansion is not None:
            r_f = self._expanded_flange(post, full)
        else:
            r_f, _ = self.chain.flange_pose(self.q, post.chain_params(full))  # (..., ko, 3, 3)
        if self.sag_w is not None:
            comp = full[..., post.n_full - post.C:]
            r_f = exp_so3(np.einsum("kjn,...n->...kj", self.sag_w, comp)) @ r_f
        rot, _ = post.corrections(full)  # (..., S, 3, 3)
        total = rot @ self.b2s0_r  # (..., S, 3, 3)
        return total[..., self.sensor_index, :, :] @ r_f

    def frames(self, a: np.ndarray) -> np.ndarray:
        """R_target per row (..., ko, 3, 3): the model's where known, else the weighted chordal mean."""
        out = np.broadcast_to(self.frame0[self.frame_index], a.shape).copy()
        w2 = self.weight ** 2
        for f in np.flatnonzero(~self.known):
            rows = self.frame_index == f
            m = np.einsum("k,...kji,kjl->...il", w2[rows], a[..., rows, :, :], self.r_meas[rows])
            out[..., rows, :, :] = _polar(m)[..., None, :, :]
        return out

    def residuals(self, post, full: np.ndarray) -> np.ndarray:
        """Weighted attitude residuals w·log(R_meas R_pred⁻¹), (..., ko, 3) "mm"."""
        a = self._sensor_flange(post, full)
        r_pred = a @ self.frames(a)
        return self.weight[:, None] * log_so3(self.r_meas @ np.swapaxes(r_pred, -1, -2))

    def jacobian(self, post, full: np.ndarray) -> np.ndarray:
        """∂(weighted prediction)/∂(full vector) at one full vector, (ko, 3, n_full): minus the
        residuals' derivative, as ``OffsetPosterior.jacobian`` gives the positions'; the profiled
        frames' columns projected out (variable projection)."""
        n, S = post.n, post.S
        params = post.chain_params(full)
        fj = self.chain.flange_jacobian(self.q, params)
        a = self._sensor_flange(post, full)  # (ko,3,3)
        e = log_so3(self.r_meas @ np.swapaxes(a @ self.frames(a), -1, -2))
        so = (post.corrections(full)[0] @ self.b2s0_r)[self.sensor_index]  # (ko,3,3)
        om = np.zeros((self.k, 3, post.n_full))  # rotation (sensor frame) per unit of each entry
        om[..., :n] = so @ fj.jw[..., :n]
        if post.L:
            om[..., n + 6 * S: n + 6 * S + post.L] = so @ fj.jw[..., post.link_idx]
        if self.sag_w is not None:
            om[..., post.n_full - post.C:] = so @ self.sag_w
        reg = full[n: n + 6 * S].reshape(S, 6)
        ca, sa = np.cos(reg[:, 3]), np.sin(reg[:, 3])
        cb, sb = np.cos(reg[:, 4]), np.sin(reg[:, 4])
        axes = [np.broadcast_to([0.0, 0.0, 1.0], (S, 3)), np.stack([-sa, ca, np.zeros_like(ca)], -1),
                np.stack([ca * cb, sa * cb, -sb], -1)]
        for s in range(S):
            rows = self.sensor_index == s
            for ax in range(3):
                om[rows, :, n + 6 * s + 3 + ax] = axes[ax][s]
        jl = so3_left_jacobian_inv(-e) * self.weight[:, None, None]  # (ko,3,3)
        g = np.einsum("kij,kjp->kip", jl, om)
        for f in np.flatnonzero(~self.known):
            rows = self.frame_index == f
            b = (jl[rows] @ a[rows]).reshape(-1, 3)  # the frame's columns (3·kf, 3)
            gf = g[rows].reshape(-1, post.n_full)
            gf = gf - b @ np.linalg.solve(b.T @ b, b.T @ gf)
            g[rows] = gf.reshape(-1, 3, post.n_full)
        return g
