"""Study: real 6-DoF tracker data of a UR10 (``../shared/fixtures/ur10-ipa-tracker-6dof/``),
position-only against position + attitude full identification.

Per series (B: 1 495 joint-space poses; D: 632 ISO-cube poses): 200 random calibration poses
(seeded), the rest held out, scored with the calibration's registration and target frame.
"before": the nominal UR10 (UR's DH) with the registration least-squares fitted on the
calibration poses and the T-Mac frame those poses give for it; "base+tool": only registration,
T-Mac position and frame fitted (the reference's baseline); then full identification with
positions only (its attitude through the T-Mac frame the calibration's orientations give for the
identified model) and with position + attitude rows. Across series: the robot identified on B,
only registration and T-Mac (position, frame) re-fitted on 20 poses of D, scored on D's rest.

The default run (``acquire fit``: the model chosen by cross-validation, ``calib.fit.model_choice``,
fitted by the zero-offset posterior's mode) with position + attitude rows and with positions only
(its attitude through the T-Mac frame the calibration's orientations give for the fitted robot),
and full identification with joint compliance and attitude rows (the reference's model).
Across series both ways (B → D and D → B).

    python tests/bench/study_ur10_pose.py [--seed 0] [--cal 200]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.fit.identification import (IdentOptions, attitude_errors, corrected_model, estimated_tool_frames,  # noqa: E402
                                      identify, pose_errors)
from calib.fit.pose_scoring import fitted_frames, held_out_pose_errors  # noqa: E402
from calib.fit.metrics import registrations  # noqa: E402
from calib.fit.model_choice import choose_model, options_for, parse_candidate  # noqa: E402
from calib.fit.offsets import FitOptions, fit_mode  # noqa: E402
from calib.measure.ipa_tracker import read_ipa_series  # noqa: E402
from calib.robot.kinematics import Chain  # noqa: E402
from calib.robot.model import load_robot_model  # noqa: E402

SHARED = ROOT.parent / "shared" / "fixtures" / "ur10-ipa-tracker-6dof"
SERIES = {"B": SHARED / "Series_B" / "measurements_joint_configurations.csv",
          "D": SHARED / "Series_D" / "measurements_iso_cubes.csv"}
MODEL = load_robot_model(ROOT / "fixtures" / "robots" / "ur10.yaml")
#: The issue's independent fit (geometric errors + joint-2/3 compliance, 200 calibration poses).
REFERENCE = {"B": ((1.035, 0.081), (0.371, 0.044)), "D": ((0.730, 0.100), (0.316, 0.043))}


def kinematic_names(model) -> list[str]:
    """Every joint offset and link parameter of the model (what "base+tool" keeps nominal)."""
    return [n for n in Chain(model).param_names if n.split(".")[0] in model.axis_names]


def split(ds, n_cal: int, seed: int):
    sel = np.zeros(len(ds), bool)
    sel[np.random.default_rng(seed).permutation(len(ds))[:n_cal]] = True
    return ds.subset(sel), ds.subset(~sel)


def score(model, params, cal, val, b2s, frames) -> tuple[float, float, float, float]:
    p = pose_errors(model, params, val, b2s)
    a = np.degrees(attitude_errors(model, params, val, b2s, frames))
    return p.mean(), a.mean(), p.max(), a.max()


def fits(model, cal, val, n_starts: int = 6) -> dict[str, tuple]:
    chain = Chain(model)
    out = {}
    reg = registrations(cal, chain.marker_positions(cal.q_rad)[:, 0])
    out["before (nominal, registered)"] = score(model, chain.nominal, cal, val, reg,
                                                estimated_tool_frames(model, chain.nominal, cal, reg))
    base_tool = IdentOptions(n_starts=1, exclude=tuple(kinematic_names(model)))
    r = identify(model, cal, base_tool)
    out["base+tool"] = score(model, r.params, cal, val, r.base2sensor, r.tool_frames)
    r = identify(model, cal.without_orientation(), IdentOptions(n_starts=n_starts))
    out["full, position only"] = score(model, r.params, cal, val, r.base2sensor,
                                       estimated_tool_frames(model, r.params, cal, r.base2sensor))
    pose = identify(model, cal, IdentOptions(n_starts=n_starts))
    out["full, position + attitude"] = score(model, pose.params, cal, val, pose.base2sensor, pose.tool_frames)
    if model.has_dynamics:
        sag = identify(model, cal, IdentOptions(n_starts=n_starts, compliance=True))
        out["full+compliance, pos + att"] = score_sag(model, sag, val)
    return out, pose


def score_sag(model, result, val) -> tuple[float, float, float, float]:
    """Held-out errors of an identification with compliance: the sag turns the arm at val's poses."""
    from calib.robot.gravity import gravity_torques

    chain = Chain(model)
    if result.compliance is None:
        return score(model, result.params, None, val, result.base2sensor, result.tool_frames)
    q = val.q_rad + chain.sign * result.compliance * gravity_torques(chain, val.q_rad, result.params)
    return score(model, result.params, None, replace(val, q_rad=q), result.base2sensor, result.tool_frames)


