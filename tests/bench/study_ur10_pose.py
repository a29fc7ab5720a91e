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

    python tests/bench/study_ur10_pose.py [--seed 0] [--cal 200]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.fit.identification import (IdentOptions, attitude_errors, corrected_model, estimated_tool_frames,  # noqa: E402
                                      identify, pose_errors)
from calib.fit.metrics import registrations  # noqa: E402
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
    return out, pose


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
    identified = {}
    for name, ds in data.items():
        cal, val = split(ds, args.cal, args.seed)
        rows, identified[name] = fits(MODEL, cal, val)
        print(f"Series {name} ({len(cal)} cal / {len(val)} held out)")
        for label, v in rows.items():
            print(f"  {label:32}" + "".join(f"{x:>10.4f}" for x in v))
        (rb, ab), (ra, aa) = REFERENCE[name]
        print(f"  {'reference: base+tool → full+compl.':32}{rb:>10.3f}{ab:>10.3f} → {ra:.3f} mm, {aa:.3f}°")
    # Across series: the robot from B, registration and T-Mac re-fitted on 20 poses of D.
    robot_b = corrected_model(MODEL, identified["B"].params)
    cal, val = split(data["D"], 20, args.seed)
    only_base_tool = IdentOptions(n_starts=1, exclude=tuple(kinematic_names(robot_b)))
    nominal_rows, _ = fits(MODEL, cal, val, n_starts=1)
    r = identify(robot_b, cal, only_base_tool)
    print("Across series: robot identified on B (position + attitude); on D only registration and T-Mac re-fitted "
          f"on {len(cal)} poses, {len(val)} held out")
    print(f"  {'nominal robot, base+tool':32}" + "".join(f"{x:>10.4f}" for x in nominal_rows["base+tool"]))
    print(f"  {'robot from B, base+tool':32}" + "".join(f"{x:>10.4f}" for x in
                                                       score(robot_b, r.params, cal, val, r.base2sensor, r.tool_frames)))


if __name__ == "__main__":
    main()
