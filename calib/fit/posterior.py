"""The zero-offset posterior of the remastering paper (eqs. 8–15), generalised.

Model (eq. 8): a marker measured by sensor s in configuration i is predicted at

    p_pred = T*_s · base2sensor0_s · p_base(q_i + δ)

where ``base2sensor0_s`` is the initial registration (from three points, eq. 8, or least
squares), ``T*_s = Trans(x, y, z) · Rz(α) Ry(β) Rx(γ)`` its correction and ``δ`` the joint
zero-offsets added to the measured joint angles. Errors are isotropic with scale σ_s per sensor:
Gaussian (eqs. 10–13) or, for robustness, multivariate Student-t with ν degrees of freedom.
Priors: flat on δ and the corrections, Jeffreys 1/σ on each σ (eq. 14) — so with one sensor and
Gaussian errors the posterior is eq. 15: p ∝ σ^(−3n−2) exp(−E / 2σ²).

The **free vector** θ holds only what is being fitted, in SI-like units: offsets (rad),
then per sensor (x, y, z mm, α, β, γ rad), then optional link parameters (deviations of d, a mm
and α, β rad from nominal), then optional joint compliances (µrad/(N·m), see below). σ is carried
separately as log σ (mm).
``ParamMask`` says which entries are free; everything fixed sits at zero (nominal).

**Link parameters as nuisance.** Real arms have link errors of tenths of a millimetre; a
zero-offset-only model absorbs them into biased offsets and reports an uncertainty that covers
only the noise. With ``link_prior`` the link parameters enter with a Gaussian prior of the
manufacturing tolerance and are marginalised: the offsets' posterior then includes the
uncertainty of what the data cannot tell apart from a link error. This is our extension; the
paper's model (``link_prior=None``) has no such term.

**Tool markers as unknowns.** Nobody knows a reflector's position on the flange to 0.1 mm. With
marker entries in ``link_prior`` (chain parameter indices of ``Chain.marker_slice``, prior sd in
mm) the marker positions in the flange frame are fitted like the link parameters, under a
Gaussian prior about the model's values (``calib.fit.offsets.FitOptions.tool_prior_mm``). A marker's
position enters the prediction exactly (p = flange origin + R_flange·m is linear in m, so the
linearised predictor below carries it without approximation). The combinations the data cannot
tell apart — a shift along the last axis against that link's d, a rotation of the tool about
the last axis against that axis's zero-offset — are decided by the priors, and the offsets'
intervals include the tool's uncertainty.

**Joint compliance** (``compliance=True``, models with link masses): joint i yields under the
gravity torque τ_i(q) it carries by Δθ_i = k_i τ_i (``calib.robot.gravity``), i.e. its angle is off by
sign_i k_i τ_i in the controller's convention — like an offset that changes with the
configuration. Deflections are ~1e-4 rad, so the effect enters to first order, through the
offsets' Jacobian at a reference arm: p += Σ_i ∂p/∂δ_i · sign_i τ_i(q) k_i (the neglected terms
are ~1e-4 of the sag itself). The reference (``sag_params``) must be the fitted arm, not the
nominal one: a tool 10–30 mm off its drawing moves the lever of every sag by as much, and
offsets of 0.1° move the torques by 0.1 N·m — at the nominal arm this left 0.0008–0.003 mm rms per
axis of systematic error on a sagging iiwa (a sixth to two thirds of an averaged tracker row's
noise), which biased offsets known to ±0.0001° by 2–2.5 σ. ``calib.fit.offsets.fit_mode`` therefore
fits once at the nominal arm and again with the sag taken at that mode. Flat prior on each k_i.
"""

from __future__ import annotations

import contextlib

import math
from dataclasses import dataclass, field

import numpy as np

from calib.measure.dataset import Dataset
from calib.robot.kinematics import Chain, offset_kinematics
from calib.fit.offset_expansion import EXPANSION_TOLERANCE_MM, OffsetExpansion, expand_offsets
from calib.robot.transforms import apply, cross, euler_zyx_to_matrix

REG_NAMES = ("x", "y", "z", "alpha", "beta", "gamma")


