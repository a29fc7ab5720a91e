"""Full kinematic identification: every identifiable model parameter by Levenberg–Marquardt.

Jointly with the sensor registration (per sensor) and the marker offsets on the tool, as in the
pose-selection seed (Sec. 2 and 4) — but with the analytic Jacobian of ``calib.robot.kinematics``
instead of finite differences.

Which parameters are identifiable is decided from the Jacobian, not assumed: columns (scaled to
mm of marker motion, angles × lever arm) are taken in a preferred order — registration, marker
positions on the flange, joint offsets, link offsets d, lengths a, twists α, torsions β (``mdh``
models only) —
and a column that the columns already kept reproduce (relative residual below ``rank_tol``) is
excluded, with a reason naming the parameters it duplicates. Excluded parameters stay at their
nominal values. The tool comes before the joints: a last link's d, a, α, β and the last axis's
offset that the marker positions explain are kept nominal and the markers take the motion, so the
corrected model moves the tool, not the flange, and stays right for any other tool on it.

**Tool prior.** Marker positions are unknowns under a Gaussian prior about the model's values
(``IdentOptions.tool_prior_mm`` per coordinate; 0: exact, not fitted): prior rows
σ/sd · (m − m_nominal) join the residuals, σ the rms of a first solve without them.

**Starts.** Levenberg–Marquardt finds the minimum nearest its start. ``identify`` solves in
stages from nominal (registration, marker positions and joint offsets first, then every
parameter), also in one stage from nominal and from seeded random starts about it
(``IdentOptions.n_starts``; ``calib.fit.multistart``), all on one objective, keeps the best and says
when starts end in minima of materially different cost, and when markers end far outside their
prior (a tool traded against a joint turned far from its zero). A model file with a joint zero
off by 180° (a convention slip) leaves every start about nominal far away: the ±180° flips of
each fitted zero are screened by their cheap first stage and the ones the data prefer are
solved too (``_flip_screen``).

**Canonical answers.** The best solution is written on the nominal model's branch
(``calib.robot.canonical``): joint offsets in (−180°, 180°], mirrored links (θ + 180°, −a, −α …) mapped
back, the forward kinematics of every measured marker checked unchanged; ``IdentResult.canonical``
says what was mapped.

Residuals: positions (mm). Where orientation is measured (pose rows: ``Dataset.rot``, a 6-DoF
target's frame ``R_sensor←target``), each such row adds the attitude residual as a **rotation
vector**, ``log(R_measured · R_predicted⁻¹)`` (rad, sensor frame; never Euler angles), with
R_predicted = R_registration · R_flange(q) · R_target, weighted by σ_position / σ_attitude (the
data's median ``std_mm`` over the row's ``att_std_rad``) so that both kinds count by their stated
uncertainty; where the data state no spreads, by √L (``IdentOptions.orientation_weight``, L in
mm², the role of the seed's eq. 19 factor). The target's frame on the flange, R_target, is
fitted per marker (three ``{marker}.frame_r*`` columns, a rotation vector applied on the flange
side): about the model's ``rpy_deg`` under a Gaussian prior (``tool_rotation_prior_deg``; 0:
exact), or freely from a start the data give when the model has none. A turn of the target about
the last axis cannot be told from that axis's offset: the frame takes it (like the markers'
positions) unless it is known (prior 0), and then orientation identifies the last offset even
from one marker on the last axis (``calib.fit.pose_identifiability``).

**Compliance** (``IdentOptions.compliance``): joint i yields under the gravity torque it carries by
Δθ_i = sign_i k_i τ_i (``calib.robot.gravity``), entered to first order through the offsets'
Jacobian. Both the torques and the lever arms are taken at the arm being evaluated — at the
solution the identified arm (offsets, links, markers), never the data sheet's: a zero off by
2° and links off by tenths of a millimetre move the torques by a few %, which at the nominal arm
left 0.0045 mm rms per axis of systematic error on a sagging iiwa (the noise of an averaged
tracker row) and biased an offset by 3σ (``tests/calib/test_sag_fitted_arm.py``).

**Compliance with orientation**: a joint that yields by
Δθ_i = sign_i k_i τ_i turns the flange and everything on it by ω = Σ_i z_i Δθ_i (base frame), so the
predicted attitude is exp(ω)·R_flange(q), to the same first order as the positions' sag; the
compliances get attitude rows as well as position rows.

**Canonical answers with link masses**: the model's centres of mass belong to the nominal model's
frames, so a mirrored solution (a frame turned by 180°) evaluated its sag with those masses turned
with the frame — not the robot's. Mapping it back carries the masses with the frames
(``calib.robot.canonical.carries_masses_alike``): the canonical set must predict what the fitted
set predicts with its masses so carried, and is then polished with the masses where the model puts
them. An answer left mirrored (the mapping refused) is marked "do not enter", naming the axes
(``_left_mirrored``): its offsets are zeros of turned frames, and with masses no sag at that arm is
the robot's.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from calib.measure.dataset import Dataset, DatasetError
from calib.fit.offsets import initial_registrations
from calib.plan.identifiability import exact_tolerance
from calib.robot.canonical import mirrored_links
from calib.robot.kinematics import KINDS, Chain
from calib.robot.model import RobotModel
from calib.fit.multistart import StartOutcome, disagreement, solve_from
from calib.robot.transforms import (apply, euler_zyx_to_matrix, exp_so3, log_so3, matrix_to_euler_zyx,
                                    so3_left_jacobian, so3_left_jacobian_inv)

log = logging.getLogger(__name__)

REG = ("x", "y", "z", "alpha", "beta", "gamma")


@dataclass(frozen=True)
class IdentOptions:
    """``orientation_weight``: L of eq. 19 (mm²); ``rank_tol``: relative residual below which a
    column counts as a combination of the kept ones; ``exclude``: parameter names to keep nominal;
    ``exclude_reasons``: (name, reason) pairs to keep nominal with the reason given (e.g. the CLI
    option that asked for it); ``cond_warn``: scaled condition number above which the fit is called
    ill-conditioned;
    ``n_starts``, ``seed``, ``start_spread``, ``disagree_rel``: the multi-start solve (``identify``)."""

    orientation_weight: float = 100.0
    #: Prior std (degrees per axis) of a 6-DoF target's frame about the model's ``rpy_deg``; 0:
    #: taken as exact. A marker without ``rpy_deg`` has its frame fitted without a prior.
    tool_rotation_prior_deg: float = 2.0
    rank_tol: float = 1e-6
    exclude: tuple[str, ...] = ()
    exclude_reasons: tuple[tuple[str, str], ...] = ()
    fit_markers: bool = True
    compliance: bool = False
    max_nfev: int = 200
    cond_warn: float = 1e4
    initial_registration: str = "least-squares"
    tool_prior_mm: float = 10.0
    #: Starts of the solve (``identify``): 1 = the staged solve from nominal only; 2 adds the plain
    #: one-stage solve from nominal and the ±180° joint-zero flips that pass a screen
    #: (``_flip_screen``); more add random starts (seeded by ``seed``).
    n_starts: int = 6
    seed: int = 0
    #: Spread of the random starts about nominal: lengths (mm) and angles (degrees), per parameter;
    #: marker positions are drawn from their prior (``tool_prior_mm``).
    start_spread: tuple[float, float] = (2.0, 1.0)
    #: Relative cost gap above which two starts' minima count as different (0.01: 1 %; gaps of a
    #: residual rms below ``COST_FLOOR_RMS_MM`` never count).
    disagree_rel: float = 0.01


@dataclass
class IdentResult:
    model: RobotModel
    params: np.ndarray  # full Chain vector (P,)
    std: np.ndarray  # (P,) NaN where not identified
    free_names: list[str]
    excluded: dict[str, str]
    base2sensor: dict[str, np.ndarray]
    rms_mm: float
    condition_number: float
    iterations: int
    warnings: list[str] = field(default_factory=list)
    #: With ``IdentOptions.compliance``: per joint rad/(N·m) (0 where not identified) and std (NaN there).
    #: The sag they give is sign·k·τ(q) with the torques τ at ``params`` (the identified arm), as fitted.
    compliance: np.ndarray | None = None
    compliance_std: np.ndarray | None = None
    #: Prior std (mm per coordinate) of the marker positions; 0: taken as exact.
    tool_prior_mm: float = 0.0
    #: Every start of the solve, best first: label, cost (½·Σ r² over residuals and prior rows,
    #: mm²), rms of the position residuals (mm), evaluations, ``same_minimum`` as the best.
    starts: list[dict] = field(default_factory=list)
    #: Why the identified model must not be used (the guards of ``calib.robot.controller``); [] if none.
    do_not_use: list[str] = field(default_factory=list)
    #: How the solution was mapped onto the nominal model's branch (``calib.robot.canonical``); [] if not.
    canonical: list[str] = field(default_factory=list)
    #: Pose rows: each measured marker's target frame in the flange frame, (3, 3) ``R_flange←target``,
    #: and its std per axis (rad, (3,); NaN where not fitted). Empty without orientation data.
    tool_frames: dict[str, np.ndarray] = field(default_factory=dict)
    tool_frame_std_rad: dict[str, np.ndarray] = field(default_factory=dict)
    #: Attitude rows' weight (mm per rad) and how it was chosen; None without orientation data.
    attitude_weight: dict | None = None

    @property
    def chain_names(self) -> list[str]:
        return Chain(self.model).param_names

    def corrected_model(self) -> RobotModel:
        return corrected_model(self.model, self.params)


def _lookup(values: np.ndarray, names: list[str]) -> np.ndarray:
    """Index of each value in ``names``: (k,) int."""
    table = {n: i for i, n in enumerate(names)}
    return np.fromiter((table[v] for v in values.tolist()), dtype=np.intp, count=len(values))


class _Problem:
    """Residuals and Jacobian of the identification for a fixed set of free columns."""

    def __init__(self, chain: Chain, data: Dataset, b2s0: dict[str, np.ndarray], rotation: np.ndarray | None, weight: float,
                 compliance: bool = False):
        self.chain, self.data = chain, data
        self.sensors = sorted(b2s0)
        self.b2s0 = np.stack([b2s0[s] for s in self.sensors])
        self.sidx = _lookup(data.sensor, self.sensors)
        self.midx = _lookup(data.marker, chain.marker_names)
        self.rows_of = [np.flatnonzero(self.sidx == s) for s in range(len(self.sensors))]
        self.uq, self.inv = np.unique(data.q_rad, axis=0, return_inverse=True)
        self.inv = self.inv.ravel()
        if rotation is None and data.has_orientation:
            rotation = data.rot
        self.rotation = rotation
        self.P = chain.n_params
        self.names = list(chain.param_names) + [f"{s}.{r}" for s in self.sensors for r in REG]
        if rotation is not None:
            self._init_orientation(np.asarray(rotation, dtype=float), weight)
        #: Joint-angle change per µrad/(N·m) of compliance per distinct configuration (u, n) at the
        #: *nominal* arm, or None: only for the columns' scale and the check of which axes gravity
        #: loads. The residuals take the sag at the arm being evaluated (``sag_gain``).
        self.gain = None
        self.comp_start = None
        #: Centres of mass (n+1, 3) mm in place of the model's (``calib.robot.gravity.moved_coms``), or
        #: None: only while ``_canonical`` evaluates a mirrored set with its masses carried along.
        self.coms = None
        if compliance:
            self.gain = self.sag_gain(chain.nominal)
            self.comp_start = len(self.names)
            self.names += [f"{ax}.compliance" for ax in chain.model.axis_names]
        self.n_reg = 6 * len(self.sensors)
        if self.rotation is not None:
            self.frame_start = len(self.names)
            self.names += [f"{m}.frame_{a}" for m in self.frame_markers for a in ("rx", "ry", "rz")]

    def sag_gain(self, params: np.ndarray) -> np.ndarray:
        """sign_i τ_i(q) · 1e-6 (u, n) per distinct configuration: joint-angle change (rad) per
        µrad/(N·m) of compliance, the gravity torques τ (N·m) taken at the arm ``params`` (P,)."""
        from calib.robot.gravity import gravity_torques

        return self.chain.sign * gravity_torques(self.chain, self.uq, params, self.coms) * 1e-6

    def _init_orientation(self, rotation: np.ndarray, weight: float) -> None:
        """Pose rows, their weights and the targets' nominal frames on the flange."""
        data, chain = self.data, self.chain
        ok = np.isfinite(rotation).all(axis=(1, 2))
        self.orows = np.flatnonzero(ok)
        self.r_meas = rotation[self.orows]
        self.frame_markers = sorted(set(data.marker[self.orows].tolist()))
        self.fidx = _lookup(data.marker[self.orows], self.frame_markers)
        sp = float(np.nanmedian(data.std_mm)) if np.isfinite(data.std_mm).any() else math.nan
        att = data.att_std_rad[self.orows] if data.att_std_rad is not None else np.full(self.orows.size, np.nan)
        if math.isfinite(sp) and sp > 0 and np.isfinite(att).any():
            att = np.where(np.isfinite(att) & (att > 0), att, np.nanmedian(att[att > 0]) if (att > 0).any() else np.nan)
            self.att_w = sp / att
            self.weight_info = {"how": "σ_position / σ_attitude of each row (the data's spreads)",
                                "sigma_position_mm": sp, "median_mm_per_rad": float(np.median(self.att_w))}
        else:
            self.att_w = np.full(self.orows.size, math.sqrt(weight))
            self.weight_info = {"how": f"√L with L = {weight:g} mm² (the data state no spreads)",
                                "median_mm_per_rad": math.sqrt(weight)}
        # Nominal target frames: the model's rpy_deg, else the mean of what the data say at nominal.
        frames, known = [], []
        f_rot, _ = chain.flange_pose(data.q_rad[self.orows])
        sensor_r = self.b2s0[self.sidx[self.orows], :3, :3]
        for m in self.frame_markers:
            rpy = chain.model.tool.markers[chain.model.marker_index(m)].rpy_deg
            known.append(rpy is not None)
            if rpy is not None:
                frames.append(euler_zyx_to_matrix(*np.radians([rpy[2], rpy[1], rpy[0]])))
                continue
            rows = self.fidx == self.frame_markers.index(m)
            est = np.einsum("kji,kjl->kil", np.einsum("kij,kjl->kil", sensor_r[rows], f_rot[rows]), self.r_meas[rows]).sum(0)
            u, _, vt = np.linalg.svd(est)  # chordal mean on SO(3)
            frames.append(u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt)
        self.frame0 = np.array(frames).reshape(-1, 3, 3)
        self.frame_known = known

    def target_frames(self, x: np.ndarray) -> np.ndarray:
        """(F, 3, 3) ``R_flange←target`` of each frame marker at the vector x."""
        phi = x[self.frame_start: self.frame_start + 3 * len(self.frame_markers)].reshape(-1, 3)
        return exp_so3(phi) @ self.frame0

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x[: self.P], x[self.P : self.P + 6 * len(self.sensors)].reshape(len(self.sensors), 6)

    def residuals_and_jacobian(self, x: np.ndarray, want_jac: bool = True):
        """Residuals (measured − predicted; positions then weighted rotations) and, if asked,
        their Jacobian with respect to the full vector x = [chain params | registrations].

        Kinematics run once per distinct configuration and marker; each sensor's rows are then
        rotated with one matrix product.
        """
        params, reg = self.split(x)
        k = len(self.data)
        rot = euler_zyx_to_matrix(reg[:, 3], reg[:, 4], reg[:, 5])  # (S,3,3) T* rotations
        need_kin_jac = want_jac or self.gain is not None
        # The sag's torques at the arm being evaluated (its offsets and links), as its lever arms
        # below: at the solution, the fitted arm. Their change with the parameters is left out of
        # the Jacobian (k·∂τ/∂p, ~1e-4 of the columns it would join), so LM's fixed point is the
        # exact model's minimum to that order.
        gain = self.sag_gain(params) if self.gain is not None else None
        if need_kin_jac:
            fj = self.chain.flange_jacobian(self.uq, params)
            f_rot, f_pos = fj.rotation, fj.position  # (u,3,3), (u,3)
        else:
            f_rot, f_pos = self.chain.flange_pose(self.uq, params)
        mk = params[self.chain.marker_slice()].reshape(-1, 3)  # (m,3)
        arm = np.einsum("uij,mj->umi", f_rot, mk)  # (u,m,3)
        p_base = f_pos[self.inv] + arm[self.inv, self.midx]  # (k,3)
        if self.gain is not None:
            # First-order gravity sag: each joint turns by sign·k·τ (calib.robot.gravity), seen through
            # the marker's offset derivative ∂p/∂δ = sign·z × (p − o) = jp + jw × arm.
            n = self.chain.n
            d_off = fj.jp[..., :n][:, None] + np.cross(fj.jw[..., :n][:, None], arm[..., None], axis=2)  # (u,m,3,n)
            sag_cols = d_off[self.inv, self.midx] * gain[self.inv][:, None, :]  # (k,3,n) per µrad/(N·m)
            comp = x[self.comp_start: self.comp_start + n]
            p_base = p_base + np.einsum("kjn,n->kj", sag_cols, comp)
            # The same sag turns the flange and everything on it: ω = Σ_i z_i·sign_i·k_i·τ_i (base
            # frame, the offsets' rotation Jacobian), to the same first order as the positions.
            sag_w = fj.jw[..., :n] * gain[:, None, :]  # (u,3,n) rad per µrad/(N·m)
            f_rot = exp_so3(np.einsum("ujn,n->uj", sag_w, comp)) @ f_rot
        pred = np.empty((k, 3))
        sensor_r = rot @ self.b2s0[:, :3, :3]  # (S,3,3): sensor-from-base rotation, total
        for s, rows in enumerate(self.rows_of):
            rp = (p_base[rows] @ self.b2s0[s, :3, :3].T + self.b2s0[s, :3, 3]) @ rot[s].T
            pred[rows] = rp + reg[s, :3]
        res = [(self.data.xyz_mm - pred).ravel()]
        if self.rotation is not None:
            o = self.orows
            frames = self.target_frames(x)
            r_pred = sensor_r[self.sidx[o]] @ f_rot[self.inv[o]] @ frames[self.fidx]  # (ko,3,3)
            e = log_so3(self.r_meas @ np.swapaxes(r_pred, 1, 2))  # (ko,3) rad, sensor frame
            res.append((self.att_w[:, None] * e).ravel())
        r = np.concatenate(res)
        if not want_jac:
            return r, None
        n_reg = 6 * len(self.sensors)
        n_cols = len(self.names)
        # d(p_base)/d(chain params) per distinct configuration and marker: (u,m,3,P).
        jw = fj.jw[:, None]  # (u,1,3,P)
        a = arm[..., None]  # (u,m,3,1)
        cross = np.stack(
            [jw[:, :, 1] * a[:, :, 2] - jw[:, :, 2] * a[:, :, 1],
             jw[:, :, 2] * a[:, :, 0] - jw[:, :, 0] * a[:, :, 2],
             jw[:, :, 0] * a[:, :, 1] - jw[:, :, 1] * a[:, :, 0]],
            axis=2,
        )
        jk = fj.jp[:, None] + cross
        ms = self.chain.marker_slice()
        for mi in range(self.chain.m):
            jk[:, mi, :, ms.start + 3 * mi : ms.start + 3 * mi + 3] = f_rot
        jp = np.zeros((k, 3, n_cols))
        axes = self._reg_axes(reg)
        for s, rows in enumerate(self.rows_of):
            jrows = jk[self.inv[rows], self.midx[rows]]  # (ks,3,P)
            jp[rows, :, : self.P] = np.einsum("ij,kjp->kip", sensor_r[s], jrows)
            if self.gain is not None:
                jp[rows, :, self.comp_start: self.comp_start + self.chain.n] = np.einsum("ij,kjn->kin", sensor_r[s], sag_cols[rows])
            c = self.P + 6 * s
            jp[rows, :, c : c + 3] = np.eye(3)
            rp = pred[rows] - reg[s, :3]
            for ax in range(3):
                jp[rows, :, c + 3 + ax] = np.cross(axes[ax][s], rp)
        blocks = [-jp.reshape(3 * k, -1)]
        if self.rotation is not None:
            # R_pred → exp(ω·dξ) R_pred (ω in the sensor frame) moves e by −J_l(−e)⁻¹ ω dξ.
            ko = o.size
            w = np.zeros((ko, 3, n_cols))
            so = sensor_r[self.sidx[o]]
            w[:, :, : self.P] = np.einsum("kij,kjp->kip", so, fj.jw[self.inv[o]])
            if self.gain is not None:
                w[:, :, self.comp_start: self.comp_start + self.chain.n] = np.einsum("kij,kjn->kin", so, sag_w[self.inv[o]])
            sid = self.sidx[o]
            for ax in range(3):
                for s in range(len(self.sensors)):
                    w[sid == s, :, self.P + 6 * s + 3 + ax] = axes[ax][s]
            phi = x[self.frame_start: self.frame_start + 3 * len(self.frame_markers)].reshape(-1, 3)
            side = np.einsum("kij,kjl->kil", so @ f_rot[self.inv[o]], so3_left_jacobian(phi)[self.fidx])  # (ko,3,3)
            for f in range(len(self.frame_markers)):
                rows = self.fidx == f
                w[rows, :, self.frame_start + 3 * f: self.frame_start + 3 * f + 3] = side[rows]
            jr = -np.einsum("kij,kjp->kip", so3_left_jacobian_inv(-e), w) * self.att_w[:, None, None]
            blocks.append(jr.reshape(3 * ko, -1))
        return r, np.concatenate(blocks)

    @staticmethod
    def _reg_axes(reg: np.ndarray) -> list[np.ndarray]:
        """Rotation axes of the ZYX correction's three angles, in the sensor frame: (S,3) each."""
        ca, sa = np.cos(reg[:, 3]), np.sin(reg[:, 3])
        cb, sb = np.cos(reg[:, 4]), np.sin(reg[:, 4])
        return [
            np.broadcast_to([0.0, 0.0, 1.0], (reg.shape[0], 3)),
            np.stack([-sa, ca, np.zeros_like(ca)], -1),
            np.stack([ca * cb, sa * cb, -sb], -1),
        ]

    def scale(self, lever: float) -> np.ndarray:
        out = []
        for name in self.names:
            kind = name.rsplit(".", 1)[1]
            out.append(1.0 if kind in ("d", "a", "x", "y", "z") else lever)
        if self.gain is not None:  # compliances: mm of marker motion per µrad/(N·m)
            out[self.comp_start: self.comp_start + self.chain.n] = list(lever * np.maximum(np.sqrt(np.mean(self.gain ** 2, axis=0)), 1e-12))
        return np.array(out)


