"""``acquire fit … --report`` as a whole process against the fit itself, measured in the same run.

    python tests/bench/bench_fit_process.py [--repeat 3] [--repo PATH]

``--repo`` measures another checkout (e.g. the main branch, for a before/after) with this script.

Whole process: a fresh ``python -m acquire fit DATA --robot MODEL --validate VAL -o result.json
--report report.html`` (interpreter start-up, imports, reading, fit, metrics, report with its
figures, writing) — wall time. The fit itself: ``calib.fit.offsets.fit_offsets`` with the command's
default options on the same calibration rows, in this process after a warm-up — wall time.
Both are medians of ``--repeat`` runs, interleaved (process, fit, process, …) so a load change
hits both alike. Prints both, their ratio (issue 16's target: ≤ 2×), and where the rest of the
process goes (a fresh interpreter importing ``COMMAND_IMPORTS``, metrics and report in this
process), plus the load.
Data: fixtures/datasets/iiwa14_sim_{cal,val}.csv and the LBR iiwa 14 model of fixtures/robots.

The child processes inherit this environment: with ``PYTHONDONTWRITEBYTECODE`` set (and no
``PYTHONPYCACHEPREFIX``) every start compiles the checkout's own modules again, which an installed
wheel never does (pip writes their bytecode at install time); the first line says which.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: What the command imports before it reads anything: the CLI, the command and the modules the
#: command imports when it runs (the report's own modules are counted with the report).
COMMAND_IMPORTS = ["acquire.cli", "acquire.commands.fit", "calib.robot.controller", "calib.measure.dataset", "calib.fit.offsets",
                   "calib.fit.metrics", "calib.robot.model", "calib.fit.result"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--repo", type=Path, default=ROOT, help="checkout to measure (default: this one)")
    args = ap.parse_args()
    root = args.repo.resolve()
    sys.path.insert(0, str(root))
    data, val_path = root / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", root / "fixtures" / "datasets" / "iiwa14_sim_val.csv"
    robot = root / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"
    env = dict(os.environ, PYTHONPATH=str(root))

    from acquire.commands.fit import _link_tolerance
    from acquire.record.datasets import load_dataset
    from calib.fit.offsets import FitOptions, fit_offsets
    from calib.robot.kinematics import Chain
    from calib.fit.metrics import accuracy_metrics
    from calib.robot.model import load_robot_model
    from calib.fit.result import result_dict

    model = load_robot_model(robot)
    cal = load_dataset(data, model).calibration()
    val = load_dataset(val_path, model)
    options = FitOptions(link_tolerance=_link_tolerance("0.2,0.02"), paper_burn_in=200_000 - 25_000)

    def fit_once() -> tuple[float, object]:
        t0 = time.perf_counter()
        res = fit_offsets(model, cal, options)
        return time.perf_counter() - t0, res

    fit_once()  # warm-up: first-call caches, page faults
    proc_t, fit_t = [], []
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "acquire", "fit", str(data), "--robot", str(robot), "--validate", str(val_path),
               "-o", str(Path(tmp) / "r.json"), "--report", str(Path(tmp) / "r.html")]
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            done = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True)
            proc_t.append(time.perf_counter() - t0)
            if done.returncode != 0:
                sys.exit(f"acquire fit failed ({done.returncode}):\n{done.stderr[-2000:]}")
            fit_t.append(fit_once()[0])
        imp = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", "import " + ", ".join(COMMAND_IMPORTS)], cwd=tmp, env=env, check=True)
            imp.append(time.perf_counter() - t0)
        _, res = fit_once()
        t0 = time.perf_counter()
        metrics = accuracy_metrics(Chain(model), cal, res.applied_offsets_rad, res.offset_samples_rad, res.applied_sigma_mm,
                                   validation=val, n_random=1000, seed=0)
        t_metrics = time.perf_counter() - t0
        from calib.report.html import write_report

        doc = result_dict(res, cal, metrics=metrics)
        t0 = time.perf_counter()
        write_report(Path(tmp) / "again.html", res, cal, doc)
        t_report = time.perf_counter() - t0  # first report of this process: imports the report's modules
        t0 = time.perf_counter()
        write_report(Path(tmp) / "again.html", res, cal, doc)
        t_report_warm = time.perf_counter() - t0

    p, f = statistics.median(proc_t), statistics.median(fit_t)
    print(f"checkout {root}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; {len(cal)} measurements, {model.name}; "
          f"medians of {args.repeat}; bytecode cache {'off: own modules compiled at each start' if sys.dont_write_bytecode and not sys.pycache_prefix else 'on'}")
    print(f"  acquire fit … --report, whole process: {p:7.3f} s   (runs {', '.join(f'{t:.2f}' for t in proc_t)})")
    print(f"  fit_offsets in process (the fit):      {f:7.3f} s   (runs {', '.join(f'{t:.2f}' for t in fit_t)})")
    print(f"  ratio process / fit: {p / f:.2f}x  (target <= 2x)")
    print(f"  where the rest goes: fresh interpreter + the command's imports {statistics.median(imp):.3f} s, "
          f"metrics {t_metrics:.3f} s, report {t_report:.3f} s cold (its imports included) / {t_report_warm:.3f} s warm")


if __name__ == "__main__":
    main()
