"""Study (not a timed test): a model file with one joint zero 180° off — does the default
``--method full`` reach the minimum that the model with the right zero reaches, and is the answer
reported canonically (offset ≈ ±180° + δ in (−180°, 180°], links on the nominal branch)?

    python tests/bench/study_zero_flips.py [--seeds 4]

Data: the tracker cell of ``tests/calib/tracker_sim.py`` (Stäubli TX60, nest plate 10 mm off,
link errors, 36 configurations × 3 nests, noise 0.03 mm) with J2, J3, J4 or J5 turned 180°.
Per case: the default fit's rms and cost against the right model's (2 starts), which start won,
the time, and whether offsets and link parameters are canonical.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.robot.canonical import wrap_angle  # noqa: E402
from calib.fit.identification import IdentOptions, identify  # noqa: E402
from calib.robot.kinematics import Chain  # noqa: E402
from tests.calib.tracker_sim import CAL_NESTS, observe, tracker_cell  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args()
    logging.disable(logging.WARNING)
    reached = canonical = total = 0
    for joint in (1, 2, 3, 4):
        for seed in range(args.seeds):
            cell = tracker_cell(seed)
            chain = Chain(cell.model)
            truth = cell.truth.copy()
            truth[joint] += math.pi
            cal = observe(chain, cell.cal.q_rad[::len(CAL_NESTS)], truth, CAL_NESTS, cell.base2sensor,
                          np.random.default_rng(seed), 0.03, "cal")
            t0 = time.perf_counter()
            r = identify(cell.model, cal)
            dt = time.perf_counter() - t0
            d = cell.model.model_dump()
            d["joints"][joint]["theta"] += 180.0
            right = identify(type(cell.model).model_validate(d), cal, IdentOptions(n_starts=2))
            ok = r.starts[0]["cost"] <= right.starts[0]["cost"] * (1 + 1e-6)
            twists = np.concatenate([chain.index("alpha"), chain.index("beta")])
            branch = np.all(np.abs(r.params[chain.index("a")] - chain.nominal[chain.index("a")]) < 5.0) \
                and np.all(np.abs(wrap_angle(r.params[twists] - chain.nominal[twists])) < math.radians(1.0)) \
                and abs(abs(math.degrees(r.params[joint])) - 180.0) < 1.0 and np.all(np.abs(r.params[:chain.n]) <= math.pi)
            reached += ok
            canonical += bool(branch)
            total += 1
            print(f"J{joint + 1} +180° seed {seed}: rms {r.rms_mm:.4f} mm (right model {right.rms_mm:.4f}), best "
                  f"{'reached' if ok else 'MISSED'} by '{r.starts[0]['label']}', canonical {bool(branch)}, "
                  f"offset {math.degrees(r.params[joint]):+.3f}°, {dt:.1f} s", flush=True)
    print(f"reached the right model's minimum: {reached}/{total}; canonical: {canonical}/{total}")


if __name__ == "__main__":
    main()
