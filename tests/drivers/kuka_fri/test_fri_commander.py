"""``FriCommander`` driving ``FakeSunrise`` over real UDP on 127.0.0.1."""

from __future__ import annotations

import logging
import math
import os
import threading
import time

import numpy as np
import pytest
from fri_helpers import RecordingScene, assert_timed_commands_within_limits, fri_pair

from drivers.errors import DeviceFaultError, LimitError
from drivers.kuka_fri.commander import FriCommander, MotionStoppedError
from drivers.kuka_fri.messages import SessionState
from drivers.protocols import JointCommander
from drivers.registry import load_driver
from drivers.sim.clock import SimClock

Q0 = np.radians([0.0, 20.0, 0.0, -60.0, 0.0, 45.0, 0.0])
TARGETS_DEG = [
    [30.0, 40.0, -20.0, -90.0, 15.0, 60.0, 90.0],
    [-25.0, 10.0, 35.0, -40.0, -30.0, 20.0, -45.0],
    [0.0, 20.0, 0.0, -60.0, 0.0, 45.0, 0.0],
]


def test_fri_is_registered_and_is_a_joint_commander(limits):
    cls = load_driver("fri")
    assert cls is FriCommander
    assert isinstance(FriCommander.from_url("fri://127.0.0.1:0", limits=limits), JointCommander)


def test_url_options_are_parsed_and_unknown_ones_refused(limits):
    c = FriCommander.from_url(
        "fri://127.0.0.1:30201?controller=127.0.0.1&rt_priority=0&timeout_ms=250&max_speed=0.5"
        "&start_tolerance_deg=1&name=iiwa",
        limits=limits,
    )
    assert (c.bind, c.controller_host, c.rt_priority, c.name) == (("127.0.0.1", 30201), "127.0.0.1", 0, "iiwa")
    assert c.receive_timeout_s == pytest.approx(0.25) and c.max_speed == 0.5
    assert c.session.start_tolerance_rad == pytest.approx(math.radians(1))
    assert FriCommander.from_url("fri://", limits=limits).bind == ("0.0.0.0", 30200)
    with pytest.raises(ValueError, match=r"unknown FRI URL option\(s\) \['speed'\]; allowed: controller"):
        FriCommander.from_url("fri://127.0.0.1:0?speed=1", limits=limits)
    with pytest.raises(ValueError, match="rt_priority='high' is not valid"):
        FriCommander.from_url("fri://127.0.0.1:0?rt_priority=high", limits=limits)
    with pytest.raises(ValueError, match="must start with fri://"):
        FriCommander.from_url("rsi://127.0.0.1:0", limits=limits)


