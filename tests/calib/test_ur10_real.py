"""The UR10 model's masses, and the default fit on real laser-tracker data of a UR10 (issue 22).

Data: ``../shared/fixtures/ur10-ipa-tracker-6dof/`` (series B: 1 495 joint configurations, series D:
632 configurations on ISO 9283 cubes; a Leica T-Mac on the flange, positions in mm). The test
calibrates on a random part of one series and scores configurations the fit never saw: the rest
of that series (with the fit's own registration) and the other series (the T-Mac was mounted
anew there: its position on the flange and the tracker's registration are fitted on 200 of that
series' configurations, the robot kept as calibrated, and all the others scored). The reference is an
exact geometric Levenberg–Marquardt fit written here, independently of ``calib``: every DH
parameter of every joint, Hayati's β for the parallel axes J2, J3, the tool and the registration,
no priors.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib.fit.auto_fit import auto_fit
from calib.fit.identification import IdentOptions, identify, pose_errors
from calib.fit.model_choice import options_for, parse_candidate
from calib.fit.offsets import FitOptions, fit_mode
from calib.measure.dataset import Dataset, from_arrays
from calib.robot.gravity import gravity_torques
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model

ROOT = Path(__file__).resolve().parents[2]
UR10 = ROOT / "fixtures" / "robots" / "ur10.yaml"
DATA = ROOT.parent / "shared" / "fixtures" / "ur10-ipa-tracker-6dof"
SERIES = {"B": DATA / "Series_B" / "measurements_joint_configurations.csv",
          "D": DATA / "Series_D" / "measurements_iso_cubes.csv"}
JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
G = 9.81  # m/s², the model's gravity


# --- the model's masses (fast) -----------------------------------------------------------------------
def test_ur10_gravity_torques_match_a_hand_sum_of_the_published_masses_with_the_arm_stretched_out():
    """At q = 0 UR's DH puts the arm horizontal along −x: the shoulder (J2) and elbow (J3) carry
    Σ m·g·(horizontal lever), summed here by hand from UR's table (masses kg, centres of mass in
    each link's frame); the base (J1) and J6 axes carry nothing."""
    model = load_robot_model(UR10)
    assert model.has_dynamics
    m = [7.1, 12.7, 4.27, 2.0, 2.0, 0.365]  # UR10 (CB3), kg
    shoulder_to_elbow, elbow_to_wrist = 0.612, 0.5723  # m
    # x of each centre from the shoulder axis: link 2 at 0.38 m from the elbow back towards the
    # shoulder, link 3 at 0.24 m from the wrist back towards the elbow, the wrist links on the wrist.
    lever2 = [0.0, shoulder_to_elbow - 0.38, shoulder_to_elbow + elbow_to_wrist - 0.24] + [shoulder_to_elbow + elbow_to_wrist] * 3
    tau2 = G * sum(mi * li for mi, li in zip(m[1:], lever2[1:]))
    tau3 = G * (m[2] * (elbow_to_wrist - 0.24) + sum(m[3:]) * elbow_to_wrist)
    tau = gravity_torques(Chain(model), np.zeros(6))
    assert tau[1] == pytest.approx(tau2, rel=1e-9) and tau[2] == pytest.approx(tau3, rel=1e-9)
    assert abs(tau[0]) < 1e-9 and abs(tau[5]) < 1e-9
    assert 110 < tau[1] < 130  # about 119 N·m: the UR10's shoulder holds its outstretched arm


# --- real data ---------------------------------------------------------------------------------------
def read_series(path: Path) -> Dataset:
    """An IPA series file as a dataset: ';' separated, decimal comma, joints in radians, the T-Mac
    position (mm) and, as the spread of one sample, the rms of its per-axis standard deviations."""
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    col = {h: i for i, h in enumerate(lines[0].split(";"))}
    a = np.array([[float(v.replace(",", ".")) for v in ln.split(";")] for ln in lines[1:]])
    std = np.sqrt(np.mean(a[:, [col[f"measurement_std_{c}"] for c in "xyz"]] ** 2, axis=1))
    return from_arrays(a[:, [col[j] for j in JOINTS]], a[:, [col[f"measurement_{c}"] for c in "xyz"]],
                       marker="tmac", sensor="tracker", config=np.array([f"c{i}" for i in range(len(a))]),
                       std_mm=std, count=np.ones(len(a)), split="cal")