def _excluded_by_choice(model: RobotModel, chain: Chain, names: list[str], options: IdentOptions) -> dict[str, str]:
    """Parameters left out before looking at the data: by the options, or by the convention."""
    excluded: dict[str, str] = {n: "excluded by the options" for n in options.exclude}
    excluded.update(dict(options.exclude_reasons))
    if model.convention == "dh":
        for i in chain.index("beta"):
            excluded[names[i]] = "β is not a parameter of the standard DH convention (use mdh for near-parallel axes)"
    if not options.fit_markers:
        for i in range(chain.marker_slice().start, chain.marker_slice().stop):
            excluded[names[i]] = "marker offsets fixed by the options"
    elif options.tool_prior_mm == 0:
        for i in range(chain.marker_slice().start, chain.marker_slice().stop):
            excluded[names[i]] = "marker positions taken as exact (tool prior 0 mm)"
    if options.tool_rotation_prior_deg == 0:
        for name in names:
            marker, _, kind = name.rpartition(".")
            if kind.startswith("frame_") and model.tool.markers[model.marker_index(marker)].rpy_deg is not None:
                excluded[name] = "the target's frame on the flange taken as exact (the model's rpy_deg, rotation prior 0°)"
    return excluded


def _preference(problem: _Problem, chain: Chain) -> list[int]:
    """Column order in which parameters are kept: registration, marker positions, offsets, then the
    link parameters — so what the tool explains is taken by the tool, never by the last link."""
    order = list(range(problem.P, problem.P + 6 * len(problem.sensors)))  # registration first
    order += list(range(chain.marker_slice().start, chain.marker_slice().stop))
    frames = _frame_columns(problem)
    order += frames
    for kind in KINDS:
        order += list(chain.index(kind))
    order += [c for c in range(problem.P + 6 * len(problem.sensors), len(problem.names)) if c not in frames]  # compliances
    return order


