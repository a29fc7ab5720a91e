"""Study (issue 35): adaptive runs stopped on the operator's terms, against the full plan, over
simulated cells, scored against each cell's truth.

Each cell (``--cells``, seed k): the KUKA iiwa 14 with one motion-capture marker in the example
plan's region (``--poses`` candidate poses, every IK branch: 20 → 40 configurations, the packaged
example; 40 → 80+), a true arm with link errors (0.2 mm, 0.02°, 1σ), the tool marker 1 mm per axis
off its drawing (not declared), joint sag under gravity and hidden zero-offsets N(0, 0.05°). Each
configuration is the mean of the plan's ``samples`` readings, each with ``--noise`` mm per axis
(a list cycles over the cells), written as the run writes it (mean, spread, count): the run's σ
is what it measures. The adaptive run is the run's own loop (``acquire.run.adaptive.AdaptiveRun``)
with the plan's rule; the full plan measures every configuration (the adaptive run's readings and
the rest).

Scored per cell, adaptive and full plan:
* configurations and cell time (the run's estimate: moves, settling, measuring; the seconds the
  robot stood while the run chose are printed apart — a run computes its choices ahead);
* the three errors: the largest 95 % half-width of the determinable offsets (Laplace fit of the
  plan's model), the noise-free model error at new poses of the plan's region (20 poses of the
  same generator, another seed, every branch) and over the working joint space (``--js`` uniform
  configurations within the limits less the margin, another seed than the design's) — the fitted
  model (posterior mode) against the true positions, through the fit's registration;
* coverage: how often each determinable offset's 95 % interval holds the truth;
* predicted at the stop against found.

    nice python3 tests/bench/study_adaptive_cells.py --cells 8                  # the example plan
    nice python3 tests/bench/study_adaptive_cells.py --cells 8 --poses 40       # 80+ configurations
    nice python3 tests/bench/study_adaptive_cells.py --cells 8 --joint-space-pct 30
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "bench")]

from acquire.plan.schema import load_plan, resolve_configurations  # noqa: E402
from acquire.run import SENSOR_RATE_HZ, plan_settings  # noqa: E402
from acquire.run.adaptive import AdaptiveRun, fit_options, joint_space_samples  # noqa: E402
from acquire.run.sequencer import estimate_measure_s, estimate_settle_s, move_times, order_configurations  # noqa: E402
from calib.fit.offsets import fit_mode, fit_offsets  # noqa: E402
from drivers.protocols import JointLimits  # noqa: E402
from study_adaptive import Cell, Standing, dataset  # noqa: E402


def plan_file(folder: Path, poses: int, stop: dict, seed: int = 1, min_configurations: int | None = None) -> Path:
    doc = yaml.safe_load((ROOT / "fixtures/plans/example.yaml").read_text())
    doc["sensors"][0]["markers"] = {"sir": "ms:tool:sir"}
    doc["robot"] = str(ROOT / "fixtures/robots/kuka_iiwa14_r820.yaml")
    doc["fake"]["sim_config"] = str(ROOT / "fixtures/sim/default.yaml")
    doc["poses"]["generated"].update(n=poses, seed=seed)
    doc["output"]["folder"] = str(folder)
    doc["adaptive"] = {"stop_when": stop, "min_configurations": min_configurations}
    path = folder / f"plan{seed}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class ReadingCell(Cell):
    """``Cell`` read as the run reads a sensor: ``samples`` readings of ``noise`` mm per axis each,
    their mean, spread (ddof 1) and count."""

    def __init__(self, model, seed: int, noise_mm: float, samples: int) -> None:
        super().__init__(model, seed, 0.0, "sir")
        self.per_reading, self.samples = noise_mm, samples

    def read(self, q: np.ndarray) -> dict:
        true = self.observe(np.asarray(q)[None, :], noise=False)[0]
        reads = true + self.rng.normal(0, self.per_reading, (self.samples, 3))
        return {"sensor": "mocap", "marker": "sir", "mean_mm": reads.mean(axis=0).tolist(),
                "std_mm": reads.std(axis=0, ddof=1).tolist(), "count": self.samples}


def scores(lp, cell, q, xyz, ids, opts, determinable, region_q, js_q, coverage: bool) -> dict:
    """The fit of the given configurations against the cell's truth: the largest 95 % half-width
    (deg) and coverage over the determinable offsets, and the noise-free model error (rms 3-D, mm)
    at ``region_q`` and ``js_q``."""
    data = dataset(q, xyz, ids, "sir")
    mf = fit_mode(lp.model, data, opts)
    out = {}
    for key, qs in (("region", region_q), ("joint_space", js_q)):
        names = [f"{key}{i}" for i in range(len(qs))]
        res = mf.predict_residuals(dataset(qs, cell.observe(qs, noise=False), names, "sir"))
        out[key] = float(np.sqrt(np.mean(np.sum(res**2, axis=-1))))
    out["half"], out["hits"], out["trials"] = float("nan"), 0, 0
    if coverage:
        fit = fit_offsets(lp.model, data, opts)
        half = []
        for i, name in enumerate(lp.model.axis_names):
            if f"{name}.offset" in determinable and fit.identifiable()[i]:
                lo, hi = fit.offsets_ci95_rad[i]
                half.append(math.degrees(hi - lo) / 2)
                out["trials"] += 1
                out["hits"] += bool(lo <= cell.offsets[i] <= hi)
        out["half"] = max(half) if half else float("nan")
    return out


def joint_space_bound(order, ratio: float = 1.3) -> int:
    """The fewest configurations after which the linear model predicts the working-joint-space
    error within ``ratio`` × the full plan's, choosing greedily by that gain alone (no travel),
    at the plan's σ per configuration: a lower bound on what any order of the plan needs."""
    from calib.plan.adaptive import _inv_sym

    d = order.design
    full = d.full_joint_space_mm()
    chosen, info = [], d.model.prior.copy()
    while len(chosen) < d.model.n_plan:
        cov = _inv_sym(info)
        if d.joint_space_uncertainty_mm(cov) <= ratio * full:
            break
        left = np.array([i for i in range(d.model.n_plan) if i not in chosen])
        g = d.gains(left, cov=cov, criteria=["joint_space_error_mm"])["joint_space"]
        k = int(left[int(np.argmax(g))])
        chosen.append(k)
        info = info + d._blocks[k] / d.sigma_mm**2
    return len(chosen)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cells", type=int, default=8)
    ap.add_argument("--poses", type=int, default=20, help="candidate poses (every IK branch): 20 → 40 configurations")
    ap.add_argument("--noise", type=str, default="0.03", help="mm per axis per reading, a comma list cycles over the cells")
    ap.add_argument("--interval", type=float, default=0.01, help="stop_when.interval_deg")
    ap.add_argument("--region", type=float, default=0.05, help="stop_when.region_error_mm")
    ap.add_argument("--joint-space-mm", type=float, default=None, help="stop_when.joint_space_error_mm")
    ap.add_argument("--joint-space-pct", type=float, default=None, help="stop_when.joint_space_within_pct")
    ap.add_argument("--min", type=int, default=None, help="adaptive.min_configurations [null: the plan's default]")
    ap.add_argument("--js", type=int, default=100, help="joint-space configurations the errors are scored on")
    ap.add_argument("--no-coverage", action="store_true", help="skip the Laplace fits (half-widths, coverage)")
    args = ap.parse_args()
    t0 = time.process_time()
    noises = [float(x) for x in args.noise.split(",")]
    stop = {k: v for k, v in (("interval_deg", args.interval), ("region_error_mm", args.region),
                              ("joint_space_error_mm", args.joint_space_mm),
                              ("joint_space_within_pct", args.joint_space_pct)) if v is not None}
    with tempfile.TemporaryDirectory() as tmp:
        lp = load_plan(plan_file(Path(tmp), args.poses, stop, min_configurations=args.min))
        configs = resolve_configurations(lp)
        region = resolve_configurations(load_plan(plan_file(Path(tmp), 20, stop, seed=77)))
    region_q = np.stack([c.q_rad for c in region])
    js_q = joint_space_samples(lp, seed=4242, n=args.js)
    s = plan_settings(lp.plan)
    limits = JointLimits.from_model(lp.model)
    per_config = estimate_settle_s(s.settle_window_s) + estimate_measure_s(s.samples, [SENSOR_RATE_HZ["natnet"]])
    start = np.zeros(lp.model.n_joints)
    t_full = float(move_times(order_configurations(configs, start, limits, s.speed), start, limits, s.speed).sum()
                   + len(configs) * per_config)
    opts = fit_options(lp)
    print(f"plan: {len(configs)} configurations ({args.poses} poses), full plan {t_full:.0f} s; rule {stop}, "
          f"min_configurations {args.min or 'default'}; {s.samples} readings per configuration; scored on "
          f"{len(region)} new configurations of the region and {len(js_q)} of the working joint space", flush=True)
    rows = []
    for k in range(args.cells):
        noise = noises[k % len(noises)]
        cell = ReadingCell(lp.model, k, noise, s.samples)
        robot = Standing(limits)
        run = AdaptiveRun(lp, configs, robot, s.speed, per_config, None, set(), start)
        if k == 0:  # (the design still at the plan's σ)
            print(f"linear bound: no order of this plan predicts the working-joint-space error within 1.3× the full "
                  f"plan's before {joint_space_bound(run.order)} configurations (of {len(configs)}; σ the plan's)",
                  flush=True)
        seen = {}
        for cfg in run.choices(lambda kind, **f: None):
            mk = cell.read(cfg.q_rad)
            seen[cfg.config_id] = (cfg.q_rad, np.array(mk["mean_mm"]))
            robot.q = np.asarray(cfg.q_rad, dtype=float)
            run.outcome(cfg, "measured", {"config_id": cfg.config_id, "markers": [mk],
                                          "q_measured_deg": np.degrees(cfg.q_rad).tolist()})
        summ = run.summary()
        determinable = set(summ["half_width_deg"])
        ids = list(seen)
        ad = scores(lp, cell, [seen[i][0] for i in ids], [seen[i][1] for i in ids], ids, opts, determinable,
                    region_q, js_q, not args.no_coverage)
        xyz_all = [seen[c.config_id][1] if c.config_id in seen else np.array(cell.read(c.q_rad)["mean_mm"])
                   for c in configs]
        fu = scores(lp, cell, [c.q_rad for c in configs], xyz_all, [c.config_id for c in configs], opts, determinable,
                    region_q, js_q, not args.no_coverage)
        p = summ["decision"]["predicted"]
        moving = summ["estimated_seconds"] - summ["compute_seconds"]
        row = dict(cell=k, noise=noise, n=len(ids), t=moving, choose=summ["compute_seconds"], reason=summ["reason"],
                   ad=ad, fu=fu, p=p, sigma=summ["decision"]["noise"]["used_mm"],
                   misfit=summ["decision"]["noise"]["misfit_mm"])
        rows.append(row)
        print(f"cell {k} ({noise:g} mm/reading): adaptive {len(ids)} of {len(configs)}, {moving:.0f} s = "
              f"{moving / t_full:.0%} (+{summ['compute_seconds']:.1f} s choosing); σ {row['sigma']:.4f}, misfit "
              f"{row['misfit']:.4f} mm | half-width pred/found {p['max_half_width_deg']:.4f}/{ad['half']:.4f}° "
              f"(full {p['full_max_half_width_deg']:.4f}/{fu['half']:.4f}) | region pred/found {p['region_mm']:.4f}/"
              f"{ad['region']:.4f} mm (full {p['full_region_mm']:.4f}/{fu['region']:.4f}) | joint space pred/found "
              f"{p['joint_space_mm']:.4f}/{ad['joint_space']:.4f} mm (full {p['full_joint_space_mm']:.4f}/"
              f"{fu['joint_space']:.4f}) | cover {ad['hits']}/{ad['trials']} (full {fu['hits']}/{fu['trials']})",
              flush=True)
    print()
    print("| cell (noise per reading) | configurations | cell time: adaptive / full plan | largest 95 % half-width "
          "predicted / found, adaptive (full) | model error, plan's region, predicted / found, adaptive (full) | "
          "model error, working joint space, predicted / found, adaptive (full) | coverage adaptive / full |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        a, f, p = r["ad"], r["fu"], r["p"]
        print(f"| {r['cell']} ({r['noise']:g} mm) | {r['n']} of {len(configs)} | {r['t']:.0f} s = {r['t'] / t_full:.0%} "
              f"/ {t_full:.0f} s | {p['max_half_width_deg']:.4f} / {a['half']:.4f}° ({p['full_max_half_width_deg']:.4f} / "
              f"{f['half']:.4f}°) | {p['region_mm']:.4f} / {a['region']:.4f} mm ({p['full_region_mm']:.4f} / "
              f"{f['region']:.4f}) | {p['joint_space_mm']:.4f} / {a['joint_space']:.4f} mm ({p['full_joint_space_mm']:.4f}"
              f" / {f['joint_space']:.4f}) | {a['hits']}/{a['trials']} / {f['hits']}/{f['trials']} |")
    med = lambda key, which: float(np.median([r[which][key] for r in rows]))  # noqa: E731
    cov_a = sum(r["ad"]["hits"] for r in rows) / max(1, sum(r["ad"]["trials"] for r in rows))
    cov_f = sum(r["fu"]["hits"] for r in rows) / max(1, sum(r["fu"]["trials"] for r in rows))
    share = float(np.median([r["t"] / t_full for r in rows]))
    js_ratio = float(np.median([r["ad"]["joint_space"] / r["fu"]["joint_space"] for r in rows]))
    worst_half = max(r["ad"]["half"] for r in rows)
    print()
    print(f"median over {len(rows)} cells: {np.median([r['n'] for r in rows]):.0f} configurations, cell time "
          f"{share:.0%} of the full plan's ({t_full:.0f} s; +{np.mean([r['choose'] for r in rows]):.1f} s choosing, "
          f"mean); model error, plan's region {med('region', 'ad'):.4f} mm (full {med('region', 'fu'):.4f}); "
          f"working joint space {med('joint_space', 'ad'):.4f} mm (full {med('joint_space', 'fu'):.4f}), ratio "
          f"{js_ratio:.2f}; largest half-width found {worst_half:.4f}°; coverage {cov_a:.1%} (full {cov_f:.1%})")
    targets = {"every half-width ≤ 0.01°": worst_half <= 0.01, "coverage 90–97 %": 0.90 <= cov_a <= 0.97,
               "region ≤ 0.05 mm": med("region", "ad") <= 0.05, "joint space ≤ 1.3× full": js_ratio <= 1.3,
               "≤ 50 % of the full plan's time": share <= 0.5}
    print("targets: " + "; ".join(f"{k}: {'met' if v else 'NOT met'}" for k, v in targets.items()))
    print(f"CPU {time.process_time() - t0:.0f} s")


if __name__ == "__main__":
    main()
