"""Study: do socket approaches chosen for spread gravity torques (``calib.plan.socket_poses``) fit
the sag better than approaches picked at random from the same IK candidates?

For each seed, the plan of ``fixtures/plans/example-socket.yaml`` (3 placements × 2 sockets, 6
configurations each) is built twice: the planner's farthest-point choice, and 6 random picks
from a pool of 30 of the same candidates. The simulated cell's operator (``fixtures/sim/socket.yaml``,
``SocketOperator.solve``: hidden kinematics, sag, 0.02 mm play) puts the ball into each socket
from every approach, and the socket fit with compliance gives its σ of the compliances A2–A4 and
of the offsets A2–A6. Prints the means over the seeds and the ratio spread/random (< 1: the
planner's choice determines them better).

Run: ``python tests/bench/bench_socket_poses.py [--seeds 4]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.fit.socket import SocketDataset, fit_socket, with_distance  # noqa: E402
from calib.plan.socket_poses import socket_approaches  # noqa: E402
from drivers.sim.cell import SimCell  # noqa: E402
from drivers.sim.socket_operator import SocketOperator  # noqa: E402


def dataset(kind: str, seed: int, cell: SimCell, op: SocketOperator, plan: dict, truth: dict) -> SocketDataset:
    rng = np.random.default_rng(seed)
    q, keys = [], []
    for i, pl in enumerate(plan["placements"]):
        for j, so in enumerate(pl["sockets"]):
            s = seed * 100 + 10 * i + j
            if kind == "spread":
                found = socket_approaches(cell.model, so["xyz_mm"], plan["ball_mm"], 6, seed=s)
            else:
                pool = socket_approaches(cell.model, so["xyz_mm"], plan["ball_mm"], 30, seed=s, candidates=48)
                found = [pool[k] for k in rng.choice(len(pool), 6, replace=False)]
            for a in found:
                target = truth[(pl["name"], so["name"])] + rng.normal(0, 0.02, 3)
                q.append(op.solve(a.q, target))
                keys.append((pl["name"], so["name"]))
    groups = sorted(set(keys))
    return SocketDataset(np.array(q), np.array([groups.index(k) for k in keys]), groups, with_distance(groups, 50.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args()
    cell = SimCell.from_yaml(ROOT / "fixtures" / "sim" / "socket.yaml")
    op = SocketOperator(cell, None)
    plan = yaml.safe_load((ROOT / "fixtures" / "plans" / "example-socket.yaml").read_text())["socket"]
    truth = {(p.placement, p.socket): np.array(p.xyz_mm) for p in cell.config.sockets.points}
    out = {}
    for kind in ("spread", "random"):
        comp, off = [], []
        for seed in range(args.seeds):
            fit = fit_socket(cell.model, dataset(kind, seed, cell, op, plan, truth), compliance=True)
            comp.append(fit.compliance_std[1:4] * 1e6)
            off.append(np.degrees(fit.std[1:6]))
        out[kind] = (np.nanmean(comp, axis=0), np.nanmean(off, axis=0))
        print(f"{kind:>6}: σ compliance A2–A4 {np.round(out[kind][0], 2)} µrad/(N·m); "
              f"σ offset A2–A6 {np.round(out[kind][1], 4)}°")
    print(f"ratio spread/random: compliance {np.round(out['spread'][0] / out['random'][0], 2)}, "
          f"offsets {np.round(out['spread'][1] / out['random'][1], 2)}")


if __name__ == "__main__":
    main()