def _frame_columns(problem: _Problem) -> list[int]:
    """Columns of the 6-DoF targets' frames on the flange ([] without orientation data)."""
    if problem.rotation is None:
        return []
    return list(range(problem.frame_start, problem.frame_start + 3 * len(problem.frame_markers)))


def select_identifiable(jac: np.ndarray, names: list[str], scale: np.ndarray, order: list[int], excluded: dict[str, str], rank_tol: float) -> list[int]:
    """Greedy rank-revealing selection (modified Gram–Schmidt in preference order).

    Works on the R factor of the scaled Jacobian: an orthogonal transform keeps every column
    norm and every linear relation between columns, and R is only P×P.
    """
    j = np.linalg.qr(jac / scale, mode="r")
    kept: list[int] = []
    basis: list[np.ndarray] = []
    biggest = float(np.linalg.norm(j, axis=0).max())
    for c in order:
        if names[c] in excluded:
            continue
        v = j[:, c].copy()
        norm = np.linalg.norm(v)
        if norm <= rank_tol * biggest:
            excluded[names[c]] = "does not move any measured marker in these configurations"
            continue
        for b in basis:
            v -= (b @ v) * b
        residual = np.linalg.norm(v) / norm
        if residual < rank_tol:
            coef, *_ = np.linalg.lstsq(j[:, kept], j[:, c], rcond=None)
            top = np.argsort(-np.abs(coef))[:3]
            combo = " ".join(f"{coef[t]:+.3g}·{names[kept[t]]}" for t in top if abs(coef[t]) > 1e-9)
            # "exactly" only at rounding level (calib.plan.identifiability.exact_tolerance), else say how close.
            if residual <= exact_tolerance(1.0, jac.shape):
                excluded[names[c]] = f"not identifiable: moves the markers exactly like {combo} (kept nominal)"
            else:
                excluded[names[c]] = (f"not identifiable from these configurations: moves the markers like {combo} "
                                      f"to within {residual:.1g} of its effect (a near-degeneracy above rounding level; kept nominal)")
            continue
        basis.append(v / np.linalg.norm(v))
        kept.append(c)
    return sorted(kept)