def default_fit(model, cal, val) -> dict[str, tuple]:
    """The default run's model (cross-validated choice among the zero-offset candidates and full),
    fitted with and without the attitude rows; for a chosen "full" the identification's rows above."""
    base = FitOptions(method="laplace")
    choice = choose_model(model, cal, base, include_full=False)
    cand = parse_candidate(choice.chosen, model)
    scale = choice.link_scale
    options = options_for(cand, base, (scale["length_mm"], scale["angle_deg"]) if scale else None)
    out, robot = {}, None
    for label, data in ((f"default [{choice.chosen}], pos only", cal.without_orientation()),
                        (f"default [{choice.chosen}], pos + att", cal)):
        mf = fit_mode(model, data, options, tol=1e-10)
        frames = fitted_frames(_with_orientation(mf, cal), mf.theta)
        p, a = held_out_pose_errors(mf, val, frames)
        a = np.degrees(a)
        out[label] = (p.mean(), a.mean(), p.max(), a.max())
        full = mf.post.full_vector(mf.theta)
        comp = full[mf.post.n_full - mf.post.C:] * 1e-6 if mf.post.C else np.zeros(model.n_joints)
        robot = (corrected_model(model, mf.post.chain_params(full)), comp)  # the last: position + attitude
    return out, robot


def sagged(model, data, compliance):
    """``data`` with each configuration turned by the robot's own sag (compliance rad/(N·m))."""
    from calib.robot.gravity import gravity_torques

    chain = Chain(model)
    return replace(data, q_rad=data.q_rad + chain.sign * compliance * gravity_torques(chain, data.q_rad))


def _with_orientation(mf, cal):
    """The fit's posterior on ``cal`` with its attitude rows (the same mask): its profiled target
    frame at the fit's vector is the one the calibration's orientations give for the fitted robot."""
    from calib.fit.posterior import OffsetPosterior

    post = mf.post
    return OffsetPosterior(post.chain, cal, mf.b2s0, mf.mask, error=post.error, nu=post.nu, link_prior=mf.link_prior,
                           compliance=bool(post.C), sag_params=mf.sag_params)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cal", type=int, default=200)
    args = ap.parse_args()
    if not all(p.is_file() for p in SERIES.values()):
        sys.exit(f"the shared UR10 data is not at {SHARED}")
    data = {k: read_ipa_series(p, prefix=k) for k, p in SERIES.items()}
    print(f"UR10, Leica tracker + T-Mac; {args.cal} calibration poses per series (seed {args.seed}), the rest held out")
    print(f"{'':34}{'EACPE mm':>10}{'EACAE °':>10}{'EMCPE mm':>10}{'EMCAE °':>10}")
    identified, default_robots = {}, {}
    for name, ds in data.items():
        cal, val = split(ds, args.cal, args.seed)
        rows, identified[name] = fits(MODEL, cal, val)
        more, default_robots[name] = default_fit(MODEL, cal, val)
        rows.update(more)
        print(f"Series {name} ({len(cal)} cal / {len(val)} held out)")
        for label, v in rows.items():
            print(f"  {label:32}" + "".join(f"{x:>10.4f}" for x in v))
        (rb, ab), (ra, aa) = REFERENCE[name]
        print(f"  {'reference: base+tool → full+compl.':32}{rb:>10.3f}{ab:>10.3f} → {ra:.3f} mm, {aa:.3f}°")
    # Across series: the robot from one series, registration and T-Mac re-fitted on 20 poses of the other.
    for src, dst in (("B", "D"), ("D", "B")):
        robot = corrected_model(MODEL, identified[src].params)
        cal, val = split(data[dst], 20, args.seed)
        for label, c in (("pos + att", cal), ("pos only", cal.without_orientation())):
            nominal = identify(MODEL, c, IdentOptions(n_starts=1, exclude=tuple(kinematic_names(MODEL))))
            r = identify(robot, c, IdentOptions(n_starts=1, exclude=tuple(kinematic_names(robot))))
            print(f"Across series: robot identified on {src} (position + attitude); on {dst} only registration and "
                  f"T-Mac re-fitted on {len(cal)} poses ({label}), {len(val)} held out")
            for name, res, m in (("nominal robot, base+tool", nominal, MODEL), (f"robot from {src}, base+tool", r, robot)):
                fr = res.tool_frames or estimated_tool_frames(m, res.params, cal, res.base2sensor)
                print(f"  {name:32}" + "".join(f"{x:>10.4f}" for x in score(m, res.params, cal, val, res.base2sensor, fr)))
            # The default run's robot from src (its links, offsets and compliances): its sag applied.
            robot_d, comp = default_robots[src]
            c_s, v_s = sagged(robot_d, c, comp), sagged(robot_d, val, comp)
            r = identify(robot_d, c_s, IdentOptions(n_starts=1, exclude=tuple(kinematic_names(robot_d))))
            fr = r.tool_frames or estimated_tool_frames(robot_d, r.params, sagged(robot_d, cal, comp), r.base2sensor)
            print(f"  {'default-run robot from ' + src + ', b+t':32}" + "".join(
                f"{x:>10.4f}" for x in score(robot_d, r.params, c_s, v_s, r.base2sensor, fr)))


if __name__ == "__main__":
    main()
