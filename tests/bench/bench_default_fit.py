"""Benchmark: the default ``acquire fit`` against ``--method full`` on the same data, in one run (issue 33).

    python tests/bench/bench_default_fit.py [--tree /work/main] [--repeat 1] [--only NAME] [--keep DIR]

Each case is a CSV written from the data (real UR10 series B and D from
``../shared/fixtures/ur10-ipa-tracker-6dof/``, skipped when absent; the README's simulated iiwa),
fitted by the command line as a user runs it, ``python -m acquire fit DATA --robot MODEL`` (the
default) and ``… --method full``, in child processes of this one. CPU seconds are the child's
user + system time (``resource.getrusage(RUSAGE_CHILDREN)`` before and after), so the load of the
shared machine does not enter them; wall seconds and the load average are printed beside. The two
methods run alternately (default, full, default, full, …) ``--repeat`` times each, the same clock
and the same repetitions for both; the table prints the medians and the ratio default ÷ full
(issue 33's target: ≤ 3) and the default's peak resident memory (``ru_maxrss`` of the children:
the largest child so far, so the cases run largest last).

``--tree DIR`` runs the command line of another checkout; ``--before DIR`` adds that checkout's
default fit as a "before" column, run interleaved with this one's (``/work/main``: the speed-ups'
before and after at the same load); ``--keep DIR`` keeps the CSVs and each run's result.json there
(``before/`` and ``after/``: the answers' comparison, ``tests/bench/compare_fits.py``).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from calib.measure.dataset import from_arrays, write_csv  # noqa: E402

SHARED = ROOT.parent / "shared" / "fixtures" / "ur10-ipa-tracker-6dof"
SERIES = {"B": SHARED / "Series_B" / "measurements_joint_configurations.csv",
          "D": SHARED / "Series_D" / "measurements_iso_cubes.csv"}
UR10 = ROOT / "fixtures" / "robots" / "ur10.yaml"
IIWA = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"


def _subset(ds, n: int, seed: int = 0):
    """``n`` configurations of ``ds`` drawn at random (seeded), kept in file order."""
    pick = np.sort(np.random.default_rng(seed).permutation(len(ds))[:n])
    return ds.subset(pick)


def cases(out: Path) -> list[tuple[str, Path, Path]]:
    """(name, CSV, robot model) of every case whose data is here; the CSVs are written under ``out``."""
    from calib.measure.ipa_tracker import read_ipa_series

    found = [("iiwa14 README (sim, 173)", ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", IIWA)]
    for series, n, pose in (("B", 200, True), ("D", 200, True), ("D", 120, False)):
        if not SERIES[series].exists():
            print(f"skipped UR10 series {series}: {SERIES[series]} not found", file=sys.stderr)
            continue
        ds = _subset(read_ipa_series(SERIES[series]), n)
        if not pose:  # positions only, as a tracker without a T-Mac measures
            ds = from_arrays(ds.q_rad, ds.xyz_mm, marker=ds.marker, sensor=ds.sensor, config=ds.config,
                             std_mm=ds.std_mm, count=ds.count)
        path = out / f"ur10_{series}{n}_{'pose' if pose else 'positions'}.csv"
        write_csv(ds, path, comment=f"{n} configurations of UR10 series {series} (seed 0), bench_default_fit.py")
        found.append((f"UR10 {series}, {n} {'with attitude' if pose else 'positions only'}", path, UR10))
    return found


def run_fit(tree: Path, data: Path, robot: Path, method: str | None, result: Path | None) -> tuple[float, float, int, int]:
    """(CPU s, wall s, exit code, peak RSS kB so far of the children) of one ``acquire fit``."""
    cmd = [sys.executable, "-m", "acquire", "fit", str(data), "--robot", str(robot)]
    if method:
        cmd += ["--method", method]
    if result is not None:
        cmd += ["-o", str(result)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(tree)})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode not in (0, 1):  # 1: fitted, but "do not enter" — still a fit
        print(done.stderr[-2000:], file=sys.stderr)
    return cpu, wall, done.returncode, after.ru_maxrss


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", type=Path, default=ROOT, help="checkout whose `acquire fit` runs (default: this one)")
    ap.add_argument("--before", type=Path, default=None, help="another checkout's default fit, interleaved")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each method per case, alternating")
    ap.add_argument("--only", default=None, help="only the cases whose name contains this")
    ap.add_argument("--keep", type=Path, default=None, help="keep the CSVs and result.json files here")
    args = ap.parse_args()
    keep = args.keep
    # (label, tree, method) in the order they run, per repetition
    runs = ([("before", args.before, None)] if args.before else []) + [("after", args.tree, None), ("full", args.tree, "full")]
    with tempfile.TemporaryDirectory() as tmp:
        out = keep or Path(tmp)
        for label, _, _ in runs:
            (out / label).mkdir(parents=True, exist_ok=True)
        print(f"tree {args.tree}{f', before {args.before}' if args.before else ''}; {os.cpu_count()} cores; "
              f"load {os.getloadavg()[0]:.1f} at start; CPU s = the child's user + system time, median of {args.repeat}")
        head = f"{'case':<34}" + (f"{'before CPU s':>13}" if args.before else "") + f"{'CPU s':>8}{'full CPU s':>12}"
        head += (f"{'before ÷ full':>14}" if args.before else "") + f"{'÷ full':>8}{'wall s':>8}{'load':>6}{'exit':>6}"
        print(head)
        for name, data, robot in cases(out):
            if args.only and args.only not in name:
                continue
            times: dict[str, list[tuple[float, float]]] = {label: [] for label, _, _ in runs}
            codes = []
            for _ in range(args.repeat):
                for label, tree, method in runs:
                    res = out / label / f"{data.stem}.{method or 'default'}.json" if keep else None
                    cpu, wall, code, _ = run_fit(tree, data, robot, method, res)
                    times[label].append((cpu, wall))
                    if label == "after":
                        codes.append(code)
            med = {label: statistics.median(t[0] for t in v) for label, v in times.items()}
            wall = statistics.median(t[1] for t in times["after"])
            row = f"{name:<34}" + (f"{med['before']:>13.1f}" if args.before else "") + f"{med['after']:>8.1f}{med['full']:>12.1f}"
            row += (f"{med['before'] / med['full']:>14.1f}" if args.before else "")
            row += f"{med['after'] / med['full']:>8.1f}{wall:>8.1f}{os.getloadavg()[0]:>6.1f}{','.join(map(str, codes)):>6}"
            print(row, flush=True)
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        print(f"largest child's peak resident memory: {peak:.0f} MB")


if __name__ == "__main__":
    main()
