"""Study (not a timed test): how often each start of ``--method full`` reaches the best minimum
when the nominal model is poor — a joint's zero 120° or 180° from the model's (a convention slip).

    python tests/bench/study_multistart.py [--seeds 4] [--starts 14]

Data: the tracker cell of ``tests/calib/tracker_sim.py`` (Stäubli TX60, nest plate 10 mm off,
link errors, 36 configurations × 3 nests, noise 0.03 mm) with J2, J4 or J5 turned. For each
case, ``identify`` with ``--starts`` starts (spread 5 mm / 3°, seeded); the best of them is the
reference. Prints per case whether the staged solve from nominal and the plain one-stage solve
from nominal reach it (else their rms), the best rms, and the counts.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.fit.identification import IdentOptions, identify  # noqa: E402
from calib.robot.kinematics import Chain  # noqa: E402
from tests.calib.tracker_sim import CAL_NESTS, observe, tracker_cell  # noqa: E402


def _reached(start: dict) -> str:
    return "best" if start["same_minimum"] else f"{start['rms_mm']:.3f} mm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--starts", type=int, default=14)
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # the fits' own warnings: the table says it
    staged_ok = plain_ok = total = 0
    for joint in (1, 3, 4):
        for deg in (120.0, 180.0):
            for seed in range(args.seeds):
                cell = tracker_cell(seed)
                chain = Chain(cell.model)
                truth = cell.truth.copy()
                truth[joint] += np.radians(deg)
                rng = np.random.default_rng(seed)
                cal = observe(chain, cell.cal.q_rad[::len(CAL_NESTS)], truth, CAL_NESTS, cell.base2sensor, rng, 0.03, "cal")
                r = identify(cell.model, cal, IdentOptions(n_starts=args.starts, seed=5, start_spread=(5.0, 3.0)))
                by = {s["label"]: s for s in r.starts}
                st, pl = by["staged from nominal"], by["plain from nominal"]
                staged_ok += st["same_minimum"]
                plain_ok += pl["same_minimum"]
                total += 1
                print(f"J{joint + 1} +{deg:.0f}° seed {seed}: staged {_reached(st)}, plain {_reached(pl)}, "
                      f"best rms {r.starts[0]['rms_mm']:.3f} mm", flush=True)
    print(f"reached the best of {args.starts} starts: staged {staged_ok}/{total}, plain {plain_ok}/{total}")


if __name__ == "__main__":
    main()
