"""Cell time of the paper's plan: our ordering + settle detection against the paper's procedure,
and a laser-tracker run with beam breaks against the motion-capture run.

    python tests/bench/bench_run.py

Everything is in SIMULATED CELL TIME, computed (not run) from the same pieces the run uses:

- motion: ``drivers.trajectory.motion_time`` of every move in the sequence, under the plan's
  speed override — exactly the trajectories the commanders stream;
- settle (ours): the fake Sunrise's joint servo (second order, 6 Hz, ζ 0.7, as
  ``drivers.kuka_fri.fake``) integrated along every trajectory; the robot window of
  ``CommanderBase.wait_settled`` (restarts whenever an axis leaves the tolerance of the window's
  first reading, polled every 4 ms) is found on that response; the sensor window runs at the
  same time (``acquire.run.settle.wait_settled``) and is not restarted by noise of the plan's size;
- settle (paper): a fixed 3 s after the move ("settling time … set to 3 sec");
- measure: ``samples`` at the sensor's rate (Motive 120 Hz, tracker averaging 1000 Hz);
- beam breaks: the simulated cell's line-of-sight test (``SimCell.visibility``) along every
  trajectory, sampled every 20 ms; a break costs what ``LostTargetSuspender`` does on the fake
  tracker: the failed read, an aim at the predicted reflector (slew π rad/s, predicted by the
  least-squares registration of the samples so far on nominal kinematics — the real
  ``ReflectorPredictor``), a spiral search when the prediction misses the 5 mm capture radius
  (π s² / (pitch · speed)), the ADM lock (0.1 s), the resume delay and a new settle window.

Orders: ours = ``order_configurations`` (move time, nearest neighbour + 2-opt); the paper's =
``order_by_pose_proximity`` (Cartesian poses nearest-first, every configuration of a pose in a
row). A configuration the sensor cannot see at rest is skipped in every run alike.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from acquire.plan.schema import load_plan, resolve_configurations  # noqa: E402
from acquire.run.sequencer import (  # noqa: E402
    move_times,
    order_by_pose_proximity,
    order_by_proximity,
    order_configurations,
)
from acquire.run.suspenders import ReflectorPredictor  # noqa: E402
from calib.robot.kinematics import Chain  # noqa: E402
from drivers.protocols import JointLimits  # noqa: E402
from drivers.sim.cell import SimCell  # noqa: E402
from drivers.trajectory import JointTrajectory, scaled_limits  # noqa: E402

PAPER_SETTLE_S = 3.0
SERVO_HZ, SERVO_ZETA = 6.0, 0.7  # drivers.kuka_fri.fake defaults
POLL_S = 0.004  # CommanderBase.wait_settled poll
MOCAP_HZ, TRACKER_AVG_HZ = 120.0, 1000.0
# drivers.tracker.fake defaults
CAPTURE_MM, SLEW_RAD_S, ADM_LOCK_S, SEARCH_SPEED_MM_S = 5.0, math.pi, 0.1, 200.0
SEARCH_PITCH_MM = CAPTURE_MM
RESUME_DELAY_S = 0.1  # LostTargetSuspender.settle_after_s
READ_S = 0.002  # one tracker MEAS round trip


def servo_settle_times(seq, start_q, limits, speed, tol_rad, window_s, h=0.0005) -> np.ndarray:
    """(k,) seconds from each trajectory's end until the robot window holds (servo simulated)."""
    v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed)
    pts = [np.asarray(start_q, float)] + [np.asarray(c.q_rad, float) for c in seq]
    trajs = [JointTrajectory.plan(pts[i], pts[i + 1], v, a, j) for i in range(len(seq))]
    k, n = len(trajs), len(start_q)
    dur = np.array([t.duration for t in trajs])
    tail = window_s + 2.0
    steps = int(math.ceil((dur.max() + tail) / h))
    w, z = 2 * math.pi * SERVO_HZ, SERVO_ZETA
    q = np.array(pts[:-1])
    qd = np.zeros((k, n))
    t_grid = np.arange(steps) * h
    poll_every = int(round(POLL_S / h))
    # set-points at the commander's 5 ms cycle (sample-and-hold), for every move at once
    cyc = 0.005
    sp_times = np.floor(t_grid / cyc) * cyc
    out = np.full(k, np.nan)
    ref = np.zeros((k, n))
    t0 = np.full(k, np.nan)
    sp_cache = {}
    for s in range(steps):
        ts = sp_times[s]
        if ts not in sp_cache:
            sp_cache.clear()
            sp_cache[ts] = np.array([tr.sample(min(ts, tr.duration))[0] for tr in trajs])
        sp = sp_cache[ts]
        acc = w * w * (sp - q) - 2 * z * w * qd
        qd += acc * h
        q += qd * h
        if s % poll_every:
            continue
        t = t_grid[s]
        active = (t >= dur) & np.isnan(out)
        if not np.any(active):
            if np.all(~np.isnan(out)):
                break
            continue
        fresh = active & np.isnan(t0)
        ref[fresh], t0[fresh] = q[fresh], t
        moved = active & (np.max(np.abs(q - ref), axis=1) > tol_rad)
        ref[moved], t0[moved] = q[moved], t
        held = active & ~moved & (t - t0 >= window_s)
        out[held] = t - dur[held]
    return np.where(np.isnan(out), tail, out)