@dataclass(frozen=True)
class ParamMask:
    """Which parameters are free. ``offsets``: (n,) bool; ``registration``: (S, 6) bool."""

    offsets: np.ndarray
    registration: np.ndarray
    reasons: dict[str, str] = field(default_factory=dict)
    link: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    compliance: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    @property
    def full(self) -> np.ndarray:
        return np.concatenate([self.offsets, self.registration.ravel(), self.link, self.compliance])

    def fix(self, full_index: int, reason: str, names: list[str]) -> "ParamMask":
        full = self.full.copy()
        full[full_index] = False
        n, r, ln = self.offsets.size, self.registration.size, self.link.size
        reasons = dict(self.reasons)
        reasons[names[full_index]] = reason
        return ParamMask(full[:n], full[n : n + r].reshape(self.registration.shape), reasons, full[n + r : n + r + ln],
                         full[n + r + ln :])


def _once(shared: dict | None, key: str, make):
    """``make()``, or what the first posterior sharing the dict ``shared`` made for ``key``."""
    if shared is None:
        return make()
    if key not in shared:
        shared[key] = make()
    return shared[key]


class OffsetPosterior:
    """Log posterior of zero-offsets, registration corrections and σ for one dataset.

    ``base2sensor0``: dict sensor name → (4, 4) initial registration.
    ``link_prior``: chain parameter index → prior standard deviation (mm or rad) of the link
    parameters to marginalise; their free flags are ``mask.link`` in the same order.
    """

    def __init__(
        self,
        chain: Chain,
        data: Dataset,
        base2sensor0: dict[str, np.ndarray],
        mask: ParamMask,
        *,
        error: str = "gaussian",
        nu: float = 4.0,
        link_prior: dict[int, float] | None = None,
        compliance: bool = False,
        sag_params: np.ndarray | None = None,
        orientation: bool = True,
        shared: dict | None = None,
    ) -> None:
        """``shared``: a dict shared by posteriors of the same data, registration, priors and sag
        that differ only in their masks (``calib.fit.offsets.fit_mode`` tries several): what depends
        on the data and not on the mask — the chain folded at every row, the gravity torques and
        the sag's levers, the attitude rows' sag levers, the Jacobian of every entry at the nominal
        model — is computed by the first and reused by the others, the same arrays (never written)."""
        self._shared = shared
        if error not in ("gaussian", "student"):
            raise ValueError(f"error model {error!r} not known; use 'gaussian' or 'student'")
        if error == "student" and not nu > 2:
            raise ValueError(f"Student-t needs nu > 2 for a finite variance, got {nu}")
        self.chain, self.data, self.mask = chain, data, mask
        self.error, self.nu = error, float(nu)
        self.sensors = sorted(base2sensor0)
        missing = set(data.sensors) - set(self.sensors)
        if missing:
            raise ValueError(f"no initial registration for sensor(s) {sorted(missing)}")
        self.b2s0 = np.stack([base2sensor0[s] for s in self.sensors])  # (S, 4, 4)
        self.sensor_index = np.array([self.sensors.index(s) for s in data.sensor])
        self.marker_index = np.array([chain.marker_names.index(m) for m in data.marker])
        self.n_rows = len(data)
        self.n = chain.n
        self.S = len(self.sensors)
        link_prior = link_prior or {}
        self.link_idx = np.array(list(link_prior), dtype=int)
        self.link_sd = np.array([link_prior[i] for i in self.link_idx], dtype=float)
        self.L = self.link_idx.size
        if mask.link.size != self.L:
            raise ValueError(f"the mask has {mask.link.size} link flags for {self.L} link parameters")
        if np.any(self.link_sd <= 0):
            raise ValueError("link prior standard deviations must be positive")
        self.C = chain.n if compliance else 0
        if mask.compliance.size != self.C:
            raise ValueError(f"the mask has {mask.compliance.size} compliance flags for {self.C} compliances")
        self.free = np.flatnonzero(mask.full)
        self.names = (
            [f"{ax}.offset" for ax in chain.model.axis_names]
            + [f"{s}.{r}" for s in self.sensors for r in REG_NAMES]
            + [chain.param_names[i] for i in self.link_idx]
            + [f"{ax}.compliance" for ax in chain.model.axis_names[: self.C]]
        )
        self.free_names = [self.names[i] for i in self.free]
        #: (L,) True where the entry is a tool-marker coordinate (mm, flange frame), not a link parameter.
        self.is_tool = self.link_idx >= chain.marker_slice().start
        self.rows_per_sensor = np.bincount(self.sensor_index, minlength=self.S)
        self._rows_of_sensor = [np.flatnonzero(self.sensor_index == k_s) for k_s in range(self.S)]
        # Only the offsets move inside the fit: fold the rest of the kinematics once.
        markers_flange = np.array([mk.xyz for mk in chain.model.tool.markers], dtype=float)
        self._offset_fk = _once(self._shared, "offset_fk", lambda: offset_kinematics(chain, data.q_rad,
                                                                             markers_flange[self.marker_index]))
        self._link_jac: np.ndarray | None = None  # (k, 3, L_links) when the link terms are linearised
        self._linearised = False
        self._link_ref = np.zeros(0)  # the link deviations the linear terms are taken about (``linearise_links``)
        self._expansion: OffsetExpansion | None = None
        #: Largest disagreement (mm) seen between the expanded predictor and the chain walk, and how
        #: many batches fell back to the walk (``expand``).
        self.expansion_check = {"max_error_mm": 0.0, "checked": 0, "walked_batches": 0}
        self._tool_fk = None  # offset kinematics at 4 points per row (marker, marker + e_x, e_y, e_z)
        self._flange_walked: tuple[np.ndarray, np.ndarray] | None = None  # (full vector(s), flange rotations)
        if self.is_tool.any():
            # Per row, the entries of the tool vector holding its marker's x, y, z (T: "not free").
            start = chain.marker_slice().start
            col = {int(i) - start: k for k, i in enumerate(self.link_idx[self.is_tool])}
            n_t = int(self.is_tool.sum())
            per_marker = np.array([[col.get(3 * m + c, n_t) for c in range(3)] for m in range(chain.m)], dtype=int)
            self._row_tool = per_marker[self.marker_index]
        if self.C:
            from calib.robot.gravity import gravity_torques

            #: The chain vector (P,) the sag's torques and lever arms are taken at (nominal: None).
            self.sag_params = chain.nominal if sag_params is None else np.asarray(sag_params, dtype=float)

            def sag() -> tuple[np.ndarray, np.ndarray]:
                torques = gravity_torques(chain, data.q_rad, self.sag_params)  # (k, n) N·m at that arm
                _, jac = chain.marker_jacobian(data.q_rad, self.sag_params)
                j_off = jac[np.arange(self.n_rows), self.marker_index][..., : self.n]  # (k, 3, n)
                return torques, j_off * (chain.sign * torques * 1e-6)[:, None, :]

            #: the torques (k, n) N·m; ∂ p_base / ∂ k (k, 3, n), mm per µrad/(N·m).
            self.torques, self._sag = _once(self._shared, "sag", sag)
        #: Position rows (the dataset's) and their sensors; ``n_rows``/``sensor_index`` count every
        #: residual row of three coordinates: the positions, then the attitude rows (``calib.fit.attitude``).
        self.k_pos = self.n_rows
        self._pos_sensor = self.sensor_index
        self.attitude = None
        #: Dataset row of each residual row (n_rows,): the positions, then the attitude rows'.
        self.row_source = np.arange(self.k_pos)
        if orientation and data.has_orientation:
            from calib.fit.attitude import AttitudeRows

            self.attitude = AttitudeRows(chain, data, self.sensors, self.b2s0,
                                         chain.sign * self.torques * 1e-6 if self.C else None,
                                         self.sag_params if self.C else None, shared=self._shared)
            self.n_rows = self.k_pos + self.attitude.k
            self.sensor_index = np.concatenate([self._pos_sensor, self.attitude.sensor_index])
            self.rows_per_sensor = np.bincount(self.sensor_index, minlength=self.S)
            self.row_source = np.concatenate([self.row_source, self.attitude.rows])

    # --- parameter packing -----------------------------------------------------------
    @property
    def dim(self) -> int:
        return int(self.free.size)

    @property
    def n_full(self) -> int:
        return self.n + 6 * self.S + self.L + self.C

    def full_vector(self, theta: np.ndarray) -> np.ndarray:
        """Free vector(s) (..., dim) → full vector(s) (..., n + 6·S + L) with fixed entries at 0."""
        theta = np.asarray(theta, dtype=float)
        full = np.zeros(theta.shape[:-1] + (self.n_full,))
        full[..., self.free] = theta
        return full

    def link_free(self) -> np.ndarray:
        """Positions in the free vector of the free link parameters, and their prior sds."""
        start = self.n + 6 * self.S
        pos = [k for k, i in enumerate(self.free) if start <= i < start + self.L]
        return np.array(pos, dtype=int), self.link_sd[self.free[pos] - start] if pos else np.zeros(0)

    def chain_params(self, full: np.ndarray) -> np.ndarray:
        """Chain parameter vector(s) (..., P) for full vector(s): offsets and link deviations applied."""
        params = self.chain.with_offsets(full[..., : self.n])
        if self.L:
            params[..., self.link_idx] += full[..., self.n + 6 * self.S : self.n + 6 * self.S + self.L]
        return params

    def corrections(self, full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """T*_s rotation (..., S, 3, 3) and translation (..., S, 3) from full vector(s)."""
        reg = full[..., self.n : self.n + 6 * self.S].reshape(full.shape[:-1] + (self.S, 6))
        return euler_zyx_to_matrix(reg[..., 3], reg[..., 4], reg[..., 5]), reg[..., :3]

    def linearise_links(self, theta: np.ndarray | None) -> None:
        """From now on, predict the link parameters' effect to first order, through their
        Jacobian at ``theta``'s offsets (None: back to the exact chain).

        The expansion is about ``theta``'s link values (the mode), exact there: the neglected terms
        are second order in the deviations from the mode. (About the nominal links, as before, a
        link error of 0.4 mm / 0.08° left 2e-3 mm at the mode — half a tracker's averaged noise —
        and moved the sampled posterior's mode away from the fitted one: Pareto k̂ 3.8.)
        Every prediction then costs the offsets-only kinematics plus one product instead of a walk
        of the whole chain.
        """
        if theta is None or not self.L:
            self._link_jac = None
            self._linearised = False
            return
        full = self.full_vector(np.asarray(theta, dtype=float))
        lo = self.n + 6 * self.S
        links = full[lo: lo + self.L]
        self._link_ref = links[~self.is_tool].copy()  # link terms about the mode's links, the tool at its values
        params = self.chain_params(full)
        self._linearised = True
        markers_flange = params[self.chain.marker_slice()].reshape(-1, 3)[self.marker_index]
        self._lin_fk = offset_kinematics(self.chain, self.data.q_rad, markers_flange, params)
        link_cols = self.link_idx[~self.is_tool]
        if link_cols.size:
            _, jac = self.chain.marker_jacobian(self.data.q_rad, params)
            self._link_jac = np.ascontiguousarray(jac[np.arange(self.k_pos), self.marker_index][..., link_cols])
            self._link_jac_t = np.ascontiguousarray(self._link_jac.reshape(-1, link_cols.size).T)  # (L_links, 3k)
        else:
            self._link_jac = None
        if self.is_tool.any():
            self._tool_ref = links[self.is_tool].copy()
            mk = params[self.chain.marker_slice()].reshape(-1, 3)[self.marker_index]  # (k, 3) at theta
            pts = np.concatenate([mk, mk + [1.0, 0, 0], mk + [0, 1.0, 0], mk + [0, 0, 1.0]])
            self._tool_fk = offset_kinematics(self.chain, np.tile(self.data.q_rad, (4, 1)), pts, params)

    def expand(self, theta: np.ndarray | None) -> None:
        """From now on, predict by ``calib.fit.offset_expansion`` about ``theta``: second order in the
        offsets, first in the link parameters (as ``linearise_links``), exact in the tool to first
        order in the offsets — one matrix product per batch instead of a walk of the chain. Each
        batch is checked at its two proposals farthest from ``theta`` against the walk
        (``linearise_links`` about ``theta``) and walked instead if they differ by more than
        ``EXPANSION_TOLERANCE_MM``. None: back to the exact chain."""
        self.linearise_links(theta)
        if theta is None:
            self._expansion = None
            if self.attitude is not None:
                self.attitude.expand(self, None)
            return
        full = self.full_vector(np.asarray(theta, dtype=float))
        if self.attitude is not None:  # the attitude rows' flange rotations alike (``AttitudeRows.expand``)
            self.attitude.expand(self, full)
        self._expansion_offsets = np.flatnonzero(self.mask.offsets)
        self._expansion_ref = full[self._expansion_offsets].copy()
        self._expansion = expand_offsets(self.chain, self.data.q_rad, self.marker_index, self.chain_params(full),
                                         self._expansion_offsets, self.link_idx[~self.is_tool], self.link_idx[self.is_tool])

    @property
    def expanding(self) -> bool:
        """Whether positions are predicted by the offset expansion (``expand``; not within ``exact``)."""
        return self._expansion is not None

    @property
    def expanded(self) -> bool:
        """Whether predictions go through the expansion or the linearised links (``expand``)."""
        return self._expansion is not None or self._linearised

    @contextlib.contextmanager
    def exact(self):
        """Within: predict by walking the whole chain (the expansion and linearisation set aside)."""
        saved = self._expansion, self._linearised
        self._expansion, self._linearised = None, False
        try:
            yield self
        finally:
            self._expansion, self._linearised = saved

    def _expanded_base(self, full: np.ndarray) -> np.ndarray:
        """Markers in the base frame (..., k, 3) mm by the expansion, checked (see ``expand``)."""
        lead = full.shape[:-1]
        flat = full.reshape(-1, full.shape[-1])
        lo = self.n + 6 * self.S
        links = flat[:, lo: lo + self.L]
        eps = flat[:, self._expansion_offsets] - self._expansion_ref
        out = self._expansion.positions(eps, links[:, ~self.is_tool] - self._link_ref, links[:, self.is_tool] - self._tool_ref
                                        if self.is_tool.any() else links[:, :0])
        far = np.unique(np.argsort(np.abs(eps).sum(axis=-1))[-2:])
        walked = self._walked_base(flat[far])
        err = float(np.abs(walked - out[far]).max()) if far.size else 0.0
        check = self.expansion_check
        check["max_error_mm"] = max(check["max_error_mm"], err)
        check["checked"] += int(far.size)
        if err > EXPANSION_TOLERANCE_MM:
            check["walked_batches"] += 1
            out = self._walked_base(flat)
        return out.reshape(lead + out.shape[-2:])

    # --- prediction and residuals ----------------------------------------------------
    def _walked_base(self, full: np.ndarray) -> np.ndarray:
        """Markers in the base frame (..., k, 3) mm by walking the (offsets-only folded) chain; the
        link terms to first order when ``linearise_links`` is on. Compliance sag not included."""
        if self.L and self._linearised:
            links = full[..., self.n + 6 * self.S: self.n + 6 * self.S + self.L]
            if self._tool_fk is not None:
                # Exact in the marker position: p = p(m_ref) + R_flange (m − m_ref), R's columns
                # from the same folded kinematics at m_ref + e_x, e_y, e_z.
                k = self.k_pos
                four = self._tool_fk.positions(full[..., : self.n])  # (..., 4k, 3)
                p_base = four[..., :k, :]
                dev = links[..., self.is_tool] - self._tool_ref  # (..., T)
                dev = np.concatenate([dev, np.zeros(dev.shape[:-1] + (1,))], axis=-1)[..., self._row_tool]  # (..., k, 3)
                for c in range(3):
                    p_base = p_base + dev[..., c, None] * (four[..., (c + 1) * k:(c + 2) * k, :] - four[..., :k, :])
            else:
                p_base = self._lin_fk.positions(full[..., : self.n])
            if self._link_jac is not None:
                p_base = p_base + ((links[..., ~self.is_tool] - self._link_ref) @ self._link_jac_t).reshape(p_base.shape)  # one BLAS product
        elif self.L:
            params = self.chain_params(full)
            rot, flange = self.chain.flange_pose(self.data.q_rad, params)  # (..., k, 3, 3), (..., k, 3)
            if self.attitude is not None:  # the attitude rows turn with the same walk (``flange_rotation``)
                self._flange_walked = (full, rot)
            markers = self.chain._markers_param(params, flange.ndim - 1)  # (..., 1, m, 3)
            pos = flange[..., None, :] + np.einsum("...ij,...mj->...mi", rot, markers)  # (..., k, m, 3)
            p_base = pos[..., np.arange(self.k_pos), self.marker_index, :]
        else:
            p_base = self._offset_fk.positions(full[..., : self.n])  # (..., k, 3)
        return p_base

    def flange_rotation(self, full: np.ndarray) -> np.ndarray | None:
        """The flange rotations (..., k, 3, 3) of every dataset row at full vector(s) ``full``
        where the last exact walk of the positions was at the same vector(s), else None."""
        walked = self._flange_walked
        if walked is None or walked[0].shape != full.shape or not np.array_equal(walked[0], full):
            return None
        return walked[1]

    def predict(self, theta: np.ndarray) -> np.ndarray:
        """Predicted marker positions in each row's sensor frame: (..., k, 3) mm."""
        full = self.full_vector(theta)
        p_base = self._expanded_base(full) if self._expansion is not None else self._walked_base(full)
        if self.C:
            p_base = p_base + np.einsum("kjc,...c->...kj", self._sag, full[..., self.n_full - self.C :])
        rot, trans = self.corrections(full)  # (..., S, 3, 3), (..., S, 3)
        # Compose T*_s · base2sensor0_s once per draw and sensor, then apply it to that sensor's rows.
        r_total = rot @ self.b2s0[:, :3, :3]  # (..., S, 3, 3)
        t_total = np.einsum("...ij,...j->...i", rot, self.b2s0[:, :3, 3]) + trans  # (..., S, 3)
        if self.S == 1:
            return p_base @ np.swapaxes(r_total[..., 0, :, :], -1, -2) + t_total[..., 0, None, :]
        out = np.empty_like(p_base)
        for k_s, rows in enumerate(self._rows_of_sensor):
            out[..., rows, :] = p_base[..., rows, :] @ np.swapaxes(r_total[..., k_s, :, :], -1, -2) + t_total[..., k_s, None, :]
        return out

    def position_residuals(self, theta: np.ndarray) -> np.ndarray:
        """measured − predicted positions, (..., k, 3) mm (the dataset's rows)."""
        return self.data.xyz_mm - self.predict(theta)

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """measured − predicted, (..., n_rows, 3) mm: the positions, then the weighted attitude rows
        (``calib.fit.attitude``) where orientation is measured."""
        r = self.data.xyz_mm - self.predict(theta)
        if self.attitude is None:
            return r
        return np.concatenate([r, self.attitude.residuals(self, self.full_vector(theta))], axis=-2)

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """∂ predicted / ∂ θ_free for one θ: (n_rows·3, dim), positions then attitude rows."""
        theta = np.asarray(theta, dtype=float)
        if self._shared is not None and not theta.any():  # the nominal model: shared between masks
            return _once(self._shared, "zero_jacobian", lambda: self._jacobian_full(self.full_vector(theta)))[:, self.free]
        return self._jacobian_full(self.full_vector(theta))[:, self.free]

    def _jacobian_full(self, full: np.ndarray) -> np.ndarray:
        """∂ predicted / ∂ (full vector) at one full vector: (n_rows·3, n_full)."""
        params = self.chain_params(full)
        pos, jac = self.chain.marker_jacobian(self.data.q_rad, params)  # (k, m, 3), (k, m, 3, P)
        rows = np.arange(self.k_pos)
        p_base = pos[rows, self.marker_index]
        j_rows = jac[rows, self.marker_index]  # (k, 3, P)
        j_off = j_rows[..., : self.n]  # (k, 3, n)
        b2s0 = self.b2s0[self._pos_sensor]
        rot, trans = self.corrections(full)  # (S,3,3), (S,3)
        r_rows = rot[self._pos_sensor]
        total = r_rows @ b2s0[:, :3, :3]  # (k, 3, 3)
        j = np.zeros((self.k_pos, 3, self.n_full))
        j[..., : self.n] = total @ j_off
        if self.L:
            j[..., self.n + 6 * self.S : self.n + 6 * self.S + self.L] = total @ j_rows[..., self.link_idx]
        if self.C:
            j[..., self.n_full - self.C :] = total @ self._sag
            p_base = p_base + np.einsum("kjc,c->kj", self._sag, full[self.n_full - self.C :])
        p_s0 = apply(b2s0, p_base)
        rp = np.einsum("kij,kj->ki", r_rows, p_s0)  # R* p_s0
        reg = full[self.n : self.n + 6 * self.S].reshape(self.S, 6)
        ca, sa = np.cos(reg[:, 3]), np.sin(reg[:, 3])
        cb, sb = np.cos(reg[:, 4]), np.sin(reg[:, 4])
        ez = np.array([0.0, 0.0, 1.0])
        ey_rot = np.stack([-sa, ca, np.zeros_like(ca)], -1)  # Rz(α) e_y
        ex_rot = np.stack([ca * cb, sa * cb, -sb], -1)  # Rz(α) Ry(β) e_x
        s = self._pos_sensor
        for k_s in range(self.S):
            rows_s = s == k_s
            col = self.n + 6 * k_s
            j[rows_s, :, col : col + 3] = np.eye(3)
            j[rows_s, :, col + 3] = cross(ez, rp[rows_s])
            j[rows_s, :, col + 4] = cross(ey_rot[k_s], rp[rows_s])
            j[rows_s, :, col + 5] = cross(ex_rot[k_s], rp[rows_s])
        if self.attitude is not None:
            j = np.concatenate([j, self.attitude.jacobian(self, full)])
        return j.reshape(self.n_rows * 3, -1)

    # --- densities ---------------------------------------------------------------------
    def log_posterior(self, theta: np.ndarray, log_sigma: np.ndarray) -> np.ndarray:
        """log p(θ, σ | data) up to a constant; batched: θ (..., dim), log σ (..., S).

        The prior on each σ is the paper's: eq. 14 writes p(Θ, σ²) ∝ σ⁻² and eq. 16 samples
        eq. 15 as a density over σ, i.e. p(σ) ∝ σ⁻². The density here is with respect to
        (θ, log σ), so it carries the Jacobian σ: −log σ per sensor in total. (Jeffreys' 1/σ
        would differ by one power of σ out of 3n + 2 — immaterial, but we follow the paper so the
        reference sampler and the fast one target exactly the same distribution.)
        """
        log_sigma = np.asarray(log_sigma, dtype=float)
        r2 = np.sum(self.residuals(theta) ** 2, axis=-1)  # (..., k)
        sig2 = np.exp(2 * log_sigma)[..., self.sensor_index]  # (..., k)
        if self.error == "gaussian":
            ll = -0.5 * r2 / sig2 - 3.0 * log_sigma[..., self.sensor_index]
        else:
            nu = self.nu
            # Multivariate t in 3-D with scale σ: density ∝ σ^-3 (1 + r²/(ν σ²))^(-(ν+3)/2).
            ll = -0.5 * (nu + 3) * np.log1p(r2 / (nu * sig2)) - 3.0 * log_sigma[..., self.sensor_index]
            ll = ll + math.lgamma((nu + 3) / 2) - math.lgamma(nu / 2)
        out = ll.sum(axis=-1) - log_sigma.sum(axis=-1)
        if self.L:
            pos, sd = self.link_free()
            out = out - 0.5 * np.sum((np.asarray(theta)[..., pos] / sd) ** 2, axis=-1)
        return out

    def sse(self, theta: np.ndarray) -> np.ndarray:
        """E of eq. 7 per sensor: (..., S) mm²."""
        r2 = np.sum(self.residuals(theta) ** 2, axis=-1)
        out = np.zeros(r2.shape[:-1] + (self.S,))
        for k_s in range(self.S):
            out[..., k_s] = r2[..., self.sensor_index == k_s].sum(axis=-1)
        return out