def identify(
    model: RobotModel,
    data: Dataset,
    options: IdentOptions = IdentOptions(),
    *,
    rotation: np.ndarray | None = None,
    registration: dict[str, np.ndarray] | None = None,
) -> IdentResult:
    """Identify all identifiable parameters from ``data`` (and measured flange rotations
    ``rotation`` (k, 3, 3) in the sensor frame, if any)."""
    if data.n_joints != model.n_joints:
        raise DatasetError(f"the dataset has {data.n_joints} joints, the model '{model.name}' has {model.n_joints}")
    chain = Chain(model)
    dropped = []
    b2s0 = registration or initial_registrations(chain, data, options.initial_registration, 0)
    if options.compliance and not model.has_dynamics:
        raise ValueError(f"{model.name}: the compliance model needs link masses and centres of mass in the robot model")
    problem = _Problem(chain, data, b2s0, rotation, options.orientation_weight, compliance=options.compliance)
    x0 = np.zeros(len(problem.names))
    x0[: problem.P] = chain.nominal
    excluded = _excluded_by_choice(model, chain, problem.names, options)
    if options.compliance:  # as the fast fit: an axis gravity hardly loads cannot show its sag
        rms = np.sqrt(np.mean(problem.gain ** 2, axis=0)) * 1e6
        for i in np.flatnonzero(rms < 0.05 * rms.max()):
            excluded[f"{model.axis_names[i]}.compliance"] = (
                f"gravity turns this axis by only {rms[i] if rms[i] > 1e-9 * rms.max() else 0.0:.1g} N·m (rms) in these "
                "configurations: its sag cannot be seen")
    p_base = chain.marker_positions(data.q_rad)
    lever = float(np.sqrt(np.mean(np.sum(p_base**2, axis=-1))))
    _, j0 = problem.residuals_and_jacobian(x0)
    scale = problem.scale(lever)
    free = select_identifiable(j0, problem.names, scale, _preference(problem, chain), excluded, options.rank_tol)
    n_att = 3 * problem.orows.size if problem.rotation is not None else 0
    if 3 * len(data) + n_att < 2 * len(free):
        raise DatasetError(
            f"{len(data)} measurements give {3 * len(data) + n_att} coordinates for {len(free)} identifiable parameters; "
            f"measure at least {math.ceil(2 * len(free) / (6 if n_att else 3))}"
        )

    def fun(z):
        x = x0.copy()
        x[free] = x0[free] + z / scale[free]
        return problem.residuals_and_jacobian(x, want_jac=False)[0]

    def jac(z):
        x = x0.copy()
        x[free] = x0[free] + z / scale[free]
        return problem.residuals_and_jacobian(x)[1][:, free] / scale[free]

    if not (math.isfinite(options.tool_prior_mm) and 0 <= options.tool_prior_mm <= 100):
        raise ValueError(f"tool_prior_mm must lie in 0…100 mm (0: exact markers), given {options.tool_prior_mm}")
    if options.n_starts < 1:
        raise ValueError(f"n_starts must be at least 1 (the staged solve from nominal), given {options.n_starts}")
    ms = chain.marker_slice()
    # Prior rows (σ/sd)·z: marker positions about the model's (sd tool_prior_mm) and known target
    # frames about the model's rpy_deg (sd tool_rotation_prior_deg × lever, in the scaled units of z).
    frame_cols = set(_frame_columns(problem))
    known = {problem.frame_start + 3 * f + a for f, k in enumerate(getattr(problem, "frame_known", [])) if k for a in range(3)}
    tool_pos = np.array([k for k, c in enumerate(free) if ms.start <= c < ms.stop or (c in frame_cols and c in known)], dtype=int)
    prior_sd = np.array([options.tool_prior_mm if free[k] < problem.P else
                         math.radians(options.tool_rotation_prior_deg) * scale[free[k]] for k in tool_pos])
    prior_weight = [0.0]  # σ, set after a first solve without the prior

    def fun_p(z):
        return np.concatenate([fun(z), prior_weight[0] * z[tool_pos] / prior_sd])

    def jac_p(z):
        prior = np.zeros((tool_pos.size, len(free)))
        prior[np.arange(tool_pos.size), tool_pos] = prior_weight[0] / prior_sd
        return np.concatenate([jac(z), prior])

    starts, sol = _solve_starts(problem, free, scale, options, fun_p, jac_p, tool_pos, prior_weight, len(data))
    nfev = sum(o.nfev for o in starts)
    warnings = dropped + _start_warnings(starts, options, 3 * len(data))
    for w in warnings:
        log.warning(w)
    x = x0.copy()
    x[free] = x0[free] + sol.z / scale[free]
    x, sol, canonical = _canonical(chain, problem, data, x, x0, free, scale, sol, fun_p, jac_p, options, tool_pos.size)
    mirrored = _left_mirrored(chain, x[: problem.P], options.compliance)
    r = sol.fun[: sol.fun.size - tool_pos.size]
    n_pos = 3 * len(data)
    rms = float(np.sqrt(np.mean(r[:n_pos] ** 2)))
    dof = max(r.size - len(free), 1)
    s2 = float(r @ r) / dof
    js = sol.jac
    sv = np.linalg.svd(js, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    cov = np.linalg.pinv(js.T @ js) * s2
    std = np.full(len(problem.names), np.nan)
    std[free] = np.sqrt(np.diag(cov)) / scale[free]
    if cond > options.cond_warn:
        warnings.append(
            f"ill-conditioned: scaled condition number {cond:.3g} > {options.cond_warn:g}; the weakest directions are "
            "poorly determined — measure more varied configurations (see `acquire select`)"
        )
        log.warning(warnings[-1])
    params, reg = problem.split(x)
    warnings += _prior_conflicts(chain, params, options)
    do_not_use = mirrored + _implausible(problem, data, r[:n_pos].reshape(-1, 3))
    worse = {id(o) for o in disagreement(starts, options.disagree_rel, _cost_floor(starts))}
    comp = comp_std = None
    if options.compliance:
        cs = slice(problem.comp_start, problem.comp_start + chain.n)
        comp, comp_std = x[cs] * 1e-6, std[cs] * 1e-6
    tool_frames, frame_std = {}, {}
    if problem.rotation is not None:
        for f, (m, t) in enumerate(zip(problem.frame_markers, problem.target_frames(x))):
            tool_frames[m] = t
            cols = range(problem.frame_start + 3 * f, problem.frame_start + 3 * f + 3)
            frame_std[m] = np.array([std[c] for c in cols])
    rot = euler_zyx_to_matrix(reg[:, 3], reg[:, 4], reg[:, 5])
    b2s = {}
    for k, s in enumerate(problem.sensors):
        t = np.eye(4)
        t[:3, :3] = rot[k]
        t[:3, 3] = reg[k, :3]
        b2s[s] = t @ problem.b2s0[k]
    return IdentResult(
        model=model,
        params=params,
        std=std[: problem.P],
        free_names=[problem.names[i] for i in free],
        excluded=excluded,
        base2sensor=b2s,
        rms_mm=rms,
        condition_number=cond,
        iterations=nfev,
        warnings=warnings,
        compliance=comp,
        compliance_std=comp_std,
        tool_prior_mm=float(options.tool_prior_mm) if options.fit_markers else 0.0,
        starts=[{"label": o.label, "cost": o.cost, "rms_mm": _rms(o.fun[:n_pos]), "evaluations": o.nfev,
                 "same_minimum": id(o) not in worse} for o in starts],
        do_not_use=do_not_use,
        canonical=canonical,
        tool_frames=tool_frames,
        tool_frame_std_rad=frame_std,
        attitude_weight=problem.weight_info if problem.rotation is not None else None,
    )


def _canonical(chain, problem, data, x, x0, free, scale, sol, fun_p, jac_p, options, n_prior):
    """The best solution on the nominal model's branch (``calib.robot.canonical``): offsets wrapped to
    (−180°, 180°], mirrored links mapped back with the same forward kinematics. The mapped point
    must give the same residuals (else, e.g. measured orientations that see a turned flange, only
    the wrapping is kept). With the compliance model the fitted set's sag had the model's masses
    turned with its frames: the mapped set must carry them alike (the same gravity torques with the
    masses moved with the frames, ``calib.robot.canonical.carries_masses_alike``) and give the
    residuals the fitted set gives with its masses so carried; else only the wrapping. A mirror
    moves markers toward their prior (and with masses puts them where the model says), so the
    mapped point is polished (a few LM steps; the same minimum, with masses the one of the masses
    where the model puts them) and its Jacobian gives the stds. ``n_prior``: the
    prior rows at the end of the residuals. Returns (x, outcome, lines saying what was mapped)."""
    from calib.robot.canonical import FK_TOLERANCE_MM, canonical_params, carries_masses_alike, wrapped_only
    from calib.robot.gravity import moved_coms

    names = {problem.names[c] for c in free}
    measured = sorted(set(data.marker.tolist()))
    original = x[: problem.P].copy()
    mapping = canonical_params(chain, original, names, problem.uq, measured)
    x = x.copy()
    x[: problem.P] = mapping.params
    if not mapping.changes:
        return x, sol, []
    z = (x[free] - x0[free]) * scale[free]
    n_res = sol.fun.size - n_prior
    before = sol.fun[:n_res]
    masses = ""
    if problem.gain is not None:
        if not carries_masses_alike(chain, problem.uq, original, mapping.params):
            x[: problem.P] = wrapped_only(chain, original)
            log.info("mirror not mapped back: its frames do not carry the link masses as the canonical set's do")
            return x, sol, []
        problem.coms = moved_coms(chain, original, mapping.params, problem.uq[0])
        try:
            before = fun_p(sol.z)[:n_res]  # the fitted set, its masses carried with its turned frames
        finally:
            problem.coms = None
        masses = "; the link masses carried with the turned frames"
    if np.abs(fun_p(z)[:n_res] - before).max() > FK_TOLERANCE_MM * math.sqrt(max(options.orientation_weight, 1.0)):
        x[: problem.P] = wrapped_only(chain, original)
        return x, sol, []
    polished = solve_from(sol.label, fun_p, jac_p, z, [None], options.max_nfev)
    polished.nfev += sol.nfev
    x[free] = x0[free] + polished.z / scale[free]
    x[: problem.P] = wrapped_only(chain, x[: problem.P])
    lines = [f"reported on the nominal model's branch (same forward kinematics, largest change of a measured "
             f"marker {mapping.fk_change_mm:.1g} mm{masses}): " + "; ".join(mapping.changes)]
    log.info(lines[0])
    return x, polished, lines


def _left_mirrored(chain: Chain, params: np.ndarray, compliance: bool) -> list[str]:
    """"do not enter" (one line) when the answer ``params`` (P,) is still a mirrored parameter set
    (``calib.robot.canonical.mirrored_links``): the mapping back was refused, so its offsets are
    zeros of turned frames — entered into a controller that keeps the nominal links they would be
    off by up to a half turn. With the compliance model the masses also sat turned with the frames,
    so no sag at that arm is the robot's. [] on the nominal model's branch."""
    turned = mirrored_links(chain, params)
    if not turned:
        return []
    msg = ("do not enter: the solution is a mirrored parameter set that could not be mapped back to the nominal "
           f"model's branch ({'; '.join(turned)}); its offsets are zeros of turned frames, not of the controller's ")
    if compliance:
        msg += ("model, and the link masses' centres are given in the nominal model's frames, so the gravity torques "
                "and the compliances are not this robot's either — check the model's joint zeros and conventions, "
                "fit more of the axes' parameters, or fit without --compliance")
    else:
        msg += "model — check the model's joint zeros and conventions, or fit more of the axes' parameters"
    log.warning(msg)
    return [msg]


def _ratio(cost: float, best: float) -> str:
    """How much higher a cost is than the best: '+35 %' or '×2.1e+04'."""
    ratio = cost / max(best, 1e-300)
    return f"+{ratio - 1:.0%}" if ratio < 10 else f"×{ratio:.2g}"


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r ** 2)))


