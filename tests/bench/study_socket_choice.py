"""Study: the socket default (``acquire.run.socket_fit.run_socket_fit``, ``--method auto``) on
simulated Franka Panda socket cells — which model it picks, its held-out error against the best
candidate's, the link scales the evidence chose, and how often an offset marked "enter" misses
the truth's 95 % interval.

Cells (``tests.calib.test_socket_choice._panda_cell``): zero-offsets ~ N(0, 0.3°), link errors of
a Panda's size (d, a ~ N(0, 0.5 mm); α ~ N(0, 0.3°)), the ball at (3, −2, 45) mm on the flange
where the model declares (0, 0, 60) mm, three placements of a two-socket tool 50 mm apart, 20
configurations per socket, 0.05 mm of play.

    PYTHONPATH=$PWD python3 tests/bench/study_socket_choice.py --cells 12
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

from acquire.run.socket_fit import run_socket_fit
from tests.calib.test_socket_choice import _entered_outside, _panda_cell


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cells", type=int, default=12)
    args = ap.parse_args()
    t0 = time.process_time()
    chosen, entered, missed, ratio = Counter(), 0, [], []
    for seed in range(args.cells):
        model, truth, ds = _panda_cell(100 + seed)
        doc, _ = run_socket_fit(model, ds, method="auto", link_tolerance=None)
        mc = doc["model_choice"]
        scored = [c for c in mc["candidates"] if c["cv_mean_mm"] is not None]
        best = min(c["cv_mean_mm"] for c in scored)
        pick = next(c for c in scored if c["model"] == mc["chosen"])
        links = mc["link_scale"].get("offsets+ball+links", {})
        chosen[mc["chosen"]] += 1
        ratio.append(pick["cv_mean_mm"] / best)
        n_enter = sum(j["status"] == "fitted" for j in doc["joint_offsets"])
        miss = _entered_outside(doc, truth)
        entered, missed = entered + n_enter, missed + miss
        print(f"cell {seed:2d}: {mc['chosen']:<20} held-out {pick['cv_mean_mm']:.4f} mm (best {best:.4f}, nominal "
              f"{mc['nominal']['cv_mean_mm']:.3f}); link scale {links.get('length_mm')} mm / {links.get('angle_deg')}°; "
              f"enter {n_enter}, outside the truth's interval {len(miss)}")
    print(f"chosen: {dict(chosen)}; chosen/best held-out error at most {max(ratio):.4f}")
    print(f"'enter' given {entered} times, {len(missed)} outside the truth's 95 % interval "
          f"({100 * len(missed) / max(entered, 1):.1f} %): {missed}")
    print(f"{time.process_time() - t0:.0f} CPU-s")


if __name__ == "__main__":
    main()