def test_a_sequence_of_moves_reaches_every_target_and_answers_in_time(limits):
    scene = RecordingScene(Q0)
    # The fake controller runs in a real-time process of its own, as a cabinet is a machine of
    # its own (a thread of this process waits for the interpreter lock behind the test's threads:
    # beside four CPU hogs its 5 ms send period stretched to 0.75 s). The scene lives there too.
    with fri_pair(limits, scene=scene, send_period_ms=5, rt_priority=60, own_process=True,
                  url_query="rt_priority=70") as (commander, fake):
        assert fake.stats.answers_in_idle == 0
        for target_deg in TARGETS_DEG:
            target = np.radians(target_deg)
            commander.move_to(target, 0.8, timeout=10.0)
            state = commander.wait_settled(tolerance_rad=1e-5, window_s=0.05, timeout=5.0)
            np.testing.assert_allclose(state.position_rad, target, atol=1e-4)
            # the controller shows the scene where its joints are (read a few cycles apart, settled)
            np.testing.assert_allclose(fake.scene.q, fake.actual_position(), rtol=0, atol=1e-6)
        stats = fake.stats
        updates = fake.scene.updates
        link = commander.link_stats()
    # The exchange answers every message, typically far within the cycle: a systematic fault (an
    # answer to a stale message, one answer in two) makes most answers late. How many may be late
    # under load is a timing target, measured by tests/bench/bench_fri.py --load beside a probe
    # that tells the machine's stalls from the exchange's (on a shared host a stall of tens of ms
    # makes a handful late at once); none may cost the session.
    assert link.latency_p50_s < 0.25 * 0.005, link.report()
    assert link.late_answers <= max(3, link.packets // 20), link.report()
    assert stats.session_drops == 0
    assert stats.bad_reflections == 0 and stats.malformed_answers == 0
    assert stats.violations == []
    assert updates > 100
    assert_timed_commands_within_limits(stats.commands, limits, 0.005, speed=0.8)


def test_refused_moves_leave_the_robot_where_it_is(limits):
    with fri_pair(limits, initial_position_rad=Q0, url_query="rt_priority=0&max_speed=0.5&session_wait_s=0.3") as (c, fake):
        outside = Q0.copy()
        outside[1] = math.radians(119.8)  # within the limit but not its 0.5° margin
        with pytest.raises(LimitError, match=r"A2=119.800° not in \[-119.500, 119.500\]°"):
            c.move_to(outside, 0.3, timeout=5.0)
        with pytest.raises(LimitError, match=r"speed 0.8 is not allowed; the plan allows \(0, 0.5\]"):
            c.move_to(Q0 + 0.1, 0.8, timeout=5.0)
        with pytest.raises(LimitError, match=r"shape \(6,\), expected \(7,\)"):
            c.move_to(Q0[:6], 0.3, timeout=5.0)
        fake.stop_commanding()
        fake.wait_state(SessionState.MONITORING_READY, 2.0)
        c.wait_session(SessionState.MONITORING_READY, 2.0)
        # a session that does not come back within session_wait_s: a device fault the run waits out
        # (READY; or WAIT if this normal-priority exchange missed enough answer windows on a loaded
        # host that the controller dropped the session)
        with pytest.raises(DeviceFaultError, match="session is MONITORING_(READY|WAIT), not COMMANDING_ACTIVE"):
            c.move_to(Q0 + 0.1, 0.3, timeout=5.0)
        np.testing.assert_allclose(fake.actual_position(), Q0, atol=1e-9)
        assert all(np.array_equal(cmd, Q0) for _, cmd in fake.stats.commands)


def test_the_commander_refuses_a_model_that_is_not_seven_axes():
    from drivers.protocols import JointLimits

    six = JointLimits(-np.ones(6), np.ones(6), np.ones(6), np.ones(6))
    with pytest.raises(ValueError, match="an LBR iiwa has 7 axes; the model limits have 6"):
        FriCommander.from_url("fri://127.0.0.1:0", limits=six)


def test_stop_decelerates_within_limits_and_the_move_reports_it(limits):
    with fri_pair(limits, initial_position_rad=Q0) as (c, fake):
        target = np.radians([150.0, 100.0, 150.0, 100.0, 150.0, 100.0, 150.0])
        errors = []

        def mover():
            try:
                c.move_to(target, 1.0, timeout=20.0)
            except MotionStoppedError as exc:
                errors.append(exc)

        t = threading.Thread(target=mover)
        t.start()
        fake.wait_state(SessionState.COMMANDING_ACTIVE, 1.0)
        while len(fake.stats.commands) < 150:  # let it speed up (0.75 s of motion)
            threading.Event().wait(0.01)
        c.stop()
        t.join(5.0)
        assert len(errors) == 1
        held = fake.stats.commands[-1][1]
        assert np.all(np.abs(held - target) > math.radians(5))
        state = c.wait_settled(1e-5, 0.05, 5.0)
        np.testing.assert_allclose(state.position_rad, held, atol=1e-4)
        assert fake.stats.violations == []
        assert_timed_commands_within_limits(fake.stats.commands, limits, 0.005)


def test_sim_clock_runs_the_exchange_faster_than_real_time(limits):
    clock = SimClock(time_scale=2.0)
    with fri_pair(limits, clock=clock, send_period_ms=10, initial_position_rad=Q0,
                  commander_kwargs={"clock": clock.now, "sleep": clock.sleep}) as (c, fake):
        target = np.radians(TARGETS_DEG[0])
        t0 = clock.now()
        c.move_to(target, 1.0, timeout=10.0)
        state = c.wait_settled(1e-5, 0.05, 5.0)
        np.testing.assert_allclose(state.position_rad, target, atol=1e-4)
        assert state.device_time == pytest.approx(time.time(), abs=60.0)  # the controller's clock: time of day
        assert clock.now() - t0 > 0.5  # simulated seconds, half as many on the wall
        assert fake.stats.violations == []


def test_the_exchange_process_reports_how_it_is_scheduled(limits):
    # (the refusal of SCHED_FIFO and its log line: tests/drivers/test_exchange.py)
    with fri_pair(limits, commanding=False, url_query="rt_priority=0") as (c, fake):
        c.wait_session(SessionState.MONITORING_READY, 5.0)
        assert c.rt_scheduling.startswith("normal priority (rt_priority=0)")
        assert c.exchange_pid not in (None, os.getpid())
        assert "exchange process: normal priority" in " ".join(c.link_stats().notes)


def test_ctrl_c_does_not_reach_the_exchange_and_sigterm_ends_commanding(limits):
    import signal

    with fri_pair(limits, initial_position_rad=Q0) as (c, fake):
        pid = c.exchange_pid
        os.kill(pid, signal.SIGINT)  # Ctrl-C goes to the whole process group: the exchange ignores it
        target = np.radians(TARGETS_DEG[0])
        c.move_to(target, 1.0, timeout=10.0)
        c.wait_settled(1e-5, 0.05, 5.0)
        os.kill(pid, signal.SIGTERM)  # on its own: holds, then stops answering; Sunrise ends commanding
        fake.wait_state(SessionState.MONITORING_WAIT, 5.0)
        assert fake.stats.session_drops == 1 and fake.stats.violations == []
        np.testing.assert_allclose(fake.stats.commands[-1][1], target, atol=1e-9)


def test_a_healthy_session_start_is_not_a_warning_but_a_long_wait_is(limits, caplog):
    """The robot application starts its overlay a moment after MONITORING_READY: a move made
    then waits a little, and says so at INFO; only a wait past QUIET_SESSION_WAIT_S warns."""
    caplog.set_level(logging.INFO, logger="remaster.device")
    with fri_pair(limits, commanding=False, initial_position_rad=Q0, application=True,
                  application_start_cycles=100) as (c, fake):
        c.wait_session(SessionState.MONITORING_READY, 10.0)
        c.move_to(Q0 + 0.01, 0.5, timeout=20.0)
    waits = [r for r in caplog.records if "waiting up to" in r.getMessage()]
    assert waits and all(r.levelno == logging.INFO for r in waits)
    caplog.clear()
    with fri_pair(limits, commanding=False, initial_position_rad=Q0,
                  url_query="rt_priority=0&session_wait_s=3.5") as (c, fake):
        c.wait_session(SessionState.MONITORING_READY, 10.0)
        with pytest.raises(DeviceFaultError, match="not COMMANDING_ACTIVE"):
            c.move_to(Q0 + 0.01, 0.5, timeout=20.0)
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "still MONITORING_READY" in r.getMessage()]
    assert len(warned) == 1