def _stage_columns(problem: _Problem, free: list[int]) -> np.ndarray:
    """Positions in ``free`` of the first stage: registration, marker positions, joint offsets."""
    first = [k for k, c in enumerate(free) if c < problem.P and problem.names[c].rsplit(".", 1)[1] in ("offset", "x", "y", "z")]
    first += [k for k, c in enumerate(free) if problem.P <= c < problem.P + problem.n_reg or c in _frame_columns(problem)]
    return np.array(sorted(first), dtype=int)


def _random_start(problem: _Problem, free: list[int], scale: np.ndarray, options: IdentOptions,
                  rng: np.random.Generator) -> np.ndarray:
    """A start about nominal in the scaled units of the solve: lengths N(0, spread mm), angles
    N(0, spread°) (times their lever arm), markers from their prior; compliances at 0."""
    mm, deg = options.start_spread
    z = np.zeros(len(free))
    for k, c in enumerate(free):
        if c >= problem.P + problem.n_reg:
            continue
        kind = problem.names[c].rsplit(".", 1)[1]
        is_marker = c < problem.P and kind in ("x", "y", "z")
        if is_marker:
            z[k] = rng.normal(0.0, options.tool_prior_mm)
        elif kind in ("d", "a", "x", "y", "z"):
            z[k] = rng.normal(0.0, mm)
        else:
            z[k] = rng.normal(0.0, math.radians(deg)) * scale[c]
    return z


def _solve_starts(problem, free, scale, options, fun_p, jac_p, tool_pos, prior_weight, n_rows):
    """Every start on one objective: the staged solve from nominal (registration, marker positions
    and joint offsets first, then everything), the plain one-stage solve from nominal, then random
    staged starts. With fitted markers, a staged solve without the tool prior first gives σ, and
    so the prior rows' weight σ/sd. Returns (outcomes best first, the best)."""
    first = _stage_columns(problem, free)
    staged = [first, None] if 0 < first.size < len(free) else [None]
    z0 = np.zeros(len(free))
    pre_nfev = 0
    screened, flips = _flip_screen(problem, free, scale, options, fun_p, jac_p, first if len(staged) == 2 else None)
    if tool_pos.size:
        label, lowest = min(screened, key=lambda t: t[1].cost)
        pre = solve_from(f"without the tool prior ({label})", fun_p, jac_p, lowest.z, [None], options.max_nfev)
        prior_weight[0] = max(_rms(pre.fun[: 3 * n_rows]), 1e-9)
        pre_nfev = pre.nfev + sum(o.nfev for _, o in screened)
    outcomes = [solve_from("staged from nominal", fun_p, jac_p, z0, staged, options.max_nfev)]
    outcomes[0].nfev += pre_nfev
    if options.n_starts >= 2:
        outcomes.append(solve_from("plain from nominal", fun_p, jac_p, z0, [None], options.max_nfev))
    for label, o in flips:  # continued with the tool prior from the first stage of the screen
        outcomes.append(solve_from(label, fun_p, jac_p, o.z, [None], options.max_nfev))
        outcomes[-1].nfev += o.nfev
    rng = np.random.default_rng(options.seed)
    for i in range(2, options.n_starts):
        z = _random_start(problem, free, scale, options, rng)
        outcomes.append(solve_from(f"random start {i - 1}", fun_p, jac_p, z, staged, options.max_nfev))
    outcomes.sort(key=lambda o: o.cost)
    return outcomes, outcomes[0]


#: At most this many ±180° zero flips are continued past the screen (the ones whose first stage
#: ends lowest); a model with more than this many zeros off by 180° is not what this is for.
MAX_FLIP_STARTS = 2
#: The flips are screened only when nominal's first stage (registration, markers, offsets) leaves
#: more than this rms (mm per coordinate): with a right model it leaves the link errors (tenths of
#: a mm, about 1 mm on a poor arm); a zero half a turn off moves the markers by twice their
#: distance from that axis (tens to hundreds of mm), which the first stage cannot absorb. Below
#: it the screen would cost n small solves (half a normal fit's time) for nothing.
FLIP_SCREEN_RMS_MM = 2.0
#: Evaluations of a flip's first stage in the screen: a right flip converges in a few (5–15 seen
#: on the tracker cell), a wrong one needs a hundred and more to reach a poor minimum anyway.
SCREEN_NFEV = 30


