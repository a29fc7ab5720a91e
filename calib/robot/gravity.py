"""Gravity torques on the joints, and the check for sag that the fit does not model.

Every link's mass sits at its centre of mass (the model's ``joints[i].mass_kg`` / ``com_mm``,
in that joint's DH frame), the tool's at ``tool.com_mm`` (flange frame). Joint i turns about
z_{i−1} through o_{i−1} and carries the gravity torque of every mass beyond it:

    τ_i = z_{i−1} · Σ_{j ≥ i} (c_j − o_{i−1}) × m_j g          [N·m]

A joint with compliance k_i (rad/(N·m)) yields by Δθ_i = k_i τ_i in the DH sense, i.e. by
Δq_i = sign_i k_i τ_i in the controller's convention: a joint-angle error that depends on the
configuration, which constant zero-offsets cannot absorb.

``compliance_score`` is the check a fit without a compliance model runs on its residuals: the
score (Lagrange-multiplier) test for adding the n compliances — whether the residuals lean in the
directions gravity sag would push the markers, beyond what the fitted parameters absorb.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.robot.kinematics import Chain, joint_frames


def _masses(chain: Chain) -> tuple[np.ndarray, np.ndarray]:
    """Masses (n+1,) kg and centres of mass (n+1, 3) mm in their own frames (links, then tool)."""
    model = chain.model
    if not model.has_dynamics:
        raise ValueError(f"{model.name}: the robot model gives no link masses and centres of mass "
                         "(joints[].mass_kg, com_mm); the gravity model needs them")
    m = np.array([j.mass_kg for j in model.joints] + [model.tool.mass_kg], dtype=float)
    c = np.array([j.com_mm for j in model.joints] + [model.tool.com_mm], dtype=float)
    return m, c


def gravity_torques(chain: Chain, q: np.ndarray, params: np.ndarray | None = None,
                    coms: np.ndarray | None = None) -> np.ndarray:
    """Gravity torque about each joint axis, DH sense: (..., n) N·m for q (..., n) rad.

    coms: centres of mass (n+1, 3) mm in the frames of ``params`` (links, then the tool in the
    flange frame) in place of the model's — the same masses written for a parameter set whose
    frames are turned against the model's (``moved_coms``)."""
    n = chain.n
    masses, coms0 = _masses(chain)
    coms = coms0 if coms is None else np.asarray(coms, dtype=float)
    frames = joint_frames(chain, q, params)
    tool_frame = frames[..., n, :, :] @ chain.flange
    own = np.concatenate([frames[..., 1:, :, :], tool_frame[..., None, :, :]], axis=-3)  # (..., n+1, 4, 4)
    centres = np.einsum("...ij,...j->...i", own[..., :3, :3], coms) + own[..., :3, 3]  # (..., n+1, 3) mm
    weight = masses[:, None] * np.asarray(chain.model.gravity_m_s2, dtype=float)  # (n+1, 3) N
    origins, axes = frames[..., :n, :3, 3], frames[..., :n, :3, 2]  # joint i about z_{i-1}
    tau = np.empty(np.shape(q)[:-1] + (n,))
    for i in range(n):
        lever = centres[..., i:, :] - origins[..., i, None, :]  # masses beyond joint i
        moment = np.cross(lever, weight[i:]).sum(axis=-2)  # N·mm
        tau[..., i] = np.einsum("...j,...j->...", moment, axes[..., i, :]) / 1000.0
    return tau


