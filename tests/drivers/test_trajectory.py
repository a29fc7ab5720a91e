"""The shared joint trajectory: exact limits, synchronisation, optimality, stops."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.trajectory import JointTrajectory, default_jerk, motion_time, scaled_limits

TOL = 1e-9


@st.composite
def moves(draw):
    n = draw(st.integers(1, 7))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    start = rng.uniform(-3, 3, n)
    # mix of long, short and zero moves
    kind = rng.integers(0, 3, n)
    delta = np.where(kind == 0, rng.uniform(-4, 4, n), np.where(kind == 1, rng.uniform(-0.02, 0.02, n), 0.0))
    v = rng.uniform(0.2, 6.0, n)
    a = rng.uniform(0.5, 30.0, n)
    return start, start + delta, v, a


def dense(traj, n=4001):
    t = np.linspace(-0.01, traj.duration + 0.01, n)
    return t, *traj.sample(t)


@settings(max_examples=150, deadline=None, database=None)
@given(moves())
def test_plan_never_exceeds_velocity_or_acceleration_and_ends_at_target(move):
    start, target, v, a = move
    traj = JointTrajectory.plan(start, target, v, a)
    _, p, vel, acc = dense(traj)
    assert np.all(np.abs(vel) <= v * (1 + TOL) + 1e-12)
    assert np.all(np.abs(acc) <= a * (1 + TOL) + 1e-12)
    np.testing.assert_allclose(p[0], start, atol=1e-12)
    np.testing.assert_allclose(p[-1], target, atol=1e-12)
    np.testing.assert_allclose(vel[[0, -1]], 0.0, atol=1e-12)
    # positions stay between start and target (no overshoot)
    lo, hi = np.minimum(start, target), np.maximum(start, target)
    assert np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9)


@settings(max_examples=150, deadline=None, database=None)
@given(moves())
def test_all_moving_axes_finish_together_at_the_slowest_axis_optimal_time(move):
    start, target, v, a = move
    traj = JointTrajectory.plan(start, target, v, a)
    j = default_jerk(v, a)
    single = [motion_time(start[i : i + 1], target[i : i + 1], v[i : i + 1], a[i : i + 1], j[i : i + 1]) for i in range(len(v))]
    assert traj.duration == pytest.approx(max(single), rel=1e-12, abs=1e-15)
    assert traj.duration == pytest.approx(motion_time(start, target, v, a), rel=1e-12, abs=1e-15)
    moving = np.abs(target - start) > 0
    np.testing.assert_allclose(traj.axis_durations[moving], traj.duration, rtol=1e-9)


def test_long_move_duration_matches_the_closed_form_s_curve():
    v, a, j, d = 2.0, 4.0, 40.0, 3.0
    traj = JointTrajectory.plan([0.0], [d], [v], [a], [j])
    # accel phase v/a + a/j, cruise d/v - (v/a + a/j), total d/v + v/a + a/j
    assert traj.duration == pytest.approx(d / v + v / a + a / j, rel=1e-12)
    # time-optimal: peak velocity and acceleration both reached
    _, _, vel, acc = dense(traj, 20001)
    assert np.abs(vel).max() == pytest.approx(v, rel=1e-9)
    assert np.abs(acc).max() == pytest.approx(a, rel=1e-9)


def test_short_move_without_constant_acceleration_matches_closed_form():
    v, a, j, d = 2.0, 4.0, 10.0, 0.01
    traj = JointTrajectory.plan([0.0], [d], [v], [a], [j])
    # pure jerk profile: d = 2 j tj^3 and T = 4 tj
    tj = (d / (2 * j)) ** (1 / 3)
    assert traj.duration == pytest.approx(4 * tj, rel=1e-12)


def test_velocity_is_the_derivative_of_position_and_acceleration_is_continuous():
    traj = JointTrajectory.plan([0.0, 1.0], [2.0, -0.5], [1.5, 2.0], [3.0, 2.5])
    t, p, vel, acc = dense(traj, 200001)
    dt = t[1] - t[0]
    np.testing.assert_allclose(np.gradient(p, dt, axis=0)[1:-1], vel[1:-1], atol=1e-4)
    assert np.abs(np.diff(acc, axis=0)).max() < 1e-3  # no acceleration steps


def test_speed_override_stretches_time_exactly():
    start, target = np.zeros(3), np.array([1.0, -2.0, 0.3])
    v, a = np.array([2.0, 2.5, 3.0]), np.array([5.0, 6.0, 9.0])
    full = JointTrajectory.plan(start, target, *scaled_limits(v, a, 1.0))
    slow = JointTrajectory.plan(start, target, *scaled_limits(v, a, 0.2))
    assert slow.duration == pytest.approx(full.duration / 0.2, rel=1e-9)
    np.testing.assert_allclose(slow.sample(0.37 / 0.2)[0], full.sample(0.37)[0], atol=1e-9)


def test_motion_time_is_vectorised_over_leading_dimensions():
    rng = np.random.default_rng(3)
    q0 = rng.uniform(-1, 1, (4, 5, 6))
    q1 = rng.uniform(-1, 1, (4, 5, 6))
    v, a = np.full(6, 2.0), np.full(6, 5.0)
    T = motion_time(q0, q1, v, a)
    assert T.shape == (4, 5)
    assert T[2, 3] == pytest.approx(JointTrajectory.plan(q0[2, 3], q1[2, 3], v, a).duration, rel=1e-12)


@settings(max_examples=200, deadline=None, database=None)
@given(
    st.integers(0, 2**32 - 1),
    st.floats(0.0, 1.0),
)
def test_stop_from_any_point_of_a_move_stays_within_limits_and_ends_at_rest(seed, frac):
    rng = np.random.default_rng(seed)
    n = 6
    v, a = rng.uniform(0.3, 4, n), rng.uniform(1, 20, n)
    traj = JointTrajectory.plan(rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), v, a)
    p0, v0, a0 = traj.sample(frac * traj.duration)
    stop = JointTrajectory.stop(p0, v0, a0, v, a)
    _, p, vel, acc = dense(stop)
    assert np.all(np.abs(vel) <= v * (1 + TOL) + 1e-12)
    assert np.all(np.abs(acc) <= a * (1 + TOL) + 1e-12)
    np.testing.assert_allclose(vel[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(acc[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(p[1], p0, atol=1e-3)  # continuous with the move it interrupts
    # it never stops later than the rest of the planned move would have
    assert stop.duration <= traj.duration * (1 - frac) + 1e-6


def test_stop_from_hard_braking_state_reverses_briefly_within_limits():
    stop = JointTrajectory.stop([0.0], [0.01], [-3.0], [2.0], [3.0], [10.0])
    _, _, vel, acc = dense(stop, 20001)
    assert vel.min() < 0  # the velocity crosses zero
    assert np.abs(acc).max() <= 3.0 + 1e-12
    assert vel[-1, 0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(
    "args",
    [
        ([0.0], [1.0], [0.0], [1.0]),
        ([0.0], [1.0], [1.0], [-1.0]),
        ([0.0], [np.nan], [1.0], [1.0]),
        ([0.0, 1.0], [1.0], [1.0], [1.0]),
    ],
)
def test_bad_plan_arguments_raise_value_error(args):
    with pytest.raises(ValueError):
        JointTrajectory.plan(*args)


def test_speed_outside_unit_interval_is_refused():
    with pytest.raises(ValueError, match="speed"):
        scaled_limits([1.0], [1.0], 1.5)