def _registered_start(problem: _Problem, free: list[int], scale: np.ndarray, change: dict[int, float]) -> np.ndarray:
    """A start (scaled, like z) with the chain parameters ``change`` (column → change, rad or mm)
    applied to nominal and each free registration least-squares registered for that model (a
    joint turned by 180° turns the whole arm: the nominal model's registration is far off)."""
    from calib.fit.registration import register_least_squares

    z = np.zeros(len(free))
    pos = {c: k for k, c in enumerate(free)}
    params = problem.chain.nominal.copy()
    for c, v in change.items():
        params[c] += v
        z[pos[c]] = v * scale[c]
    pred = _marker_rows(problem.chain, problem.data, params)
    for s, rows in enumerate(problem.rows_of):
        cols = [problem.P + 6 * s + r for r in range(6)]
        if not all(c in pos for c in cols):
            continue
        try:
            t = register_least_squares(pred[rows], problem.data.xyz_mm[rows]).base2sensor
        except ValueError:
            continue
        rel = t @ np.linalg.inv(problem.b2s0[s])
        values = np.concatenate([rel[:3, 3], matrix_to_euler_zyx(rel[:3, :3])])
        for c, v in zip(cols, values):
            z[pos[c]] = v * scale[c]
    return z


def _flip_screen(problem, free, scale, options, fun_p, jac_p, first):
    """Screen the ±180° flips of the fitted joint zeros (a nominal model with a zero off by 180°,
    a convention slip, leaves Levenberg–Marquardt from nominal in a mirrored or worse minimum).

    A flip is worth a full solve only when the data prefer it at first order: each flip (one
    joint at a time) and nominal get the cheap first stage (registration, markers and offsets,
    nearly linear); flips whose first stage ends materially lower (``disagree_rel``) than
    nominal's are kept, best first, at most ``MAX_FLIP_STARTS``. The screen runs only when
    nominal's first stage leaves more than ``FLIP_SCREEN_RMS_MM``: on a right nominal model it
    costs nothing. Run without the tool prior (it is not set yet).

    Returns (every screened start as (label, outcome), the kept flips as (label, outcome))."""
    z0 = np.zeros(len(free))
    cols = first if first is not None else None
    screened = [("nominal", solve_from("first stage from nominal", fun_p, jac_p, z0, [cols], options.max_nfev))]
    if options.n_starts < 2 or _rms(screened[0][1].fun[: 3 * len(problem.data)]) <= FLIP_SCREEN_RMS_MM:
        return screened, []  # n_starts 1: the staged solve only; a first stage this close needs no flip
    for k, c in enumerate(free):
        name = problem.names[c]
        if c >= problem.P or not name.endswith(".offset"):
            continue
        z = _registered_start(problem, free, scale, {c: math.pi})
        label = f"{name.split('.')[0]} zero +180°"
        screened.append((label, solve_from(f"first stage from {label}", fun_p, jac_p, z, [cols], SCREEN_NFEV)))
    c0 = screened[0][1].cost
    better = sorted((t for t in screened[1:] if c0 - t[1].cost > options.disagree_rel * c0), key=lambda t: t[1].cost)
    return screened, [(f"staged from {label}", o) for label, o in better[:MAX_FLIP_STARTS]]


#: Residual rms (mm) below which two minima's costs count as equal whatever their ratio.
COST_FLOOR_RMS_MM = 1e-4


def _cost_floor(starts: list[StartOutcome]) -> float:
    """The cost ½·n·(COST_FLOOR_RMS_MM)² of the residual vector's length n (mm²)."""
    return 0.5 * starts[0].fun.size * COST_FLOOR_RMS_MM ** 2


#: A fitted marker coordinate this many prior stds from the model's value conflicts with the prior.
PRIOR_CONFLICT_SD = 4.0


def _implausible(problem: _Problem, data: Dataset, res: np.ndarray) -> list[str]:
    """The fast fit's σ guard, per sensor: a residual rms above ``MIN_SIGMA_GUARD_MM`` and more than
    ``MAX_SIGMA_OVER_NOISE`` × the sensor noise seen in the samples' spread (where the data carry
    it) means the identified model does not describe the data. res: (k, 3) mm."""
    from calib.robot.controller import MAX_SIGMA_OVER_NOISE, MIN_SIGMA_GUARD_MM
    from calib.fit.offsets import error_budget

    out = []
    for s, rows in zip(problem.sensors, problem.rows_of):
        rms = float(np.sqrt(np.mean(res[rows] ** 2)))
        # spreads estimated from residuals (calib.fit.noise) grow with the misfit: the absolute floor alone judges
        noise = 0.0 if data.spreads_estimated else error_budget(data, {s: (rms, 0.0)})[s]["noise_mm"] or 0.0
        if rms > max(MAX_SIGMA_OVER_NOISE * noise, MIN_SIGMA_GUARD_MM):
            seen = f", {rms / noise:.0f}× the sensor noise ({noise:.3g} mm)" if noise else ""
            out.append(f"sensor {s}: the identified model leaves an rms residual of {rms:.3g} mm per coordinate{seen}: "
                       "it does not describe the data — a minimum far from this robot (check the model's joint zeros and "
                       "conventions, try more --starts), or a wrong robot model, tool or units")
            log.warning(out[-1])
    return out


def _prior_conflicts(chain: Chain, params: np.ndarray, options: IdentOptions) -> list[str]:
    """Markers fitted far outside their prior: the tool is not where the model says, or the solve
    traded the tool against a joint turned far from its zero (another minimum)."""
    if not options.fit_markers or options.tool_prior_mm == 0:
        return []
    ms = chain.marker_slice()
    shift = np.linalg.norm((params[ms] - chain.nominal[ms]).reshape(-1, 3), axis=1)
    far = [f"{m} {d:.3g} mm" for m, d in zip(chain.marker_names, shift) if d > PRIOR_CONFLICT_SD * options.tool_prior_mm]
    if not far:
        return []
    msg = (f"markers fitted far outside their prior (±{options.tool_prior_mm:g} mm per coordinate) from the model's "
           f"positions: {', '.join(far)} — either the tool is not where the model says (fix the model's tool, or give a "
           "wider --tool-prior-mm) or the solve traded the tool against a joint turned far from its zero (another "
           "minimum: check the model's joint zeros and conventions, try more --starts)")
    log.warning(msg)
    return [msg]


def _start_warnings(starts: list[StartOutcome], options: IdentOptions, n_pos: int) -> list[str]:
    """Say when the starts ended in minima of materially different cost, naming the gap."""
    worse = disagreement(starts, options.disagree_rel, _cost_floor(starts))
    if not worse:
        return []
    best = starts[0]
    gaps = ", ".join(f"{o.label}: rms {_rms(o.fun[:n_pos]):.4g} mm (cost {_ratio(o.cost, best.cost)})" for o in worse)
    out = [f"the starts disagree: {len(worse)} of {len(starts)} ended in a worse minimum than the best "
           f"({best.label}: rms {_rms(best.fun[:n_pos]):.4g} mm) — {gaps}; the best is kept"]
    staged = next(o for o in starts if o.label == "staged from nominal")
    if any(o is staged for o in worse):
        out[0] += (f"; the staged solve from nominal stopped at rms {_rms(staged.fun[:n_pos]):.4g} mm: the nominal model "
                   "is far from this robot or the data leave it several minima — check the model (units, conventions, "
                   "tool), measure more varied configurations, and try more starts (--starts N)")
    return out


def corrected_model(model: RobotModel, params: np.ndarray) -> RobotModel:
    """A robot model with identified parameters written in (mm, degrees, controller convention).

    The zero-offset δ folds into the DH angle offset: theta' = theta + sign·δ.
    """
    chain = Chain(model)
    n = model.n_joints
    d = model.model_dump()
    for i, j in enumerate(d["joints"]):
        j["theta"] = float(j["theta"] + model.joints[i].sign * math.degrees(params[i]))
        j["d"] = float(params[n + i])
        j["a"] = float(params[2 * n + i])
        j["alpha"] = float(math.degrees(params[3 * n + i]))
        j["beta"] = float(math.degrees(params[4 * n + i]))
    mk = params[chain.marker_slice()].reshape(-1, 3)
    for i, m in enumerate(d["tool"]["markers"]):
        m["xyz"] = tuple(float(v) for v in mk[i])
    d["name"] = f"{model.name} (identified)"
    d["source"] = f"identified by remaster from nominal: {model.source}".strip()
    return RobotModel.model_validate(d)


def write_model_yaml(model: RobotModel, path: str | Path) -> None:
    """Write a model in the YAML format ``calib.robot.model.load_robot_model`` reads."""
    d = model.model_dump(mode="json")

    def clean(o):
        if isinstance(o, float):
            return round(o, 9)
        if isinstance(o, (list, tuple)):
            return [clean(v) for v in o]
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        return o

    Path(path).write_text(
        "# Written by remaster (mm, degrees, controller convention).\n" + yaml.safe_dump(clean(d), sort_keys=False),
        encoding="utf-8",
    )