def visible_at_rest(cell: SimCell, seq, sensor: str) -> np.ndarray:
    return np.array([bool(np.all(cell.visibility(np.asarray(c.q_rad), sensor))) for c in seq])


def beam_breaks(cell: SimCell, seq, start_q, limits, speed, dt=0.02) -> np.ndarray:
    """(k,) True where the tracker's line of sight breaks during the move to configuration i."""
    v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed)
    pts = [np.asarray(start_q, float)] + [np.asarray(c.q_rad, float) for c in seq]
    out = np.zeros(len(seq), bool)
    for i in range(len(seq)):
        tr = JointTrajectory.plan(pts[i], pts[i + 1], v, a, j)
        ts = np.arange(0.0, tr.duration + dt, dt)
        q = tr.sample(ts)[0]
        out[i] = not np.all(cell.visibility(q, "tracker"))
    return out


def reacquire_seconds(cell: SimCell, predictor: ReflectorPredictor, q, last_aim_mm) -> tuple[float, float]:
    """(seconds, prediction miss mm) of aim + (search) + lock at configuration q."""
    true = cell.true_marker_positions(np.asarray(q), "tracker")[cell.marker_names.index("smr")]
    pred, _ = predictor.predict("tracker", "smr", q)
    u0 = last_aim_mm / np.linalg.norm(last_aim_mm)
    u1 = pred / np.linalg.norm(pred)
    t = math.acos(float(np.clip(u0 @ u1, -1, 1))) / SLEW_RAD_S
    miss = float(np.linalg.norm(true - (true @ u1) * u1))  # ray distance, as the fake measures it
    if miss > CAPTURE_MM:
        s = miss - CAPTURE_MM
        t += math.pi * s * s / (SEARCH_PITCH_MM * SEARCH_SPEED_MM_S)
    return t + ADM_LOCK_S, miss


