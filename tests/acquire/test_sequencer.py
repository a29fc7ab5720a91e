"""The sequencer's parts on simulated time: ordering, settling status, lost-target suspender."""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from acquire.run.sequencer import (
    ConfigProcedure,
    SensorSpec,
    SequencingSettings,
    motion_cost_matrix,
    move_times,
    order_by_proximity,
    order_configurations,
)
from acquire.run.settle import StabilityWindow, wait_settled
from acquire.run.suspenders import LostTargetSuspender, ReflectorPredictor
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from drivers.errors import DeviceTimeoutError, TargetLostError
from drivers.protocols import JointLimits, JointState, MarkerMeasurement, MarkerSample

ROOT = Path(__file__).resolve().parents[2]
MODEL = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
LIMITS = JointLimits.from_model(MODEL)


@dataclass(frozen=True)
class Cfg:
    config_id: str
    q_rad: np.ndarray
    pose: str = ""
    branch: str = ""


def random_configs(n: int, seed: int) -> list[Cfg]:
    rng = np.random.default_rng(seed)
    lo, hi = LIMITS.lower_rad * 0.8, LIMITS.upper_rad * 0.8
    return [Cfg(f"c{i:03d}", rng.uniform(lo, hi)) for i in range(n)]


class ManualClock:
    """Simulated seconds that advance only when something sleeps or reads."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += max(dt, 0.0)


# ------------------------------------------------------------------------------ ordering
def test_order_is_a_permutation_and_never_slower_than_nearest_neighbour_by_distance():
    configs = random_configs(60, seed=4)
    start = np.zeros(7)
    ours = order_configurations(configs, start, LIMITS, 0.3)
    assert sorted(c.config_id for c in ours) == sorted(c.config_id for c in configs)
    t_ours = move_times(ours, start, LIMITS, 0.3).sum()
    t_prox = move_times(order_by_proximity(configs, start), start, LIMITS, 0.3).sum()
    t_given = move_times(configs, start, LIMITS, 0.3).sum()
    assert t_ours < t_prox < t_given
    assert t_ours < 0.95 * t_prox


def test_order_finds_the_optimum_of_a_small_plan():
    configs = random_configs(7, seed=11)
    start = np.radians([0, 20, 0, -90, 0, -30, 0])
    # Every order's time from the pairwise move times (5040 orders: a table look-up each, not a
    # trajectory each), after checking that a sequence's time is the sum of its moves' times.
    cost = motion_cost_matrix(np.vstack([start] + [c.q_rad for c in configs]), LIMITS, 0.5)
    given = move_times(configs, start, LIMITS, 0.5).sum()
    assert given == pytest.approx(cost[0, 1] + sum(cost[i, i + 1] for i in range(1, len(configs))), rel=1e-9)
    best = min(cost[0, p[0]] + sum(cost[a, b] for a, b in zip(p, p[1:]))
               for p in itertools.permutations(range(1, len(configs) + 1)))
    ours = move_times(order_configurations(configs, start, LIMITS, 0.5), start, LIMITS, 0.5).sum()
    assert ours <= best * 1.02


def test_order_uses_move_time_not_joint_distance():
    # A1 is slow, A7 fast: a long A7 move is quicker than a shorter A1 move.
    start = np.zeros(7)
    a1 = Cfg("a1", np.array([0.6, 0, 0, 0, 0, 0, 0.0]))
    a7 = Cfg("a7", np.array([0, 0, 0, 0, 0, 0, 0.8]))
    cost = motion_cost_matrix(np.vstack([start, a1.q_rad, a7.q_rad]), LIMITS, 1.0)
    assert cost[0, 2] < cost[0, 1]  # premise: the farther config is the quicker one
    assert [c.config_id for c in order_configurations([a1, a7], start, LIMITS, 1.0)] == ["a7", "a1"]
    assert [c.config_id for c in order_by_proximity([a1, a7], start)] == ["a1", "a7"]


def test_move_times_scale_with_the_speed_override():
    configs = random_configs(5, seed=2)
    full = move_times(configs, np.zeros(7), LIMITS, 1.0)
    slow = move_times(configs, np.zeros(7), LIMITS, 0.25)
    np.testing.assert_allclose(slow, full / 0.25, rtol=1e-9)


# ------------------------------------------------------------------------------ settling
def test_stability_window_restarts_on_a_jump_and_holds_after_the_window():
    w = StabilityWindow(0.05, 0.3)
    assert not w.update(0.0, [0.0, 0.0, 0.0])
    assert not w.update(0.2, [0.01, 0.0, 0.0])
    assert not w.update(0.25, [0.2, 0.0, 0.0])  # jump: restart here
    assert w.restarts == 1
    assert not w.update(0.5, [0.21, 0.0, 0.0])
    assert w.update(0.56, [0.2, 0.0, 0.0])


def test_stability_window_rejects_bad_settings():
    with pytest.raises(ValueError, match="tolerance"):
        StabilityWindow(0.0, 1.0)
    with pytest.raises(ValueError, match="window_s"):
        StabilityWindow(0.1, -1.0)


class DecayingSensor:
    """A marker that drifts towards its rest position (exponential, τ seconds), with noise."""

    name = "bar"

    def __init__(self, clock: ManualClock, tau: float, rate_hz: float = 100.0, noise: float = 0.01,
                 lost_at: float | None = None, wobble_mm: float = 0.0) -> None:
        self.clock, self.tau, self.dt, self.noise = clock, tau, 1.0 / rate_hz, noise
        self.wobble_mm = wobble_mm
        self.rng = np.random.default_rng(0)
        self.lost_at = lost_at

    def position(self, t: float) -> np.ndarray:
        swing = 2.0 * math.exp(-t / self.tau) + self.wobble_mm * math.sin(2 * math.pi * t / 0.3)
        return np.array([500.0, 0.0, 0.0]) + swing * np.array([1.0, 1.0, 0.0])

    def read(self, timeout: float) -> list[MarkerSample]:
        time.sleep(0.0005)  # yield, as a real read does, so the robot side sees the clock move
        self.clock.sleep(self.dt)
        t = self.clock.now()
        if self.lost_at is not None and t >= self.lost_at:
            return [MarkerSample("m", np.full(3, np.nan), t, t, visible=False)]
        p = self.position(t) + self.rng.normal(0, self.noise, 3)
        return [MarkerSample("m", p, t, t)]

    def measure(self, marker: str, n: int, timeout: float) -> MarkerMeasurement:
        pts = np.array([self.read(timeout)[0].position_mm for _ in range(n)])
        t = self.clock.now()
        return MarkerMeasurement(marker, pts.mean(0), pts.std(0, ddof=1), n, t, t)


class StillCommander:
    name = "robot"

    def __init__(self, clock: ManualClock, q: np.ndarray, settle_s: float = 0.2) -> None:
        self.clock, self.q, self.settle_s = clock, np.asarray(q, float), settle_s
        self.moves: list[np.ndarray] = []
        self.limits = LIMITS

    def joint_state(self) -> JointState:
        t = self.clock.now()
        return JointState(self.q.copy(), t, t)

    def wait_settled(self, tolerance_rad: float, window_s: float, timeout: float) -> JointState:
        """Still after ``settle_s + window_s`` of simulated time, which the sensor's reads
        advance (one thread moves the clock, so the test is deterministic)."""
        if window_s >= timeout:
            raise ValueError("window longer than timeout")
        target = self.clock.now() + self.settle_s + window_s
        last, idle = self.clock.now(), 0
        while self.clock.now() < target:
            time.sleep(0.0001)
            idle = idle + 1 if self.clock.now() == last else 0
            last = self.clock.now()
            if idle > 100:  # nobody reads any more (the sensor side ended): move time on ourselves
                self.clock.sleep(0.01)
        return self.joint_state()

    def move_to(self, target, speed, timeout) -> None:
        self.clock.sleep(1.0)
        self.q = np.asarray(target, float)
        self.moves.append(self.q)


def test_wait_settled_waits_for_the_sensor_not_a_fixed_time():
    clock = ManualClock()
    cmd = StillCommander(clock, np.zeros(7))
    fast = wait_settled(cmd, [(DecayingSensor(clock, tau=0.05), ["m"], 0.01)], tolerance_rad=1e-4,
                        window_s=0.2, sensor_stable_mm=0.02, timeout=10.0, clock=clock.now)
    clock2 = ManualClock()
    slow = wait_settled(StillCommander(clock2, np.zeros(7)), [(DecayingSensor(clock2, tau=0.5), ["m"], 0.01)],
                        tolerance_rad=1e-4, window_s=0.2, sensor_stable_mm=0.02, timeout=10.0, clock=clock2.now)
    # The drift of 2 mm·e^(-t/τ) must fall under ~0.06 mm before a window can hold; the robot's
    # own window (0.4 s here) runs at the same time, so a quick sensor costs nothing extra.
    assert fast.seconds < 0.7
    assert slow.seconds > fast.seconds + 0.3
    assert slow.restarts["bar/m"] > fast.restarts["bar/m"]


def test_wait_settled_times_out_and_reports_a_lost_marker():
    clock = ManualClock()
    vibrating = DecayingSensor(clock, tau=0.01, wobble_mm=0.3)
    with pytest.raises(DeviceTimeoutError, match="bar/m"):
        wait_settled(StillCommander(clock, np.zeros(7)), [(vibrating, ["m"], 0.01)],
                     tolerance_rad=1e-4, window_s=0.2, sensor_stable_mm=0.02, timeout=2.0, clock=clock.now)
    clock = ManualClock()
    with pytest.raises(TargetLostError, match="not visible"):
        wait_settled(StillCommander(clock, np.zeros(7)), [(DecayingSensor(clock, tau=0.01, lost_at=0.3), ["m"], 0.01)],
                     tolerance_rad=1e-4, window_s=0.5, sensor_stable_mm=0.02, timeout=5.0, clock=clock.now)
    with pytest.raises(ValueError, match="shorter than the timeout"):
        wait_settled(StillCommander(clock, np.zeros(7)), [], tolerance_rad=1e-4, window_s=3.0,
                     sensor_stable_mm=0.02, timeout=2.0, clock=clock.now)


def test_procedure_records_targets_measured_joints_and_markers():
    clock = ManualClock()
    cmd = StillCommander(clock, np.zeros(7))
    events = []
    settings = SequencingSettings(speed=0.3, settle_window_s=0.1, settle_tolerance_rad=1e-4, sensor_stable_mm=0.05,
                                  samples=10, move_timeout_s=30, measure_timeout_s=5)
    proc = ConfigProcedure(cmd, [SensorSpec(DecayingSensor(clock, tau=0.01), ["m"], 0.01)], settings,
                           clock=clock.now, sleep=clock.sleep, wall=lambda: 1.7e9,
                           event=lambda kind, **f: events.append((kind, f)))
    cfg = Cfg("p01-b2", np.radians([10, 20, 30, -40, 50, 60, 70]), pose="p01", branch="b2")
    proc.move(cfg)
    rec = proc.settle_and_measure(cfg, attempts=1, t_start_wall=1.6e9)
    assert [k for k, _ in events] == ["moved", "settled", "measured"]
    assert rec["config_id"] == "p01-b2" and rec["pose"] == "p01" and rec["branch"] == "b2"
    np.testing.assert_allclose(rec["q_target_deg"], [10, 20, 30, -40, 50, 60, 70])
    np.testing.assert_allclose(rec["q_measured_deg"], [10, 20, 30, -40, 50, 60, 70])
    assert rec["markers"][0]["count"] == 10 and rec["markers"][0]["sensor"] == "bar"
    np.testing.assert_allclose(rec["markers"][0]["mean_mm"], [500, 0, 0], atol=0.05)


# ------------------------------------------------------------------------------ suspender
class BeamTracker:
    """A tracker-like sensor: locks when aimed within ``capture`` mm of the true point, or when a
    spiral search of enough radius runs; records what it was asked."""

    name = "tracker"

    def __init__(self, true_mm, capture: float = 5.0) -> None:
        self.true = np.asarray(true_mm, float)
        self.capture = capture
        self.locked = False
        self.aims: list[np.ndarray] = []
        self.searches: list[float] = []

    def aim(self, xyz, timeout: float = 10.0) -> None:
        self.aims.append(np.asarray(xyz, float))
        self.locked = np.linalg.norm(np.asarray(xyz) - self.true) <= self.capture
        if not self.locked:
            raise TargetLostError("tracker: no reflector within the capture radius")

    def search(self, radius_mm: float, timeout: float):
        self.searches.append(radius_mm)
        miss = np.linalg.norm(self.aims[-1] - self.true) if self.aims else np.inf
        if miss > radius_mm:
            raise TargetLostError("tracker: spiral search found nothing")
        self.locked = True

    def read(self, timeout: float):
        return [MarkerSample("smr", self.true if self.locked else np.full(3, np.nan), 0.0, 0.0, visible=self.locked)]


def make_predictor(initial=None) -> ReflectorPredictor:
    return ReflectorPredictor(Chain(MODEL), {"smr": MODEL.marker_index("smr")}, initial)


def base2tracker() -> np.ndarray:
    t = np.eye(4)
    c, s = math.cos(0.3), math.sin(0.3)
    t[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    t[:3, 3] = [-2000.0, 100.0, -900.0]
    return t


def test_predictor_registers_after_three_samples_and_predicts_the_reflector():
    pred = make_predictor()
    t = base2tracker()
    configs = random_configs(4, seed=5)
    assert pred.predict("tracker", "smr", configs[0].q_rad)[0] is None
    for c in configs[:3]:
        p = pred.nominal_base("smr", c.q_rad)
        pred.add("tracker", "smr", c.q_rad, t[:3, :3] @ p + t[:3, 3])
    got, source = pred.predict("tracker", "smr", configs[3].q_rad)
    want = t[:3, :3] @ pred.nominal_base("smr", configs[3].q_rad) + t[:3, 3]
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert "3 samples" in source


def suspender(policy: str, predictor, clock: ManualClock, events: list, **kw) -> LostTargetSuspender:
    return LostTargetSuspender(policy, wait_s=1.0, predictor=predictor, clock=clock.now, sleep=clock.sleep,
                               event=lambda kind, **f: events.append((kind, f)), search_radius_mm=20.0, **kw)


def test_lost_beam_is_reacquired_by_aiming_at_the_prediction():
    clock, events = ManualClock(), []
    q = random_configs(1, seed=9)[0].q_rad
    pred = make_predictor({"tracker": base2tracker()})
    truth, _ = pred.predict("tracker", "smr", q)
    tracker = BeamTracker(truth + [1.0, 0.0, 0.0])
    rec = suspender("skip", pred, clock, events).recover(tracker, "smr", "c1", q, "beam lost")
    # policy "skip" never re-acquires; "reacquire" does
    assert rec.action == "skip" and tracker.aims == []
    events.clear()
    rec = suspender("reacquire", pred, clock, events).recover(tracker, "smr", "c1", q, "beam lost")
    assert rec.action == "resume"
    np.testing.assert_allclose(tracker.aims[0], truth)
    assert [k for k, _ in events] == ["suspended", "aimed", "resumed"]
    assert events[0][1]["reason"] == "beam lost"


def test_a_missed_aim_falls_back_to_the_spiral_search_then_to_the_policy():
    clock, events = ManualClock(), []
    q = random_configs(1, seed=9)[0].q_rad
    pred = make_predictor({"tracker": base2tracker()})
    truth, _ = pred.predict("tracker", "smr", q)
    near = BeamTracker(truth + [12.0, 0.0, 0.0])  # outside the capture radius, inside the search
    assert suspender("wait", pred, clock, events).recover(near, "smr", "c1", q, "beam lost").action == "resume"
    assert near.searches == [20.0]
    assert [k for k, _ in events][-3:] == ["aimed", "searched", "resumed"]
    far = BeamTracker(truth + [80.0, 0.0, 0.0])
    events.clear()
    rec = suspender("wait", pred, clock, events).recover(far, "smr", "c2", q, "beam lost")
    assert rec.action == "skip" and "not back within 1 s" in rec.reason
    assert ("searched", {"config_id": "c2", "sensor": "tracker", "found": False, "radius_mm": 20.0,
                         "detail": "tracker: spiral search found nothing"}) in events


def test_ask_policy_asks_on_a_terminal_and_skips_without_one():
    clock, events = ManualClock(), []
    q = np.zeros(7)
    tracker = BeamTracker([0.0, 0.0, 5000.0])
    no_tty = suspender("ask", None, clock, events).recover(tracker, "smr", "c1", q, "beam lost")
    assert no_tty.action == "skip" and "no terminal" in no_tty.reason
    asked = []
    rec = suspender("ask", None, clock, events, ask=lambda text: asked.append(text) or "abort").recover(
        tracker, "smr", "c1", q, "beam lost")
    assert rec.action == "abort" and "c1" in asked[0]


def test_suspender_rejects_unknown_policies():
    with pytest.raises(ValueError, match="wait, reacquire, ask, skip"):
        LostTargetSuspender("pray", wait_s=1.0, predictor=None, clock=lambda: 0.0, sleep=lambda s: None,
                            event=lambda *a, **k: None)


def test_reacquire_policy_aims_again_while_it_waits_for_a_beam_blocked_at_the_first_try():
    """Someone still stands in the beam when the first aim goes out: a tracker never re-locks by
    itself, so the policy ``reacquire`` aims again while it waits, and resumes once clear."""
    clock, events = ManualClock(), []
    q = random_configs(1, seed=9)[0].q_rad
    pred = make_predictor({"tracker": base2tracker()})
    truth, _ = pred.predict("tracker", "smr", q)

    class BlockedForAWhile(BeamTracker):
        def aim(self, xyz, timeout: float = 10.0) -> None:
            if clock.now() < 0.5:
                self.aims.append(np.asarray(xyz, float))
                raise TargetLostError("tracker: beam blocked")
            super().aim(xyz, timeout)

        def search(self, radius_mm: float, timeout: float):
            if clock.now() < 0.5:
                self.searches.append(radius_mm)
                raise TargetLostError("tracker: beam blocked")
            return super().search(radius_mm, timeout)

    tracker = BlockedForAWhile(truth)
    rec = suspender("reacquire", pred, clock, events).recover(tracker, "smr", "c1", q, "beam lost")
    assert rec.action == "resume" and rec.reason == "re-acquired", rec
    assert len(tracker.aims) >= 2 and tracker.locked
    assert 0.5 <= clock.now() < 1.0  # within wait_s
    # "wait" only waits: the same blocked beam is skipped
    events.clear()
    clock.t = 0.0
    tracker = BlockedForAWhile(truth)
    assert suspender("wait", pred, clock, events).recover(tracker, "smr", "c2", q, "beam lost").action == "skip"