def information_blocks(model: RobotModel, q_rad: np.ndarray, options: IdentOptions = IdentOptions(), *,
                       attitude_mm_per_rad: float | None = None) -> tuple[np.ndarray, list[str], dict[str, str]]:
    """Per-configuration information blocks for observability and pose selection.

    q_rad: (N, n) candidate configurations. Every marker of the tool is assumed measured by one
    sensor whose registration is free. With ``attitude_mm_per_rad`` (σ_position / σ_attitude of
    the sensor, mm/rad) the first marker is a 6-DoF target: its orientation rows join (weighted
    so, like the fit; its frame on the flange free), so the selection sees what orientation adds.
    Returns blocks (N, L, L) of the scaled identification Jacobian over the L parameters
    identifiable from all candidates together, their names, and the excluded parameters with
    reasons.
    """
    from calib.measure.dataset import from_arrays

    chain = Chain(model)
    q = np.asarray(q_rad, dtype=float)
    n_cfg = q.shape[0]
    m = chain.m
    qq = np.repeat(q, m, axis=0)
    markers = np.tile(np.array(chain.marker_names), n_cfg)
    pos = chain.marker_positions(q).reshape(-1, 3)
    rot = None
    if attitude_mm_per_rad is not None:
        rot = np.full((n_cfg * m, 3, 3), np.nan)
        rot[::m] = chain.flange_pose(q)[0]
    data = from_arrays(qq, pos, marker=markers, rot=rot, std_mm=1.0,
                       att_std_rad=None if attitude_mm_per_rad is None else 1.0 / attitude_mm_per_rad)
    problem = _Problem(chain, data, {"sensor": np.eye(4)}, None, options.orientation_weight)
    x0 = np.zeros(len(problem.names))
    x0[: problem.P] = chain.nominal
    excluded = _excluded_by_choice(model, chain, problem.names, options)
    _, j = problem.residuals_and_jacobian(x0)
    lever = float(np.sqrt(np.mean(np.sum(pos**2, axis=-1))))
    scale = problem.scale(lever)
    free = select_identifiable(j, problem.names, scale, _preference(problem, chain), excluded, options.rank_tol)
    js = j[:, free] / scale[free]
    blocks = js[: 3 * n_cfg * m].reshape(n_cfg, 3 * m, len(free))
    if rot is not None:  # attitude rows follow the position rows, one 3-row block per configuration
        blocks = np.concatenate([blocks, js[3 * n_cfg * m:].reshape(n_cfg, 3, len(free))], axis=1)
    return np.einsum("nri,nrj->nij", blocks, blocks), [problem.names[i] for i in free], excluded


def pose_errors(model: RobotModel, params: np.ndarray, data: Dataset, base2sensor: dict[str, np.ndarray]) -> np.ndarray:
    """Position error per row |measured − predicted| (mm) with the given parameters and registration."""
    chain = Chain(model)
    pos = chain.marker_positions(data.q_rad, params)
    idx = np.array([chain.marker_names.index(mk) for mk in data.marker])
    p = pos[np.arange(len(data)), idx]
    t = np.stack([base2sensor[s] for s in data.sensor])
    pred = np.einsum("kij,kj->ki", t[:, :3, :3], p) + t[:, :3, 3]
    return np.linalg.norm(data.xyz_mm - pred, axis=1)


def comprehensive_errors(position_err_mm: np.ndarray, attitude_err_rad: np.ndarray | None = None) -> dict[str, float | None]:
    """The seed's EACPE / EMCPE (mean / max of √(Δx²+Δy²+Δz²), mm) and EACAE / EMCAE (mean / max of
    √(Δφx²+Δφy²+Δφz²), the attitude error's rotation angle; given in rad, reported in **degrees**
    as every file of the project; None when orientation was not measured)."""
    p = np.asarray(position_err_mm, dtype=float)
    out: dict[str, float | None] = {"EACPE": float(p.mean()), "EMCPE": float(p.max())}
    if attitude_err_rad is None or np.asarray(attitude_err_rad).size == 0:
        out.update(EACAE=None, EMCAE=None)
    else:
        a = np.degrees(np.asarray(attitude_err_rad, dtype=float))
        out.update(EACAE=float(a.mean()), EMCAE=float(a.max()))
    return out


def attitude_errors(model: RobotModel, params: np.ndarray, data: Dataset, base2sensor: dict[str, np.ndarray],
                    tool_frames: dict[str, np.ndarray]) -> np.ndarray:
    """Attitude error per pose row |log(R_measured · R_predicted⁻¹)| (rad), (k_oriented,): the
    rows of ``data`` with a measured orientation, predicted with ``params``, the registration per
    sensor and each marker's target frame on the flange (``R_flange←target``)."""
    rows = np.flatnonzero(data.oriented)
    if rows.size == 0:
        return np.zeros(0)
    chain = Chain(model)
    r_f, _ = chain.flange_pose(data.q_rad[rows], params)
    s = np.stack([base2sensor[x][:3, :3] for x in data.sensor[rows]])
    t = np.stack([tool_frames[m] for m in data.marker[rows]])
    pred = s @ r_f @ t
    from calib.robot.transforms import rotation_angle

    return rotation_angle(data.rot[rows] @ np.swapaxes(pred, 1, 2))