def split(ds: Dataset, sizes: tuple[int, ...], seed: int) -> list[Dataset]:
    """Disjoint random subsets of ``ds`` of the given sizes (configurations kept in file order)."""
    perm = np.random.default_rng(seed).permutation(len(ds))
    edges = np.cumsum((0,) + sizes)
    return [ds.subset(np.sort(perm[a:b])) for a, b in zip(edges[:-1], edges[1:])]


def kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising Σ|R p + t − q|² for (k, 3) point sets."""
    pc, qc = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, qc - r @ pc


class GeometricLM:
    """Exact geometric model, independent of ``calib``: standard DH per joint
    T_i = Rz(θ_i + q_i) Tz(d_i) Tx(a_i) Rx(α_i) Ry(β_i) (β for J2, J3 only: their axes are parallel
    to the next), the marker (x, y, z) in the flange frame, the tracker pose (rotation vector, mm)."""

    BETA = (1, 2)

    def __init__(self, model) -> None:
        self.dh0 = np.array([[math.radians(j.theta), j.d, j.a, math.radians(j.alpha)] for j in model.joints])
        self.marker0 = np.array(model.tool.markers[0].xyz, dtype=float)

    def robot_positions(self, kin: np.ndarray, marker: np.ndarray, q: np.ndarray) -> np.ndarray:
        """(k, 3) marker positions in the base frame (mm) for joint angles q (k, 6) rad."""
        dh = self.dh0 + kin[:24].reshape(6, 4)
        beta = dict(zip(self.BETA, kin[24:26]))
        t = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        for i in range(6):
            th, d, a, al = dh[i]
            ct, st = np.cos(q[:, i] + th), np.sin(q[:, i] + th)
            ca, sa = math.cos(al), math.sin(al)
            link = np.zeros((len(q), 4, 4))
            link[:, 0, 0], link[:, 0, 1], link[:, 0, 2], link[:, 0, 3] = ct, -st * ca, st * sa, a * ct
            link[:, 1, 0], link[:, 1, 1], link[:, 1, 2], link[:, 1, 3] = st, ct * ca, -ct * sa, a * st
            link[:, 2, 1], link[:, 2, 2], link[:, 2, 3], link[:, 3, 3] = sa, ca, d, 1.0
            if i in beta:
                cb, sb = math.cos(beta[i]), math.sin(beta[i])
                link = link @ np.array([[cb, 0, sb, 0], [0, 1, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])
            t = t @ link
        return t[:, :3, :3] @ marker + t[:, :3, 3]

    def _fit(self, ds: Dataset, kin0: np.ndarray, marker0: np.ndarray, free_kin: bool):
        r0, t0 = kabsch(self.robot_positions(kin0, marker0, ds.q_rad), ds.xyz_mm)

        def unpack(x):
            kin = kin0 + x[9:] if free_kin else kin0
            return kin, marker0 + x[6:9], Rotation.from_rotvec(x[3:6]).as_matrix() @ r0, t0 + x[:3]

        def residuals(x):
            kin, marker, r, t = unpack(x)
            return (ds.xyz_mm - (self.robot_positions(kin, marker, ds.q_rad) @ r.T + t)).ravel()

        x0 = np.zeros(9 + (26 if free_kin else 0))
        sol = least_squares(residuals, x0, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
        return unpack(sol.x)

    def fit(self, ds: Dataset):
        """Every parameter free, from the nominal model: (kinematics (26,), marker, R, t)."""
        return self._fit(ds, np.zeros(26), self.marker0, True)

    def errors(self, fitted, ds: Dataset) -> np.ndarray:
        kin, marker, r, t = fitted
        return np.linalg.norm(ds.xyz_mm - (self.robot_positions(kin, marker, ds.q_rad) @ r.T + t), axis=1)

    def transfer(self, fitted, train: Dataset, test: Dataset) -> np.ndarray:
        """The robot kept: marker and registration fitted on ``train``, errors (mm) on ``test``."""
        kin, marker, _, _ = fitted
        return self.errors(self._fit(train, kin, marker, False), test)


def calibrated_robot(chain: Chain, params: np.ndarray, k: np.ndarray | None = None, sag_params: np.ndarray | None = None):
    """``positions(q, marker)``: base-frame marker positions (k, 3) mm of a calibrated robot (chain
    parameters ``params``) for any q, with the marker position replaced, and the gravity sag of
    joint compliances ``k`` (rad/(N·m), to first order through the offsets' Jacobian and the
    torques at the arm ``sag_params`` — the fit's reference, None: nominal — as the fit models it);
    and the calibrated marker position."""
    sag_at = chain.nominal if sag_params is None else sag_params

    def positions(q: np.ndarray, marker: np.ndarray) -> np.ndarray:
        p = params.copy()
        p[chain.marker_slice()] = marker
        pos = chain.marker_positions(q, p)[:, 0]
        if k is not None and np.any(k):
            _, jac = chain.marker_jacobian(q, sag_at)
            pos = pos + np.einsum("kjn,kn->kj", jac[:, 0, :, : chain.n], chain.sign * gravity_torques(chain, q, sag_at) * k)
        return pos

    return positions, params[chain.marker_slice()]


def chosen_robot(mode, chain: Chain):
    """``calibrated_robot`` of a fitted offsets-model (``fit_mode``): its chain parameters and,
    where fitted, its compliances."""
    post = mode.post
    full = post.full_vector(mode.theta)
    k = full[post.n_full - post.C:] * 1e-6 if post.C else None  # µrad/(N·m) → rad/(N·m)
    return calibrated_robot(chain, post.chain_params(full), k, mode.sag_params)


def transfer_errors(positions, marker0: np.ndarray, train: Dataset, test: Dataset) -> np.ndarray:
    """A calibrated robot (``positions(q, marker)``) on another series: marker and registration fitted
    on ``train``, errors (mm) on ``test``."""
    r0, t0 = kabsch(positions(train.q_rad, marker0), train.xyz_mm)

    def predict(x, ds):
        return positions(ds.q_rad, marker0 + x[6:9]) @ (Rotation.from_rotvec(x[3:6]).as_matrix() @ r0).T + t0 + x[:3]

    sol = least_squares(lambda x: (train.xyz_mm - predict(x, train)).ravel(), np.zeros(9), method="lm")
    return np.linalg.norm(test.xyz_mm - predict(sol.x, test), axis=1)


@pytest.mark.slow
@pytest.mark.timeout(1200)  # series D: the random walk takes 40 000 steps to settle — 7 min of wall time on a loaded 2-core machine
@pytest.mark.skipif(not all(p.is_file() for p in SERIES.values()), reason="the shared UR10 tracker data is not next to the repository")
@pytest.mark.parametrize("name,other", [("B", "D"), ("D", "B")])
def test_the_default_fit_predicts_real_ur10_data_at_least_as_well_as_an_exact_geometric_fit(name, other):
    """Calibrate on 120 random configurations of one series: the default (``auto_fit``, the model
    chosen by cross-validation among candidates with and without joint compliance) predicts 300
    held-out configurations of that series, and the other series (tool and registration fitted on
    200 of its configurations, the rest scored), with a mean error no
    larger than the better of two exact geometric fits (the LM here, and ``--method full``'s
    identification); the verdict follows the rule: while the chosen model's
    cross-validated error per axis is more than 3× the tracker's spread of one sample, every offset
    says "do not enter" with that reason, and result.json carries the table and the reason."""
    model = load_robot_model(UR10)
    chain = Chain(model)
    cal, hold = split(read_series(SERIES[name]), (120, 300), seed=1)
    other_data = read_series(SERIES[other])
    tool_fit, scored = split(other_data, (200, len(other_data) - 200), seed=2)

    done = auto_fit(model, cal, None, FitOptions(n_draws=300), n_random=50)
    choice = done.choice
    table = choice.format()
    assert any(c.compliance for c in map(lambda s: parse_candidate(s.name, model), choice.scores)), table

    # The chosen model's fit (its posterior mode, as in the cross-validation), scored on points it never saw.
    scale = choice.link_scale
    tol = (scale["length_mm"], scale["angle_deg"]) if scale else None
    cand = parse_candidate(choice.chosen, model)
    assert cand.kind != "full", table  # a geometric model chosen: nothing to compare
    mode = fit_mode(model, cal, options_for(cand, replace(FitOptions(), method="laplace"), tol), tol=1e-10)
    own = np.linalg.norm(mode.predict_residuals(hold), axis=1)
    positions, marker = chosen_robot(mode, chain)
    own_other = transfer_errors(positions, marker, tool_fit, scored)

    lm = GeometricLM(model)
    fitted = lm.fit(cal)
    ident = identify(model, cal, IdentOptions(n_starts=1))
    positions_full, marker_full = calibrated_robot(chain, ident.params)
    ref = {"geometric LM": (lm.errors(fitted, hold).mean(), lm.transfer(fitted, tool_fit, scored).mean()),
           "full": (pose_errors(model, ident.params, hold, ident.base2sensor).mean(),
                    transfer_errors(positions_full, marker_full, tool_fit, scored).mean())}
    summary = "\n".join([table, f"mean error (mm) on held-out {name} / on series {other}:",
                          f"  {choice.chosen}: {own.mean():.4f} / {own_other.mean():.4f}"]
                         + [f"  {k}: {v[0]:.4f} / {v[1]:.4f}" for k, v in ref.items()])
    print(summary)
    assert own.mean() <= min(v[0] for v in ref.values()), summary
    assert own_other.mean() <= min(v[1] for v in ref.values()), summary

    # The verdict follows the rule, and result.json says why — and the sampler is not the reason: on
    # series D the Laplace check fails (a curved ridge, J5's zero against a₅) and the random walk
    # must settle (it did not within the former 12 000 steps: R-hat 1.10).
    assert not any(k in r for r in done.refused for k in ("has not converged", "not settled", "effective draws")), done.refused
    chosen = choice.score(choice.chosen)
    spread = float(np.sqrt(np.mean(cal.std_mm**2)))
    entered = [a["axis"] for a in done.doc["controller"]["axes"] if a["action"] == "enter"]
    assert done.doc["model_choice"]["chosen"] == choice.chosen
    assert {c["model"] for c in done.doc["model_choice"]["candidates"]} == {s.name for s in choice.scores}
    # The chosen model's own guard (its held-out error against the tracker's spread) now says whether
    # the *model* may be used (export, compensation): model_refused. What the controller gets is judged
    # apart (calib.fit.entered): "enter" exactly where the offsets beat the robot as found held out.
    if chosen.rms_mm / math.sqrt(3) > 3 * spread:
        assert any("the measured spread of one sample" in r for r in done.model_refused), summary
    else:
        assert not any("the measured spread of one sample" in r for r in done.model_refused), summary
    gets = done.doc["entered"]
    lower = gets["heldout"]["improvement_mm"]["ci95"][0]
    assert (gets["verdict"] == "enter") == (lower is not None and lower > 0 and not done.refused), (gets, done.refused)
    assert sorted(entered) == sorted(e["joint"] for e in gets["offsets"] if e["enter"]) or gets["verdict"] != "enter"


# --- the reason the operator reads (fast) ------------------------------------------------------------
def _doc(chosen: str, names: list[str], cv_rms_mm: float = 0.4) -> dict:
    """A result document with a model-choice table and a tracker spread of 0.02 mm."""
    row = {"cv_mean_mm": 0.3, "cv_rms_mm": cv_rms_mm, "failed": None}
    return {"model_choice": {"chosen": chosen, "nominal": {"cv_mean_mm": 3.0},
                             "candidates": [dict(row, model=n) for n in names]},
            "diagnostics": {"error_budget": {"tracker": {"sample_spread_mm": 0.02, "noise_mm": 0.02, "n_rows": 100}}}}


@pytest.mark.parametrize("chosen,names,says", [
    ("offsets+tool+links", ["offsets", "offsets+tool+links", "offsets+tool+links+compliance"],
     "the chosen model (offsets+tool+links) does not describe this robot (not in it: gravity sag)"),
    ("offsets", ["offsets", "offsets+tool", "offsets+tool+links"],
     "(not in it: tool, link errors, gravity sag (the robot model has no link masses))"),
    ("offsets+tool+links+compliance", ["offsets", "offsets+tool+links+compliance"],
     "even the chosen model (offsets+tool+links+compliance: tool, link errors and gravity sag) leaves robot error"),
])
def test_a_held_out_error_far_above_the_noise_says_what_the_chosen_model_leaves_out(chosen, names, says):
    from calib.robot.controller import earned_reasons

    reasons = earned_reasons(_doc(chosen, names))
    assert len(reasons) == 1 and "12× the measured spread of one sample (0.02 mm)" in reasons[0], reasons
    assert says in reasons[0], reasons
    assert earned_reasons(_doc(chosen, names, cv_rms_mm=0.05)) == []  # 0.029 mm per axis: within 3× the spread
