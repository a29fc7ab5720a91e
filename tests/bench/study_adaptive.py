"""Study (issue 27): an adaptive run against the full plan and the paper's procedure, over seeds.

Cells (``--cell``): the KUKA iiwa 14 with one motion-capture marker (``fixtures/plans/example.yaml``'s pose
generator, ``--poses`` candidate poses, every IK branch); per seed a true arm with link errors
(0.2 mm, 0.02°, 1σ), the tool marker 1 mm per axis off its drawing (not declared), joint sag
under gravity (the simulated cell's compliances) and hidden zero-offsets N(0, 0.05°); noise
``--noise`` mm per axis per configuration (the plan says 0.03). Or a Stäubli TX60 with a laser
tracker's SMR (0.02 mm), every IK branch of poses aimed at the tracker; the same link and tool
errors, no sag (its model has no link masses). The adaptive run is the run's own
loop (``acquire.run.adaptive.AdaptiveRun``: choose, measure, update σ, check the stop rule) with
each measurement drawn from the true arm instead of a device.

Scored per seed, for the adaptive selection and for the whole plan:
* cell time: estimated motion + settle + measure (the run's estimate; the same for all three),
  the full plan in the run's minimum-time order, the paper's procedure (poses by proximity, every
  branch in a row, a fixed 3 s wait per configuration);
* held-out accuracy: rms position error (mm) of further configurations the fit never saw (the
  same pose generator with another seed: 20 poses, every branch — the plan's workspace), predicted by the fitted model (offsets, tool, links, compliances at the posterior mode) through
  the fit's own registration;
* coverage: how often each determinable offset's 95 % interval (the Laplace fit with the plan's
  model) holds the hidden truth.

* predicted against found: the held-out error and the model's own error (the fit against the
  true positions, no sensor noise) the design predicts at the stop, for the adaptive selection
  and the full plan, against what the fits show on the held-out configurations; and the
  prediction over the held-out configurations' own workspace matrix. ``--in-sample`` predicts
  as the design did before the leave-one-out correction (the errors at the measured candidates).

The adaptive loop computes each choice ahead (``lookahead="inline"``): its seconds are not the
robot's, as in a run with its worker process. ``--no-coverage`` skips the Laplace fits.

    PYTHONPATH=$PWD python3 tests/bench/study_adaptive.py --seeds 20 --held-out 10
    PYTHONPATH=$PWD python3 tests/bench/study_adaptive.py --cell tx60 --poses 20 --seeds 20 --held-out 10
    PYTHONPATH=$PWD python3 tests/bench/study_adaptive.py --seeds 20 --held-out 10 --extra 200   # + a pool
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import yaml

from acquire.plan.schema import load_plan, resolve_candidate_pool, resolve_configurations
from acquire.run import SENSOR_RATE_HZ, plan_settings
from acquire.run.adaptive import AdaptiveRun, fit_options
from acquire.run.sequencer import (estimate_measure_s, estimate_settle_s, move_times, order_by_pose_proximity,
                               order_configurations)
from calib.fit.offsets import fit_mode, fit_offsets
from calib.plan.adaptive import SequentialDesign
from calib.measure.dataset import from_arrays
from calib.robot.gravity import gravity_torques
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from drivers.protocols import JointLimits

ROOT = Path(__file__).resolve().parents[2]
K_TRUE = np.array([6e-6] * 4 + [1.2e-5] * 3)  # rad/(N·m), as fixtures/sim/default.yaml
SENSOR = np.array([2000.0, 100.0, -300.0])


def plan_file(folder: Path, poses: int, within: float | None, interval: float | None, held_out: float | None,
              seed: int = 1, marker: str = "sir", noise_mm: float = 0.03, extra: int = 0) -> Path:
    doc = yaml.safe_load((ROOT / "fixtures/plans/example.yaml").read_text())
    doc["sensors"][0]["markers"] = {marker: f"ms:tool:{marker}"}
    doc["sensors"][0]["noise_mm"] = noise_mm
    doc["poses"]["generated"]["seed"] = seed
    doc["robot"] = str(ROOT / "fixtures/robots/kuka_iiwa14_r820.yaml")
    doc["fake"]["sim_config"] = str(ROOT / "fixtures/sim/default.yaml")
    doc["poses"]["generated"]["n"] = poses
    doc["output"]["folder"] = str(folder)
    stop = {k: v for k, v in (("workspace_within_pct", within), ("interval_deg", interval),
                              ("held_out_within_pct", held_out)) if v is not None}
    doc["adaptive"] = {"stop_when": stop}
    if extra:  # a generated pool beyond the plan: the plan's generator, seed + 1 (never the held-out's 77)
        doc["adaptive"]["candidates"] = {"extra_poses": extra}
    path = folder / f"plan{seed}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class Cell:
    """A true arm: link errors, the tool off its drawing, hidden offsets, sag; noisy marker positions."""

    def __init__(self, model, seed: int, noise_mm: float, marker: str) -> None:
        self.chain = Chain(model)
        rng = np.random.default_rng(500 + seed)
        p = self.chain.nominal.copy()
        c = self.chain
        p[c.index("d")] += rng.normal(0, 0.2, c.n)
        p[c.index("a")] += rng.normal(0, 0.2, c.n)
        p[c.index("alpha")] += np.radians(rng.normal(0, 0.02, c.n))
        ms = c.marker_slice()
        p[ms] += rng.normal(0, 1.0, ms.stop - ms.start)
        self.params = p
        self.offsets = np.radians(rng.normal(0, 0.05, c.n))
        self.rng, self.noise = rng, noise_mm
        self.marker = c.marker_names.index(marker)
        self.sag = model.has_dynamics

    def observe(self, q: np.ndarray, noise: bool = True) -> np.ndarray:
        """(k, 3) measured marker positions (mm, sensor frame) at commanded ``q`` (k, n); without
        ``noise`` the true positions (for the model's own error on held-out configurations)."""
        q = np.atleast_2d(q)
        q_true = q + self.offsets
        if self.sag:
            q_true = q_true + self.chain.sign * K_TRUE * gravity_torques(self.chain, q, self.params)
        pos = self.chain.marker_positions(q_true, self.params)[:, self.marker]
        return pos + SENSOR + (self.rng.normal(0, self.noise, pos.shape) if noise else 0.0)


def dataset(q, xyz, ids, marker):
    return from_arrays(np.asarray(q), np.asarray(xyz), marker=marker, sensor="mocap", config=np.asarray(ids))


def score(lp, cell, q, xyz, ids, q_val, xyz_val, opts, marker, xyz_true=None, coverage=True):
    """(held-out rms mm, coverage hits, coverage trials, the model's own held-out rms error mm —
    against the true positions ``xyz_true``, no sensor noise — or nan) of a fit on the given
    configurations."""
    cal = dataset(q, xyz, ids, marker)
    mf = fit_mode(lp.model, cal, opts)
    names = [f"v{i}" for i in range(len(q_val))]
    res = mf.predict_residuals(dataset(q_val, xyz_val, names, marker))
    held = float(np.sqrt(np.mean(np.sum(res**2, axis=-1))))
    model = float("nan")
    if xyz_true is not None:
        res0 = mf.predict_residuals(dataset(q_val, xyz_true, names, marker))
        model = float(np.sqrt(np.mean(np.sum(res0**2, axis=-1))))
    hits = trials = 0
    if not coverage:
        return held, 0, 0, model
    try:
        fit = fit_offsets(lp.model, cal, opts)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        print(f"  (no Laplace fit: {exc})")
        return held, 0, 0, model
    for i in np.flatnonzero(fit.identifiable()):
        lo, hi = fit.offsets_ci95_rad[i]
        trials += 1
        hits += bool(lo <= cell.offsets[i] <= hi)
    return held, hits, trials, model


def tx60_configs(model, poses: int, seed: int, prefix: str = "p"):
    """Every IK branch of ``poses`` Latin-hypercube poses aimed at a tracker 1.8 m away (ids
    ``<prefix>07-b1``; prefix "x" for a generated pool, as ``acquire.plan.schema.resolve_candidate_pool``)."""
    from acquire.plan.schema import PlannedConfig
    from calib.plan.poses import plan_poses

    pp = plan_poses(model, (1800.0, 0.0, 600.0), n=poses, seed=seed, min_solutions=2)
    within: dict[int, int] = {}
    out = []
    for c in pp.configurations:
        b = within[c.pose] = within.get(c.pose, -1) + 1
        out.append(PlannedConfig(f"{prefix}{c.pose:02d}-b{b}", f"{prefix}{c.pose:02d}", c.branch,
                                 np.asarray(c.q, dtype=float)))
    return out


class Standing:
    def __init__(self, limits):
        self.limits, self.q = limits, None

    def joint_state(self):
        from drivers.errors import DeviceTimeoutError

        if self.q is None:
            raise DeviceTimeoutError("no state")
        return SimpleNamespace(position_rad=self.q)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--poses", type=int, default=60, help="candidate poses of the plan (every IK branch of each)")
    ap.add_argument("--within", type=float, default=None, help="stop_when.workspace_within_pct")
    ap.add_argument("--held-out", type=float, default=5.0, help="stop_when.held_out_within_pct")
    ap.add_argument("--interval", type=float, default=None, help="stop_when.interval_deg")
    ap.add_argument("--noise", type=float, default=None, help="mm per axis per configuration [iiwa 0.03, tx60 0.02]")
    ap.add_argument("--extra", type=int, default=0, help="adaptive.candidates.extra_poses: a generated pool the "
                                                         "design may choose from (the full plan stays the plan's)")
    ap.add_argument("--cell", choices=("iiwa", "tx60"), default="iiwa",
                    help="iiwa: motion capture (marker sir), sag; tx60: laser tracker (SMR), no link masses")
    ap.add_argument("--no-coverage", action="store_true", help="skip the Laplace fits (coverage): faster")
    ap.add_argument("--in-sample", action="store_true",
                    help="predict the errors on the measured candidates themselves (the design before the "
                         "leave-one-out correction), for comparison")
    args = ap.parse_args()
    t0 = time.process_time()
    marker = "sir" if args.cell == "iiwa" else "smr"
    noise = args.noise if args.noise is not None else (0.03 if args.cell == "iiwa" else 0.02)
    args.noise = noise
    with tempfile.TemporaryDirectory() as tmp:
        lp = load_plan(plan_file(Path(tmp), args.poses, args.within, args.interval, args.held_out, marker=marker,
                                 noise_mm=noise, extra=args.extra))
        if args.cell == "iiwa":
            configs, pool = resolve_configurations(lp), resolve_candidate_pool(lp)
            # held out: the same workspace, other poses (the generator with another seed)
            held_out = resolve_configurations(load_plan(plan_file(Path(tmp), 20, args.within, args.interval,
                                                                  args.held_out, seed=77)))
        else:  # the plan's sections on a TX60 (no plan can name its CS8 commander yet): poses aimed at a tracker
            lp = replace(lp, model=load_robot_model(ROOT / "fixtures/robots/staubli_tx60.yaml"))
            configs, held_out = tx60_configs(lp.model, args.poses, 3), tx60_configs(lp.model, 20, 77)
            pool = tx60_configs(lp.model, args.extra, 4, prefix="x") if args.extra else []
    s = plan_settings(lp.plan)
    limits = JointLimits.from_model(lp.model)
    settle, measure = estimate_settle_s(s.settle_window_s), estimate_measure_s(s.samples, [SENSOR_RATE_HZ["natnet"]])
    per_config = settle + measure
    start = np.zeros(lp.model.n_joints)
    full_order = order_configurations(configs, start, limits, s.speed)
    t_full = float(move_times(full_order, start, limits, s.speed).sum() + len(configs) * per_config)
    paper = order_by_pose_proximity(configs, start, Chain(lp.model))
    t_paper = float(move_times(paper, start, limits, s.speed).sum() + len(configs) * (3.0 + measure))
    opts = fit_options(lp)
    # the held-out configurations' own workspace matrix: the prediction over them, not the plan's
    from calib.fit.design import design_model

    held_design = design_model(lp.model, np.stack([c.q_rad for c in held_out]), {"mocap": [marker]}, opts)
    print(f"plan: {len(configs)} configurations ({args.poses} candidate poses) + {len(pool)} generated "
          f"({args.extra} poses); stop rule {lp.plan.adaptive.stop_when}")
    print(f"cell time: full plan {t_full:.0f} s (run order), paper's procedure {t_paper:.0f} s")
    rows = []
    for seed in range(args.seeds):
        cell = Cell(lp.model, seed, args.noise, marker)
        robot = Standing(limits)
        # the choice computed while the robot moves (in the caller here: the seconds it takes are
        # not the robot's, as in a run with its worker process)
        run = AdaptiveRun(lp, configs, robot, s.speed, per_config, None, set(), start, pool, lookahead="inline")
        if args.in_sample:
            d0 = run.order.design
            run.order.design = SequentialDesign(replace(d0.model, workspace_from_candidates=False), d0.rule,
                                                d0.sigma_mm)
        seen = {}
        for cfg in run.choices(lambda kind, **f: None):
            xyz = cell.observe(cfg.q_rad)[0]
            seen[cfg.config_id] = (cfg.q_rad, xyz)
            rec = {"config_id": cfg.config_id, "q_measured_deg": np.degrees(cfg.q_rad).tolist(),
                   "markers": [{"sensor": "mocap", "marker": marker, "mean_mm": xyz.tolist()}]}
            robot.q = np.asarray(cfg.q_rad, dtype=float)
            run.outcome(cfg, "measured", rec)
        summ = run.summary()
        dsg = run.order.design
        assert held_design.names == dsg.model.names
        a_held = held_design.workspace
        w_a_held = math.sqrt(float(np.sum(a_held * dsg.covariance())))
        w_f_held = math.sqrt(float(np.sum(a_held * dsg.covariance(range(len(configs))))))
        ratio_held = dsg.held_out_mm(w_a_held) / dsg.held_out_mm(w_f_held)
        w_a_new = dsg.new_pose_workspace_mm(dsg.measured)
        w_f_new = dsg.new_pose_workspace_mm(range(len(configs)))
        q_val = np.stack([c.q_rad for c in held_out])
        xyz_val = cell.observe(q_val)
        xyz_true = cell.observe(q_val, noise=False)
        cov = not args.no_coverage
        ids = list(seen)
        ad = score(lp, cell, [seen[i][0] for i in ids], [seen[i][1] for i in ids], ids, q_val, xyz_val, opts, marker,
                   xyz_true, cov)
        # the full plan: the adaptive run's measurements plus the rest, measured now
        q_all = np.stack([c.q_rad for c in configs])
        xyz_all = np.stack([seen[c.config_id][1] if c.config_id in seen else cell.observe(c.q_rad)[0] for c in configs])
        fu = score(lp, cell, q_all, xyz_all, [c.config_id for c in configs], q_val, xyz_val, opts, marker,
                   xyz_true, cov)
        # baseline: as many configurations, the first of the full plan's minimum-time tour (no design)
        pos = {c.config_id: k for k, c in enumerate(configs)}
        prefix = full_order[: len(ids)]
        t_prefix = float(move_times(prefix, start, limits, s.speed).sum() + len(prefix) * per_config)
        pre = score(lp, cell, [c.q_rad for c in prefix], [xyz_all[pos[c.config_id]] for c in prefix],
                    [c.config_id for c in prefix], q_val, xyz_val, opts, marker, coverage=cov)
        rows.append((seed, len(ids), summ["estimated_seconds"], ad, fu, summ["reason"], pre, t_prefix,
                     summ["held_out_mm"] / summ["full_held_out_mm"], summ.get("compute_seconds", 0.0),
                     (summ["held_out_mm"], summ["full_held_out_mm"], summ["workspace_mm"], summ["full_workspace_mm"],
                      summ["sigma_mm"], ratio_held, w_a_held, w_f_held, w_a_new, w_f_new),
                     summ.get("generated_measured", 0)))
        print(f"seed {seed:2d}: adaptive {len(ids):3d} configs ({summ.get('generated_measured', 0)} generated) "
              f"{summ['estimated_seconds']:6.0f} s "
              f"({summ['estimated_seconds'] / t_full:5.1%} of the full plan) held-out {ad[0]:.4f} mm "
              f"cover {ad[1]}/{ad[2]} | full {len(configs)} held-out {fu[0]:.4f} mm cover {fu[1]}/{fu[2]} | "
              f"tour prefix {t_prefix:.0f} s held-out {pre[0]:.4f} mm", flush=True)
        print(f"         predicted / found: held-out adaptive {summ['held_out_mm']:.4f} / {ad[0]:.4f}, full "
              f"{summ['full_held_out_mm']:.4f} / {fu[0]:.4f} mm; model error adaptive {summ['workspace_mm']:.4f} / "
              f"{ad[3]:.4f}, full {summ['full_workspace_mm']:.4f} / {fu[3]:.4f} mm", flush=True)
    n = np.array([r[1] for r in rows])
    t = np.array([r[2] for r in rows])
    ha = np.array([r[3][0] for r in rows])
    hf = np.array([r[4][0] for r in rows])
    d = ha - hf
    se = lambda x: float(np.std(x, ddof=1) / math.sqrt(len(x))) if len(x) > 1 else float("nan")  # noqa: E731
    cov_a = sum(r[3][1] for r in rows) / max(1, sum(r[3][2] for r in rows))
    cov_f = sum(r[4][1] for r in rows) / max(1, sum(r[4][2] for r in rows))
    print()
    print(f"{len(rows)} seeds; plan {len(configs)} configurations, full plan {t_full:.0f} s, paper's procedure {t_paper:.0f} s")
    gen = np.array([r[11] for r in rows])
    print(f"adaptive: {n.mean():.1f} configurations (min {n.min()}, max {n.max()}; {gen.mean():.1f} generated), cell time {t.mean():.0f} s = "
          f"{t.mean() / t_full:.1%} of the full plan, {t.mean() / t_paper:.1%} of the paper's procedure")
    print(f"held-out rms: adaptive {ha.mean():.4f} ± {se(ha):.4f} mm, full plan {hf.mean():.4f} ± {se(hf):.4f} mm; "
          f"paired difference {d.mean():+.4f} ± {se(d):.4f} mm")
    hp = np.array([r[6][0] for r in rows])
    tp = np.array([r[7] for r in rows])
    print(f"baseline, the full plan's tour cut at as many configurations: {tp.mean():.0f} s, held-out "
          f"{hp.mean():.4f} ± {se(hp):.4f} mm")
    pr = np.array([r[8] for r in rows])
    comp = np.array([r[9] for r in rows])
    print(f"held-out ratio adaptive / full: predicted at the stop {pr.mean():.3f}, found {np.mean(ha / hf):.3f} "
          f"± {se(ha / hf):.3f}; choosing and refitting {comp.mean():.1f} s of the cell time (wall, this machine)")
    print(f"cell time less the choosing (moves, settling, measuring): {t.mean() - comp.mean():.0f} s = "
          f"{(t.mean() - comp.mean()) / t_full:.1%} of the full plan")
    pa, pf, wa, wf, sg, rh, wah, wfh, wan, wfn = (np.array([r[10][k] for r in rows]) for k in range(10))
    ma, mfu = np.array([r[3][3] for r in rows]), np.array([r[4][3] for r in rows])
    print(f"predicted / found, mean over seeds: held-out adaptive {pa.mean():.4f} / {ha.mean():.4f} ± {se(ha):.4f} mm "
          f"(found/predicted {np.mean(ha / pa):.3f} ± {se(ha / pa):.3f}), full {pf.mean():.4f} / {hf.mean():.4f} ± "
          f"{se(hf):.4f} mm ({np.mean(hf / pf):.3f} ± {se(hf / pf):.3f}); σ used {sg.mean():.4f} mm")
    print(f"model's own error (no sensor noise), rms predicted / found: adaptive {math.sqrt(np.mean(wa**2)):.4f} / "
          f"{math.sqrt(np.mean(ma**2)):.4f} mm (mean square found/predicted {np.mean(ma**2) / np.mean(wa**2):.2f}), "
          f"full {math.sqrt(np.mean(wf**2)):.4f} / {math.sqrt(np.mean(mfu**2)):.4f} mm "
          f"({np.mean(mfu**2) / np.mean(wf**2):.2f}); over the held-out configurations' own workspace: predicted "
          f"adaptive {math.sqrt(np.mean(wah**2)):.4f}, full {math.sqrt(np.mean(wfh**2)):.4f} mm, ratio {rh.mean():.3f}; "
          f"new poses (leave-one-out over the plan's): adaptive {math.sqrt(np.mean(wan**2)):.4f}, full "
          f"{math.sqrt(np.mean(wfn**2)):.4f} mm, ratio "
          f"{np.mean(np.sqrt((3 * sg**2 + wan**2) / (3 * sg**2 + wfn**2))):.3f}")
    print(f"target (held-out within its standard error, ≤ 40 % of the full plan's time): "
          f"{'met' if d.mean() <= max(se(hf), se(d)) and t.mean() <= 0.4 * t_full else 'not met'}")
    print(f"coverage of the determinable offsets' 95 % intervals: adaptive {cov_a:.1%} "
          f"({sum(r[3][2] for r in rows)} intervals), full plan {cov_f:.1%} ({sum(r[4][2] for r in rows)})")
    print(f"CPU {time.process_time() - t0:.0f} s")


if __name__ == "__main__":
    main()