def moved_coms(chain: Chain, params: np.ndarray, model_params: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The model's centres of mass, given in the frames of ``model_params`` (P,) (the nominal
    model's branch), written in the frames of ``params`` (P,): (n+1, 3) mm, each moved by the rigid
    transform between the two sets' frames at the configuration q (n,) rad. For two sets that
    differ by frames turned 180° (mirrors, ``calib.robot.canonical``) the transforms are the same at
    every configuration, and ``gravity_torques(chain, q, params, moved)`` equals
    ``gravity_torques(chain, q, model_params)``; where it does not, the sets carry the masses
    differently."""
    n = chain.n
    _, coms = _masses(chain)
    f_new = joint_frames(chain, q, params)
    f_model = joint_frames(chain, q, model_params)
    own_new = np.concatenate([f_new[1:], (f_new[n] @ chain.flange)[None]])  # (n+1, 4, 4)
    own_model = np.concatenate([f_model[1:], (f_model[n] @ chain.flange)[None]])
    rel = np.linalg.solve(own_new, own_model)  # model frame → params' frame, per body
    return np.einsum("kij,kj->ki", rel[:, :3, :3], coms) + rel[:, :3, 3]


def chi2_sf(dof: int, x: float) -> float:
    """P(χ² with ``dof`` (integer ≥ 1) degrees of freedom > x), in closed form: the series of the
    regularised upper gamma function for integer and half-integer shape (no scipy import)."""
    if x <= 0:
        return 1.0
    h = 0.5 * x
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= h / i
            total += term
        return min(1.0, math.exp(-h) * total)
    term = math.sqrt(h) * 2.0 / math.sqrt(math.pi)  # h^(1/2) / Γ(3/2)
    total = 0.0
    for i in range((dof - 1) // 2):
        total += term
        term *= h / (i + 1.5)
    return min(1.0, math.erfc(math.sqrt(h)) + math.exp(-h) * total)


@dataclass(frozen=True)
class ComplianceScore:
    """Score test for joint compliance: statistic (χ² with ``dof``), its p-value, and the
    per-joint share of the statistic (which joints' sag the residuals resemble)."""

    statistic: float
    dof: int
    p_value: float
    joints: dict[str, float]

    @property
    def significant(self) -> bool:
        return self.p_value < 0.01


def compliance_score(chain: Chain, q: np.ndarray, jac_offsets: np.ndarray, jac_fitted: np.ndarray,
                     residuals: np.ndarray, sigma: float) -> ComplianceScore:
    """Whether residuals lean in the directions gravity sag would move the measurements.

    q: (k, n) rad, one row per measurement row; jac_offsets: (k, 3, n) ∂(prediction)/∂δ in the
    measurement frame; jac_fitted: (3k, p) the fit's Jacobian (what it already absorbs);
    residuals: (3k,) measured − predicted, mm; sigma: noise std, mm. The compliance columns are
    ∂/∂k_i = ∂/∂δ_i · sign_i τ_i(q) (Nm-scaled). Returns the score statistic rᵀP Jc (JcᵀP Jc)⁻¹
    JcᵀP r / σ² with P the projector off the fitted columns, and its χ² p-value.
    """
    tau = gravity_torques(chain, q)  # (k, n)
    jc = (jac_offsets * (chain.sign * tau)[:, None, :]).reshape(-1, chain.n)
    keep = np.linalg.norm(jc, axis=0) > 1e-9 * max(np.linalg.norm(jc), 1e-300)
    jc = jc[:, keep]
    qf, _ = np.linalg.qr(jac_fitted)
    jc_perp = jc - qf @ (qf.T @ jc)
    u, s, vt = np.linalg.svd(jc_perp, full_matrices=False)
    rank = int(np.sum(s > 1e-8 * s[0])) if s.size else 0
    if rank == 0:
        return ComplianceScore(0.0, 0, 1.0, {})
    proj = u[:, :rank].T @ residuals
    stat = float(proj @ proj / sigma ** 2)
    # Share per joint: the fitted compliances' contribution along each joint's column.
    coef = vt[:rank].T @ (proj / s[:rank])
    contrib = np.abs(coef * np.linalg.norm(jc_perp, axis=0))
    names = [ax for ax, k in zip(chain.model.axis_names, keep) if k]
    share = contrib / contrib.sum() if contrib.sum() > 0 else contrib
    return ComplianceScore(stat, rank, chi2_sf(rank, stat), {n: float(v) for n, v in zip(names, share)})


def sag_check(post, theta: np.ndarray, sigma_mm: dict[str, float]) -> ComplianceScore | None:
    """``compliance_score`` for a zero-offset posterior at ``theta`` (its mode), residuals
    whitened by each sensor's σ; None when the model has no masses (nothing to test)."""
    chain = post.chain
    if not chain.model.has_dynamics:
        return None
    full = post.full_vector(theta)
    params = post.chain_params(full)
    _, jac = chain.marker_jacobian(post.data.q_rad, params)
    k = post.k_pos  # the position rows (attitude rows, where measured, follow them: not scored here)
    s_idx = post.sensor_index[:k]
    rows = np.arange(k)
    j_off = jac[rows, post.marker_index][..., : chain.n]  # (k, 3, n) base frame
    rot, _ = post.corrections(full)
    total = rot[s_idx] @ post.b2s0[s_idx][:, :3, :3]
    j_off = total @ j_off  # sensor frame, like the predictions
    w = 1.0 / np.array([sigma_mm[s] for s in post.sensors])[s_idx]  # (k,)
    r = (post.position_residuals(theta) * w[:, None]).reshape(-1)
    jf = post.jacobian(theta)[: 3 * k] * np.repeat(w, 3)[:, None]
    return compliance_score(chain, post.data.q_rad, j_off * w[:, None, None], jf, r, 1.0)
