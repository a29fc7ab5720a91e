"""TrackerSensor against the fake tracker over real transports (TCP loopback and a pty).

The ``tracker`` fixture is parametrised over both transports, so every test in the contract
part runs twice. Simulated time runs 1000× faster than wall time.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from drivers.errors import (
    ConnectionLostError,
    DeviceFaultError,
    DeviceTimeoutError,
    LimitError,
    ProtocolError,
    TargetLostError,
)
from drivers.protocols import MarkerMeasurement, PositionSensor
from drivers.registry import load_driver
from drivers.tracker.client import DistanceLostError, TrackerSensor, TrackerWarmingUpError
from drivers.tracker.codec import Environment, GetStatus, LineCodec, Mode
from drivers.tracker.fake import FakeTracker, PtyTrackerServer, TcpTrackerServer

TRUE_MM = np.array([2000.0, 300.0, -100.0])
SIGMA_MM = 0.015 + 0.006 * np.linalg.norm(TRUE_MM) / 1000.0


def break_beam(tracker, scene):
    """Block the line of sight, let the tracker notice, then clear it again."""
    scene.visible = False
    assert tracker.status().locked is False
    scene.visible = True


# ----------------------------------------------------------------------------- contract


def test_registry_name_tracker_loads_a_position_sensor(tracker):
    assert load_driver("tracker") is TrackerSensor
    assert isinstance(tracker, PositionSensor)
    assert tracker.marker_names() == ["smr"]


def test_identify_and_status_of_a_warm_locked_tracker(tracker):
    ident = tracker.identify()
    assert (ident.vendor, ident.model, ident.protocol) == ("remaster", "SIMTRACKER-1", 1)
    st = tracker.status()
    assert (st.locked, st.mode, st.warmed_up, st.distance_valid) == (True, Mode.ADM, True, True)


def test_read_returns_one_sample_with_device_and_host_time(tracker):
    before = tracker.clock()
    s1, = tracker.read(timeout=1.0)
    s2, = tracker.read(timeout=1.0)
    after = tracker.clock()
    assert s1.visible and s1.marker == "smr"
    assert np.all(np.abs(s1.position_mm - TRUE_MM) < 6 * SIGMA_MM)
    assert s1.std_mm == pytest.approx(SIGMA_MM, abs=1e-4)
    assert before <= s1.host_time <= s2.host_time <= after
    assert s2.device_time > s1.device_time > 0


def test_measure_uses_the_device_average_with_the_specified_noise(tracker, server):
    seen = server.requests_seen
    m = tracker.measure("smr", 2000, timeout=5.0)
    assert server.requests_seen == seen + 1  # one AVG, not 2000 MEAS
    assert isinstance(m, MarkerMeasurement) and m.count == 2000
    assert np.all(np.abs(m.mean_mm - TRUE_MM) < 5 * SIGMA_MM / math.sqrt(2000))
    # per-axis sample std of 2000 normal points is within ~5 % of σ at 3 standard errors
    assert np.allclose(m.std_mm, SIGMA_MM, rtol=0.06)
    assert m.host_time > 0 and m.device_time > 0


def test_noise_grows_with_distance(tracker, scene):
    scene.position_mm = np.array([10_000.0, 0.0, 0.0])
    tracker.aim(scene.position_mm)
    m = tracker.measure("smr", 2000, timeout=5.0)
    assert np.allclose(m.std_mm, 0.015 + 0.006 * 10, rtol=0.06)


def test_measure_refuses_an_unknown_marker_and_bad_counts(tracker):
    with pytest.raises(ValueError, match="measures marker 'smr', not 'tcp'"):
        tracker.measure("tcp", 10, timeout=1.0)
    with pytest.raises(ValueError, match="n must be an integer in 1..100000"):
        tracker.measure("smr", 0, timeout=1.0)


def test_beam_break_raises_target_lost_and_stays_lost_after_sight_returns(tracker, scene):
    scene.visible = False
    with pytest.raises(TargetLostError, match="error 10"):
        tracker.measure("smr", 10, timeout=1.0)
    sample, = tracker.read(timeout=1.0)
    assert sample.visible is False and np.all(np.isnan(sample.position_mm))
    scene.visible = True  # line of sight back, but the tracker has lost lock
    with pytest.raises(TargetLostError):
        tracker.measure("smr", 10, timeout=1.0)
    assert tracker.status().locked is False
    assert [e.name for e, _ in tracker.events] == ["BEAM_LOST"]


def test_aim_within_capture_radius_reacquires(tracker, scene):
    break_beam(tracker, scene)
    tracker.aim(TRUE_MM + [0.0, 3.0, 2.0])  # 3.6 mm off the reflector, capture radius 5 mm
    assert tracker.status().locked
    m = tracker.measure("smr", 100, timeout=2.0)
    assert np.all(np.abs(m.mean_mm - TRUE_MM) < 0.05)
    assert [e.name for e, _ in tracker.events] == ["BEAM_LOST", "BEAM_LOCKED"]


def test_aim_outside_capture_radius_fails(tracker, scene):
    break_beam(tracker, scene)
    with pytest.raises(TargetLostError, match="no reflector within the capture radius"):
        tracker.aim(TRUE_MM + [0.0, 6.0, 0.0])
    assert tracker.status().locked is False


def test_aim_at_a_blocked_reflector_does_not_lock(tracker, scene):
    break_beam(tracker, scene)
    scene.visible = False
    with pytest.raises(TargetLostError):
        tracker.aim(TRUE_MM)


def test_spiral_search_finds_a_reflector_off_the_beam(tracker, scene):
    break_beam(tracker, scene)
    with pytest.raises(TargetLostError):
        tracker.aim(TRUE_MM + [0.0, 30.0, 0.0])
    found = tracker.search(radius_mm=50.0, timeout=60.0)
    assert found.found and found.turns > 3
    assert tracker.status().locked
    assert np.all(np.abs(tracker.measure("smr", 100, 2.0).mean_mm - TRUE_MM) < 0.05)


def test_spiral_search_time_grows_with_the_square_of_the_offset(tracker, scene):
    elapsed = []
    for offset in (20.0, 40.0):
        break_beam(tracker, scene)
        with pytest.raises(TargetLostError):
            tracker.aim(TRUE_MM + [0.0, 0.0, offset])
        elapsed.append(tracker.search(radius_mm=100.0, timeout=600.0).elapsed_s)
    # path length of an Archimedean spiral ∝ ρ²; the hit is at ρ minus the capture radius
    assert elapsed[1] / elapsed[0] == pytest.approx(((40 - 5) / (20 - 5)) ** 2, rel=0.05)


def test_spiral_search_fails_when_the_reflector_is_beyond_its_radius_or_time(tracker, scene):
    break_beam(tracker, scene)
    with pytest.raises(TargetLostError):
        tracker.aim(TRUE_MM + [0.0, 80.0, 0.0])
    with pytest.raises(TargetLostError, match="radius 50 mm found no reflector"):
        tracker.search(radius_mm=50.0, timeout=600.0)
    with pytest.raises(TargetLostError, match="found no reflector in 0.50 s"):
        tracker.search(radius_mm=200.0, timeout=0.5)
    with pytest.raises(TargetLostError, match=r"\(2.0 turns\)"):
        tracker.search(radius_mm=200.0, timeout=600.0, max_turns=2)
    assert tracker.search(radius_mm=200.0, timeout=600.0).found


def test_ifm_loses_its_distance_on_a_beam_break_until_home(tracker, scene):
    assert tracker.set_mode("ifm").distance_valid is False  # switching to IFM needs HOME
    tracker.home()
    tracker.measure("smr", 10, timeout=1.0)
    break_beam(tracker, scene)
    tracker.aim(TRUE_MM)  # locked again, but the interferometer count is gone
    st = tracker.status()
    assert st.locked and not st.distance_valid
    with pytest.raises(DistanceLostError, match="send HOME"):
        tracker.measure("smr", 10, timeout=1.0)
    tracker.home()
    assert tracker.status().distance_valid
    tracker.measure("smr", 10, timeout=1.0)


def test_adm_measures_again_as_soon_as_the_beam_relocks(tracker, scene):
    assert tracker.set_mode(Mode.ADM).distance_valid is True
    break_beam(tracker, scene)
    assert tracker.status().distance_valid is False
    tracker.aim(TRUE_MM)
    assert tracker.status().distance_valid is True
    tracker.measure("smr", 10, timeout=1.0)


def test_reacquire_aims_then_searches_then_homes(tracker, scene):
    tracker.set_mode("IFM")
    tracker.home()
    break_beam(tracker, scene)
    tracker.reacquire(TRUE_MM + [25.0, 0.0, 20.0], search_radius_mm=60.0)
    assert tracker.status().distance_valid
    tracker.measure("smr", 10, timeout=1.0)


def test_bad_arguments_are_refused_before_sending(tracker):
    with pytest.raises(ValueError, match="mode must be one of ADM, IFM"):
        tracker.set_mode("laser")
    with pytest.raises(ValueError, match="aim point must be 3 finite numbers"):
        tracker.aim([1.0, 2.0])
    with pytest.raises(ValueError, match=r"radius_mm must be in \(0, 10000\]"):
        tracker.search(radius_mm=-5, timeout=1.0)


# ----------------------------------------------------------------------------- device states


def test_a_cold_tracker_refuses_to_measure_until_warm(make_device):
    with TcpTrackerServer(make_device(warmup_s=1000.0)) as srv, TrackerSensor.from_url(srv.url) as t:
        st = t.status()
        assert not st.warmed_up and not st.temperature_stable and st.warmup_left_s > 900
        with pytest.raises(TrackerWarmingUpError, match=r"error 20: warming up, \d+\.\d s left"):
            t.measure("smr", 10, timeout=1.0)
        with pytest.raises(TrackerWarmingUpError):
            t.read(timeout=1.0)
        t.aim(TRUE_MM)  # aiming is allowed while cold


def test_warm_up_ends_after_its_duration(make_device, manual_clock):
    with TcpTrackerServer(make_device(warmup_s=50.0, clock=manual_clock)) as srv, \
            TrackerSensor.from_url(srv.url) as t:
        manual_clock.advance(49.0)
        assert t.status().warmup_left_s == pytest.approx(1.0)
        with pytest.raises(TrackerWarmingUpError, match="1.0 s left"):
            t.measure("smr", 10, timeout=1.0)
        manual_clock.advance(1.0)
        st = t.status()
        assert st.warmed_up and st.temperature_stable and st.warmup_left_s == 0
        t.measure("smr", 10, timeout=1.0)


def test_device_without_average_falls_back_to_single_points(make_device):
    with TcpTrackerServer(make_device(supports_average=False)) as srv, TrackerSensor.from_url(srv.url) as t:
        m = t.measure("smr", 20, timeout=5.0)
        assert m.count == 20 and srv.requests_seen == 21  # one refused AVG, then 20 MEAS
        assert np.all(np.abs(m.mean_mm - TRUE_MM) < 0.05)


# ----------------------------------------------------------------------------- faults


def test_a_stalled_device_times_out_and_its_late_reply_is_discarded(tracker, server):
    server.stall(0.4)
    with pytest.raises(DeviceTimeoutError, match=r"no reply to '\d+ STATUS\*.*' within 0.15 s"):
        tracker.request(GetStatus(), timeout=0.15)
    ident = tracker.identify()  # the late STATUS reply arrives first and is dropped by its id
    assert ident.vendor == "remaster"


def test_a_garbled_reply_raises_protocol_error_and_the_next_request_works(tracker, server):
    server.garble(1)
    with pytest.raises(ProtocolError, match="checksum|not printable|reply"):
        tracker.status()
    assert tracker.status().locked


def test_dropped_tcp_connection_is_retried_transparently(device):
    with TcpTrackerServer(device) as srv, TrackerSensor.from_url(srv.url) as t:
        t.identify()
        srv.drop()
        assert srv.connection_count == 0
        sample, = t.read(timeout=1.0)  # reconnects and sends again
        assert sample.visible
        assert srv.connection_count == 1


def test_dropped_tcp_connection_without_auto_reconnect_then_reconnect(device):
    with TcpTrackerServer(device) as srv, TrackerSensor.from_url(srv.url, auto_reconnect=False) as t:
        t.identify()  # the server has accepted the connection
        srv.drop()
        with pytest.raises(ConnectionLostError, match="connection to socket://127.0.0.1:\\d+ lost"):
            t.status()
        assert not t.connected
        with pytest.raises(ConnectionLostError, match="not connected"):
            t.status()
        t.reconnect()
        assert t.status().locked


def test_search_is_not_resent_after_a_drop(device, scene):
    with TcpTrackerServer(device) as srv, TrackerSensor.from_url(srv.url) as t:
        break_beam(t, scene)
        srv.drop()
        with pytest.raises(ConnectionLostError):
            t.search(radius_mm=10.0, timeout=1.0)


def test_connection_refused_is_a_connection_lost_error(device):
    srv = TcpTrackerServer(device)
    url = srv.url
    srv.close()
    with pytest.raises(ConnectionLostError, match="cannot open 'socket://127.0.0.1"):
        TrackerSensor.from_url(url)


def test_pty_hang_up_is_a_connection_lost_error(device):
    with PtyTrackerServer(device) as srv, TrackerSensor.from_url(srv.path, auto_reconnect=False) as t:
        assert t.status().locked
        srv.drop()
        with pytest.raises(ConnectionLostError):
            t.status()


def test_loop_url_echo_is_detected_as_a_protocol_error():
    # pyserial's loop:// hands our own request back: it must not pass for a reply.
    with TrackerSensor.from_url("loop://", reply_timeout=0.5) as t:
        with pytest.raises(ProtocolError, match=r"reply: expected '<id> OK <VERB> \.\.\.'.*got '1 ID'"):
            t.identify()
        with pytest.raises(ProtocolError, match="second word must be OK or ERR, got 'AVG'"):
            t.measure("smr", 3, timeout=0.5)


def test_bad_url_is_a_value_error():
    with pytest.raises(ValueError, match="bad URL or option"):
        TrackerSensor.from_url("nonsense://x")
    with pytest.raises(ValueError, match="url must be a pyserial URL"):
        TrackerSensor("")


def test_fake_listens_on_loopback_only(device):
    with pytest.raises(ValueError, match="loopback only"):
        TcpTrackerServer(device, host="0.0.0.0")


def test_servers_stop_their_threads_on_close(device):
    import threading

    before = set(threading.enumerate())
    srv = TcpTrackerServer(device)
    with TrackerSensor.from_url(srv.url) as t:
        t.status()
    pty = PtyTrackerServer(device)
    srv.close()
    pty.close()
    assert set(threading.enumerate()) <= before


# ----------------------------------------------------------------------------- hardware


@pytest.mark.hil
@pytest.mark.skipif(os.environ.get("REMASTER_HIL") != "1" or not os.environ.get("REMASTER_TRACKER_URL"),
                    reason="needs REMASTER_HIL=1 and REMASTER_TRACKER_URL of a real tracker")
def test_real_tracker_answers_identify_status_and_measure():
    with TrackerSensor.from_url(os.environ["REMASTER_TRACKER_URL"]) as t:
        assert t.identify().protocol == 1
        st = t.status()
        if st.locked and st.distance_valid and st.warmed_up:
            m = t.measure("smr", 10, timeout=10.0)
            assert np.all(np.isfinite(m.mean_mm))


# ----------------------------------------------------------------------------- device logic


def test_search_spends_device_time_for_its_path_length(make_device, scene, manual_clock):
    scene.position_mm = np.array([2000.0, 0.0, 0.0])  # on the x axis: 25 mm in y is lateral
    device = make_device(clock=manual_clock, adm_lock_s=0.0, search_speed_mm_s=100.0)
    with TcpTrackerServer(device) as srv, TrackerSensor.from_url(srv.url) as t:
        break_beam(t, scene)
        with pytest.raises(TargetLostError):
            t.aim([2000.0, 25.0, 0.0])
        before = t.status().device_time
        found = t.search(radius_mm=50.0, timeout=100.0)
        # reached at ρ = 25 − 5 mm: arc length π·20²/5 mm at 100 mm/s
        assert found.elapsed_s == pytest.approx(math.pi * 20**2 / 5 / 100, abs=2e-3)
        assert found.device_time - before == pytest.approx(found.elapsed_s, abs=2e-3)


def test_a_break_between_commands_is_caught_by_the_idle_tick(device, scene):
    scene.visible = False
    device.tick()  # the servers call this while no request is pending
    scene.visible = True
    assert device.locked is False
    rid, reply = LineCodec().decode_reply(device.handle(b"5 MEAS\n"))
    assert (rid, reply.code) == (5, 10)


def test_fake_refuses_nonsense_configuration(scene):
    with pytest.raises(ValueError, match="capture_radius_mm must be a positive number, got 0"):
        FakeTracker(scene, capture_radius_mm=0)
    with pytest.raises(ValueError, match="warmup_s must be a non-negative number"):
        FakeTracker(scene, warmup_s=-1)


def test_a_closed_sensor_is_not_reopened_behind_the_callers_back(tcp_server):
    t = TrackerSensor.from_url(tcp_server.url)
    t.close()
    with pytest.raises(ConnectionLostError, match="not connected .* call connect"):
        t.status()
    t.connect()
    assert t.status().locked
    t.close()


def test_a_beam_break_during_an_average_raises_target_lost(tracker, device, scene):
    device.tick = lambda: None  # keep the idle monitor from using up the scene's countdown
    scene.break_after = 1  # visible at the start of the average, broken at its end
    with pytest.raises(TargetLostError, match="beam lost during the 500-point average"):
        tracker.measure("smr", 500, timeout=2.0)
    assert tracker.status().locked is False


def test_env_from_the_host_scales_distances_by_the_refraction_ratio(make_device, scene):
    from drivers.tracker.air import Air, range_scale

    device = make_device(noise_um=0.0, noise_um_per_m=0.0)
    with TcpTrackerServer(device, seed=3) as srv:
        air = {"temperature_c": 28.0, "pressure_hpa": 985.5, "humidity_pct": 30.0}
        with TrackerSensor.from_url(srv.url, environment=air) as t:
            assert (t.air_in_use.source, t.air_in_use.temperature_c, t.air_in_use.pressure_hpa) == ("HOST", 28.0, 985.5)
            got = t.measure("smr", 10, 5.0).mean_mm
    assert device.assumed_air == Air(**air)
    assert np.allclose(got, np.asarray(scene.position_mm) * range_scale(Air(), Air(**air)), atol=2e-4)


def test_env_from_the_station_and_a_tracker_without_one(make_device):
    from drivers.tracker.air import Air

    with TcpTrackerServer(make_device(air=Air(23.4, 1002.0, 40.0)), seed=3) as srv:
        with TrackerSensor.from_url(srv.url, environment={"source": "station"}) as t:
            a = t.air_in_use
            assert (a.source, a.temperature_c, a.pressure_hpa, a.humidity_pct) == ("STATION", 23.4, 1002.0, 40.0)
            assert t.set_environment(Air(20.0, 1013.25, 50.0)).source == "HOST"
    with TcpTrackerServer(make_device(weather_station=False), seed=3) as srv:
        with pytest.raises(DeviceFaultError, match="no weather station"):
            TrackerSensor.from_url(srv.url, environment="station")


def test_reflector_type_and_offset_are_selected(tracker, server):
    reply = tracker.select_reflector("TBR05")
    assert (reply.reflector_type, reply.offset_mm) == ("TBR05", 6.35)
    reply = tracker.select_reflector("RRR15", 19.0)
    assert (reply.reflector_type, reply.offset_mm) == ("RRR15", 19.0)
    assert server.device.reflector_kind.name == "RRR15" and server.device.reflector_offset_mm == 19.0
    with pytest.raises(LimitError, match="unknown reflector type 'SMR78'; known: RRR15"):
        tracker.select_reflector("SMR78")
    with pytest.raises(ValueError, match="temp"):
        tracker.request(Environment("HOST", 99.0, 1000.0, 50.0))
