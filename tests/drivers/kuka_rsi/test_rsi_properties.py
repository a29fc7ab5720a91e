"""Property: whatever the targets, limits, speed, timing jitter and stop times, the command
stream the commander actually sends (as the fake controller received it, cycle by cycle) never
exceeds the position, velocity or acceleration limits."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from drivers.trajectory import motion_time
from rsi_helpers import HOME_DEG, KR6_LOWER, KR6_UPPER, assert_stream_within_limits, kr6_limits, rig


@st.composite
def scenarios(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    margin = 1.0
    lo, hi = np.array(KR6_LOWER) + margin, np.array(KR6_UPPER) - margin
    targets = [rng.uniform(lo, hi) for _ in range(2)]
    # short moves too: only a few axes, small distances
    if rng.random() < 0.5:
        targets[0] = np.array(HOME_DEG) + rng.normal(0, 3, 6) * (rng.random(6) < 0.5)
        targets[0] = np.clip(targets[0], lo, hi)
    return {
        "seed": seed,
        "speed_scale": draw(st.floats(0.5, 4.0)),
        "accel_scale": draw(st.floats(0.3, 4.0)),
        "speed": draw(st.floats(0.05, 1.0)),
        "jitter_s": draw(st.sampled_from([0.0, 0.0003, 0.001])),
        "stop_after_s": draw(st.one_of(st.none(), st.floats(0.0, 0.05))),
        "targets": targets,
    }


@pytest.mark.slow  # ~35 s of 25 real-time streams (near its timeout on a loaded host); the clamp itself is unit-tested beside it
@settings(max_examples=25, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
def test_command_stream_never_exceeds_limits(sc):
    limits = kr6_limits(sc["speed_scale"], sc["accel_scale"])
    # keep every move under ~1.5 s of controller time (375 cycles) so the suite stays quick
    longest = max(
        motion_time(np.radians(a), np.radians(b), limits.max_velocity_rad_s, limits.max_acceleration_rad_s2)
        for a, b in [(HOME_DEG, sc["targets"][0]), (sc["targets"][0], sc["targets"][1])]
    )
    speed = max(sc["speed"], min(1.0, longest / 1.5))
    fake = {"lockstep": True, "jitter_s": sc["jitter_s"], "seed": sc["seed"]}
    with rig(limits, fake_kwargs=fake) as (c, f):  # (lockstep: the rig widens the silence limits)
        first = np.radians(sc["targets"][0])
        if sc["stop_after_s"] is not None:
            timer = threading.Timer(sc["stop_after_s"], lambda: c.stop(end_session=False))
            timer.start()
            c.move_to(first, speed, timeout=60.0)
            timer.join()
        else:
            c.move_to(first, speed, timeout=60.0)
        c.wait_settled(np.radians(0.01), 0.02, 10.0)
        c.move_to(np.radians(sc["targets"][1]), speed, timeout=60.0)
        time.sleep(0.01)
        received = f.received()
        clamps = c.link_stats().guard_clamps
        stats = f.stats()
    assert clamps == 0  # the guard never had to intervene: the plan itself is within limits
    assert stats.clipped_corrections == 0
    ex = assert_stream_within_limits(received, HOME_DEG, limits)
    assert ex["velocity_ratio"] <= speed * 1.001 + 1e-4
    np.testing.assert_allclose(
        np.array(received[-1].correction_deg) + HOME_DEG, sc["targets"][1], atol=1e-6
    )