def main() -> None:
    t_wall = time.perf_counter()
    lp = load_plan(ROOT / "fixtures" / "plans" / "paper.yaml")
    configs = resolve_configurations(lp)
    seq_spec = lp.plan.sequencing
    speed, window = float(seq_spec.speed), float(seq_spec.settle_window_s)
    tol = math.radians(float(seq_spec.settle_tolerance_deg))
    samples = int(seq_spec.samples)
    cell = SimCell.from_yaml(ROOT / "fixtures" / "sim" / "default.yaml")
    limits = JointLimits.from_model(lp.model)
    chain = Chain(lp.model)
    start = cell.joint_positions()

    ours = order_configurations(configs, start, limits, speed)
    paper = order_by_pose_proximity(configs, start, chain)
    joint_nn = order_by_proximity(configs, start)

    print(f"plan: fixtures/plans/paper.yaml — {len(configs)} configurations, speed {speed:g}, "
          f"settle window {window:g} s, tolerance {math.degrees(tol):g}°, {samples} samples")
    print("cell time in SIMULATED seconds, computed analytically (see the module docstring)\n")

    # ---------------------------------------------------------------- 1. ordering + settling
    measure_mocap = samples / MOCAP_HZ
    rows = {}
    for name, seq in (("ours", ours), ("paper", paper), ("joint-NN", joint_nn)):
        motion = move_times(seq, start, limits, speed)
        settle = servo_settle_times(seq, start, limits, speed, tol, window)
        seen = visible_at_rest(cell, seq, "mocap")
        rows[name] = (motion, settle, seen)
    motion_o, settle_o, seen_o = rows["ours"]
    motion_p, _, seen_p = rows["paper"]
    ours_total = motion_o.sum() + (settle_o + measure_mocap)[seen_o].sum()
    paper_total = motion_p.sum() + (PAPER_SETTLE_S + measure_mocap) * seen_p.sum()
    mixed_order = motion_o.sum() + (PAPER_SETTLE_S + measure_mocap) * seen_o.sum()
    mixed_settle = motion_p.sum() + (rows["paper"][1] + measure_mocap)[seen_p].sum()
    print("1. motion capture run: ordering + settle detection vs the paper's procedure")
    print(f"   paper: pose-proximity order, fixed {PAPER_SETTLE_S:g} s settle : motion {motion_p.sum():7.1f} s, "
          f"settle {PAPER_SETTLE_S * seen_p.sum():6.1f} s, measure {measure_mocap * seen_p.sum():5.1f} s, "
          f"total {paper_total:7.1f} s ({paper_total / 60:.1f} min)")
    print(f"   ours : move-time order + 2-opt, settle detection : motion {motion_o.sum():7.1f} s, "
          f"settle {settle_o[seen_o].sum():6.1f} s (mean {settle_o[seen_o].mean():.3f} s), "
          f"measure {measure_mocap * seen_o.sum():5.1f} s, total {ours_total:7.1f} s ({ours_total / 60:.1f} min)")
    print(f"   only our order   (fixed 3 s settle): {mixed_order:7.1f} s  ratio {mixed_order / paper_total:.3f}")
    print(f"   only our settle  (paper's order)   : {mixed_settle:7.1f} s  ratio {mixed_settle / paper_total:.3f}")
    print(f"   joint-space nearest neighbour motion {rows['joint-NN'][0].sum():7.1f} s vs ours {motion_o.sum():7.1f} s "
          f"(ratio {motion_o.sum() / rows['joint-NN'][0].sum():.3f})")
    print(f"   configurations measured: {seen_o.sum()} of {len(configs)} (the rest not visible at rest)")
    r1 = ours_total / paper_total
    print(f"   RATIO ours / paper = {r1:.3f}   (target <= 0.5: {'met' if r1 <= 0.5 else 'NOT met'})\n")

    # ---------------------------------------------------------------- 2. tracker with beam breaks
    measure_tracker = samples / TRACKER_AVG_HZ
    seen_t = visible_at_rest(cell, ours, "tracker")
    breaks = beam_breaks(cell, ours, start, limits, speed)
    predictor = ReflectorPredictor(chain, {"smr": lp.model.marker_index("smr")},
                                   {"tracker": cell.truth.base2sensor["tracker"]})
    smr = cell.marker_names.index("smr")
    locked = True
    last_aim = cell.true_marker_positions(start, "tracker")[smr]
    reacq, misses, n_breaks = 0.0, [], 0
    total_t = motion_o.sum()
    for i, c in enumerate(ours):
        q = np.asarray(c.q_rad)
        true = cell.true_marker_positions(q, "tracker")[smr]
        if breaks[i]:
            locked = False
        if not seen_t[i]:
            continue  # skipped at once in both runs (not visible at rest)
        cost = settle_o[i] + measure_tracker
        if not locked:
            n_breaks += 1
            t, miss = reacquire_seconds(cell, predictor, q, last_aim)
            misses.append(miss)
            extra = READ_S + t + RESUME_DELAY_S + window  # failed read, re-acquire, delay, settle again
            reacq += extra
            cost += extra
            locked = True
        total_t += cost
        last_aim = true
        predictor.add("tracker", "smr", q, true + np.random.default_rng(i).normal(0, 0.02, 3))
    mocap_total = motion_o.sum() + (settle_o + measure_tracker)[seen_t].sum()
    r2 = total_t / mocap_total
    print("2. laser tracker run with beam breaks vs the same run without breaks (motion capture timing)")
    print(f"   beam breaks: {n_breaks} of {seen_t.sum()} measured configurations; re-acquisition {reacq:6.1f} s total, "
          f"{reacq / max(n_breaks, 1):.2f} s each; prediction miss median {np.median(misses) if misses else 0:.1f} mm, "
          f"max {max(misses) if misses else 0:.1f} mm (capture radius {CAPTURE_MM:g} mm)")
    print(f"   motion-capture run: {mocap_total:7.1f} s   tracker run: {total_t:7.1f} s")
    print(f"   RATIO tracker / motion capture = {r2:.3f}   (target <= 1.25: {'met' if r2 <= 1.25 else 'NOT met'}; "
          f"the paper: 3.5 h / 20 min = {3.5 * 60 / 20:.1f})")
    print(f"\n(bench computed in {time.perf_counter() - t_wall:.1f} s wall)")


if __name__ == "__main__":
    main()