def estimated_tool_frames(model: RobotModel, params: np.ndarray, data: Dataset,
                          base2sensor: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each measured marker's target frame on the flange (3, 3) that the pose rows of ``data`` give
    for the model ``params`` and registration: the chordal mean of (R_reg · R_flange)⁻¹ · R_measured
    — how the "before" model places a target whose frame the model does not state; the model's
    ``rpy_deg`` where it does."""
    chain = Chain(model)
    rows = np.flatnonzero(data.oriented)
    out = {}
    r_f, _ = chain.flange_pose(data.q_rad[rows], params)
    s = np.stack([base2sensor[x][:3, :3] for x in data.sensor[rows]]) if rows.size else np.zeros((0, 3, 3))
    for m in sorted(set(data.marker[rows].tolist())):
        rpy = model.tool.markers[model.marker_index(m)].rpy_deg
        if rpy is not None:
            out[m] = euler_zyx_to_matrix(*np.radians([rpy[2], rpy[1], rpy[0]]))
            continue
        sel = data.marker[rows] == m
        est = np.einsum("kji,kjl->il", s[sel] @ r_f[sel], data.rot[rows][sel])
        u, _, vt = np.linalg.svd(est)
        out[m] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return out


def ident_result_dict(result: IdentResult, cal: Dataset, val: Dataset | None = None) -> dict:
    """``result.json`` content for a full identification (mm, degrees).

    ``metrics``: the seed's EACPE/EMCPE (position; EACAE/EMCAE are null without orientation
    data) on the calibration set and, if given, the validation set — ``before`` with the nominal
    model registered by least squares on the calibration data, ``after`` with the identified model
    and its registration. Validation points are scored with those calibration registrations
    (``calib.fit.metrics.validation_scores``); ``validation.reregistered`` is the optimistic figure with
    a registration fitted to the validation points, named as such. ``metric_notes``: how, and caveats.

    ``validation`` holds only the validation points of markers the calibration measured (their
    positions were fitted): the headline. Points of markers it never measured are scored apart in
    ``validation_unseen_markers``, with each marker's estimated placement and its uncertainty
    (``unseen_marker_placement``) — an estimate, never mixed into the headline.
    """
    from calib.fit.metrics import absolute_errors, validation_scores

    chain = Chain(result.model)
    nominal = chain.nominal
    params = []
    for i, name in enumerate(chain.param_names):
        kind = name.rsplit(".", 1)[1]
        angle = kind in ("offset", "alpha", "beta")
        to_unit = math.degrees if angle else float
        entry = {
            "name": name,
            "unit": "deg" if angle else "mm",
            "nominal": to_unit(nominal[i]),
            "value": to_unit(result.params[i]),
            "change": to_unit(result.params[i] - nominal[i]),
            "std": None if math.isnan(result.std[i]) else to_unit(result.std[i]),
            "identified": name in result.free_names,
        }
        if name in result.excluded:
            entry["reason"] = result.excluded[name]
        params.append(entry)

    cal_before = _marker_rows(chain, cal, nominal)
    cal_after = _marker_rows(chain, cal, result.params)
    notes = ["before: the nominal model, registered by least squares on the calibration data; after: the identified "
             "model with the identified registration; validation points are scored with these calibration "
             "registrations (never one fitted to the points being scored)"]

    from calib.fit.metrics import registrations

    reg_before = registrations(cal, cal_before)
    oriented = cal.has_orientation
    frames_before = estimated_tool_frames(result.model, nominal, cal, reg_before) if oriented else {}

    def attitude(data: Dataset, which: str) -> np.ndarray | None:
        """Attitude errors of ``data``'s pose rows whose marker the calibration's pose rows have."""
        if not oriented or not data.has_orientation:
            return None
        keep = data.oriented & np.isin(data.marker, list(result.tool_frames)) & np.isin(data.sensor, list(reg_before))
        d = data.subset(keep)
        if which == "before":
            return attitude_errors(result.model, nominal, d, reg_before, frames_before)
        return attitude_errors(result.model, result.params, d, result.base2sensor, result.tool_frames)

    def scored(data: Dataset, after_params: np.ndarray, located: dict[str, str] | None = None) -> dict:
        b, a, rb, ra, caveats = validation_scores(cal, data, (cal_before, _marker_rows(chain, data, nominal)),
                                                  (cal_after, _marker_rows(chain, data, after_params)),
                                                  registration_after=result.base2sensor, located=located)
        notes.extend(caveats)
        return {"before": comprehensive_errors(b, attitude(data, "before")),
                "after": comprehensive_errors(a, attitude(data, "after")),
                "reregistered": {"before": comprehensive_errors(rb), "after": comprehensive_errors(ra)},
                "n_points": int(len(data)), "markers": sorted(set(data.marker.tolist()))}

    metrics = {"calibration": {"before": comprehensive_errors(absolute_errors(cal, cal_before), attitude(cal, "before")),
                               "after": comprehensive_errors(pose_errors(result.model, result.params, cal, result.base2sensor),
                                                             attitude(cal, "after"))}}
    if oriented:
        notes.append("EACAE / EMCAE (degrees): mean / max attitude error of the pose rows, the angle of "
                     "R_measured · R_predicted⁻¹; before: the nominal model with the calibration's least-squares "
                     "registration and the targets' frames on the flange that the calibration's pose rows give for it "
                     "(the model's rpy_deg where stated); after: the identified model, registration and frames")
    if val is not None and len(val):
        # Headline: only markers the calibration measured (their positions are fitted). Markers it
        # never measured are placed by an estimate: scored apart, labelled, never in the headline.
        seen = np.isin(val.marker, cal.marker)
        if seen.any():
            metrics["validation"] = scored(val.subset(seen), result.params)
        if not seen.all():
            unseen = val.subset(~seen)
            names = sorted(set(unseen.marker.tolist()))
            placed, located, sd = unseen_marker_placement(result, names)
            block = scored(unseen, placed, located)
            block["placement"] = {m: {"how": located.get(m, "the model's position (not fitted, not located)"),
                                      "uncertainty_mm": sd.get(m)} for m in names}
            block["label"] = ("held-out points of markers the calibration never measured: their position on the flange "
                              "is estimated (see placement), not measured, so this figure is not the validation headline")
            metrics["validation_unseen_markers"] = block
            if not seen.any():
                notes.append("no validation point is of a marker the calibration measured: there is no validation "
                             "headline; validation_unseen_markers scores them with estimated marker positions")
    if result.compliance is not None:
        notes.append("after: the identified kinematics without the fitted sag (a corrected model file carries "
                     "kinematics only); the sag the compliances explain is left in these errors")
    return {
        "method": "full",
        "robot": result.model.name,
        "parameters": params,
        "excluded": result.excluded,
        "registration": {s: np.asarray(t).round(9).tolist() for s, t in result.base2sensor.items()},
        "tool_prior_mm": result.tool_prior_mm,
        "rms_mm": result.rms_mm,
        "condition_number": result.condition_number,
        "evaluations": result.iterations,
        "starts": result.starts,
        "warnings": result.warnings,
        "do_not_use": result.do_not_use,
        "canonical": result.canonical,
        "attitude_weight": result.attitude_weight,
        "tool_frames": {m: {"rpy_deg": np.degrees(matrix_to_euler_zyx(t))[::-1].round(6).tolist(),
                            "std_deg_rotation_vector": [None if not math.isfinite(v) else float(np.degrees(v)) for v in result.tool_frame_std_rad[m]]}
                        for m, t in result.tool_frames.items()},
        "metrics": metrics,
        "metric_notes": notes,
        "compliance": None if result.compliance is None else [
            {"joint": ax, "unit": "rad/(N·m)", "status": "fitted" if math.isfinite(sd) else "undetermined",
             "value": float(v) if math.isfinite(sd) else None, "std": float(sd) if math.isfinite(sd) else None,
             "reason": "" if math.isfinite(sd) else result.excluded.get(f"{ax}.compliance", "")}
            for ax, v, sd in zip(result.model.axis_names, result.compliance, result.compliance_std)],
    }


#: Draws of the fitted markers (within their std) for the located marker's placement uncertainty.
PLACEMENT_DRAWS = 200


def unseen_marker_placement(result: IdentResult, unseen: list[str], seed: int = 0
                            ) -> tuple[np.ndarray, dict[str, str], dict[str, float]]:
    """``locate_unseen_markers`` with the uncertainty of each located marker (mm, rms of the 3-D
    error): the fitted markers' std carried through the rigid transform (``PLACEMENT_DRAWS``
    seeded draws) combined with the layout's misfit rms (how far the drawing's layout is from the
    fitted markers: the unseen marker's own drawing error is of that order). An estimate: the
    unseen marker's real position was never measured."""
    from calib.fit.registration import register_least_squares

    params, located = locate_unseen_markers(result, unseen)
    if not located:
        return params, located, {}
    chain = Chain(result.model)
    ms = chain.marker_slice()
    fitted = [m for m in chain.marker_names if all(f"{m}.{c}" in result.free_names for c in "xyz")]
    idx = [chain.marker_names.index(m) for m in fitted]
    nominal = chain.nominal[ms].reshape(-1, 3)
    now = result.params[ms].reshape(-1, 3)[idx]
    sd = np.nan_to_num(result.std[ms].reshape(-1, 3)[idx])
    plate = register_least_squares(nominal[idx], now).base2sensor
    misfit = float(np.sqrt(np.mean(np.sum((apply(plate, nominal[idx]) - now) ** 2, axis=1))))
    rng = np.random.default_rng(seed)
    out = {}
    draws = [register_least_squares(nominal[idx], now + rng.normal(0.0, 1.0, now.shape) * sd).base2sensor
             for _ in range(PLACEMENT_DRAWS)]
    for m in located:
        k = chain.marker_names.index(m)
        pts = np.array([apply(t, nominal[k]) for t in draws])
        spread = float(np.sqrt(np.sum(np.var(pts, axis=0))))
        out[m] = float(math.hypot(spread, misfit))
    return params, located, out


def locate_unseen_markers(result: IdentResult, unseen: list[str]) -> tuple[np.ndarray, dict[str, str]]:
    """Place markers the calibration did not measure from the model's marker layout (a nest
    plate's drawing): the rigid transform that takes the model's positions of the fitted markers
    onto their fitted positions carries the unseen ones too. Needs three fitted markers not on one
    line; otherwise the unseen markers stay at the model's positions (and the scoring says so).

    Returns (the identified parameter vector with the located markers, marker → how it was located).
    """
    from calib.fit.registration import register_least_squares

    chain = Chain(result.model)
    fitted = [m for m in chain.marker_names if all(f"{m}.{c}" in result.free_names for c in "xyz")]
    params = result.params.copy()
    if not unseen or len(fitted) < 3:
        return params, {}
    ms = chain.marker_slice()
    nominal = chain.nominal[ms].reshape(-1, 3)
    now = params[ms].reshape(-1, 3)
    idx = [chain.marker_names.index(m) for m in fitted]
    try:
        plate = register_least_squares(nominal[idx], now[idx]).base2sensor
    except ValueError:  # the fitted markers lie on one line: the turn about it is unknown
        return params, {}
    misfit = float(np.sqrt(np.mean(np.sum((apply(plate, nominal[idx]) - now[idx]) ** 2, axis=1))))
    how = (f"located from the model's marker layout, moved with the rigid transform that takes the model's "
           f"{', '.join(fitted)} onto their fitted positions (misfit rms {misfit:.3f} mm) — right if the layout "
           "(the plate's drawing) is; otherwise measure it in the calibration")
    out = {}
    for m in unseen:
        k = chain.marker_names.index(m)
        params[ms.start + 3 * k: ms.start + 3 * k + 3] = apply(plate, nominal[k])
        out[m] = how
    return params, out


def _marker_rows(chain: Chain, data: Dataset, params: np.ndarray) -> np.ndarray:
    pos = chain.marker_positions(data.q_rad, params)
    return pos[np.arange(len(data)), _lookup(data.marker, chain.marker_names)]
