"""EmsconSensor against the fake emScon server over TCP loopback: preparation, measuring,
beam breaks and re-acquisition, air and reflector, refusals and transport faults."""

from __future__ import annotations

import os
import socket

import numpy as np
import pytest

from drivers import errors
from drivers.emscon import codec as es
from drivers.emscon.client import EmsconSensor, parse_url
from drivers.protocols import PositionSensor
from drivers.registry import load_driver
from drivers.tracker.air import Air, range_scale


def test_registry_name_emscon_loads_a_position_sensor(sensor):
    assert load_driver("emscon") is EmsconSensor
    assert isinstance(sensor, PositionSensor)


def test_connect_initialises_and_sets_mm_rhr_stationary(make_server):
    # the server starts in metres and uninitialised; the sensor leaves it in mm, initialised
    srv = make_server(server={"units": {"lenUnitType": int(es.LengthUnit.Meter)}})
    dev = srv.device
    with EmsconSensor(srv.url) as s:
        assert dev.initialized
        assert dev.units["lenUnitType"] == es.LengthUnit.Millimeter
        assert dev.units["pressUnitType"] == es.PressureUnit.HPascal
        assert dev.coord_sys is es.CoordinateSystem.RHR and dev.meas_mode is es.MeasMode.Stationary
        st = s.status()
        assert st.initialized and st.locked and st.ready and st.server_version[:2] == (3, 6)


def test_initialize_is_sent_only_when_the_server_needs_it(make_server):
    srv = make_server(server={"require_initialize": False})
    seen_before = srv.device.commands_seen
    with EmsconSensor(srv.url):
        pass
    with EmsconSensor(srv.url, initialize="never") as s:
        assert s.measure("smr", 5, 5.0).count == 5
    assert srv.device.commands_seen > seen_before


def test_measure_averages_n_points_with_the_fake_noise(sensor, server, scene):
    m = sensor.measure("smr", 1000, 10.0)
    sigma = server.device.tracker.sigma_mm(float(np.linalg.norm(scene.position_mm)))
    assert m.count == 1000 and np.isnan(m.device_time)
    assert np.all(np.abs(m.mean_mm - scene.position_mm) < 5 * sigma / np.sqrt(1000))
    assert np.allclose(m.std_mm, sigma, rtol=0.15)
    assert server.device.meas_time_ms == 1000  # 1000 points at 1000 Hz
    r = sensor.read(5.0)[0]
    assert r.visible and np.all(np.abs(r.position_mm - scene.position_mm) < 5 * sigma / np.sqrt(10))


def test_beam_break_is_target_lost_and_stays_lost_until_aimed(sensor, scene):
    scene.visible = False
    with pytest.raises(errors.TargetLostError) as exc:
        sensor.measure("smr", 10, 5.0)
    assert exc.value.status == es.Status.MeasurementStatusNotReady
    assert sensor.read(5.0)[0].visible is False
    assert sensor.beam_ready is False  # the MeasStatus_NotReady notification arrived
    scene.visible = True
    with pytest.raises(errors.TargetLostError):  # sight is back, the beam is not
        sensor.measure("smr", 10, 5.0)
    sensor.aim(scene.position_mm + [0.0, 3.0, 0.0])  # within the 5 mm capture radius
    assert sensor.measure("smr", 10, 5.0).count == 10
    assert sensor.beam_ready is True


def test_aim_far_from_the_reflector_raises_and_search_finds_it(sensor, scene):
    with pytest.raises(errors.TargetLostError, match="no reflector"):
        sensor.aim(scene.position_mm + [0.0, 30.0, 0.0])
    found = sensor.search(50.0, 10.0)
    assert found.found and found.elapsed_s > 0
    assert sensor.status().locked


def test_search_beyond_its_radius_fails(sensor, scene):
    with pytest.raises(errors.TargetLostError):
        sensor.aim(scene.position_mm + [0.0, 200.0, 0.0])
    with pytest.raises(errors.TargetLostError, match="FindReflector"):
        sensor.search(50.0, 10.0)


def test_reacquire_aims_then_searches(sensor, scene):
    with pytest.raises(errors.TargetLostError):
        sensor.aim([0.0, 3000.0, 0.0])
    sensor.reacquire(scene.position_mm + [0.0, 20.0, 0.0], search_radius_mm=50.0, timeout=10.0)
    assert sensor.measure("smr", 5, 5.0).count == 5


def test_a_beam_break_during_the_measurement_is_no_stationary_result(sensor, server, scene):
    tracker = server.device.tracker
    real = scene.observe
    calls = {"n": 0}

    def breaking(name):
        calls["n"] += 1
        if calls["n"] > 2:
            scene.visible = False
        return real(name)

    scene.observe = breaking
    with pytest.raises(errors.TargetLostError) as exc:
        sensor.measure("smr", 100, 5.0)
    assert exc.value.status == es.Status.NoStationaryResult
    assert not tracker.locked


def test_air_from_the_plan_changes_distances_by_the_refraction_ratio(make_server, scene):
    srv = make_server(tracker={"noise_um": 0.0, "noise_um_per_m": 0.0})
    warm_air = {"temperature_c": 30.0, "pressure_hpa": 980.0, "humidity_pct": 20.0}
    with EmsconSensor(srv.url, environment=warm_air) as s:
        got = s.measure("smr", 10, 5.0).mean_mm
        assert s.air_in_use == Air(30.0, 980.0, 20.0) and s.air_source == "host"
    expected = scene.position_mm * range_scale(Air(), Air(**warm_air))
    assert np.allclose(got, expected, atol=1e-9)
    assert abs(np.linalg.norm(got) / np.linalg.norm(scene.position_mm) - 1) > 5e-6  # ppm-sized, not zero


def test_weather_station_source_applies_what_the_station_reads(make_server, scene):
    srv = make_server(tracker={"noise_um": 0.0, "noise_um_per_m": 0.0, "air": Air(24.0, 1001.0, 35.0)})
    with EmsconSensor(srv.url, environment={"source": "station"}) as s:
        assert s.air_in_use == Air(24.0, 1001.0, 35.0) and s.air_source == "station"
        assert np.allclose(s.measure("smr", 5, 5.0).mean_mm, scene.position_mm, atol=1e-9)  # true air used
        assert s.status().weather_monitor == es.WeatherMonitorStatus.ReadAndCalculateRefractions


def test_no_weather_station_is_a_device_fault_naming_the_fix(make_server):
    srv = make_server(tracker={"weather_station": False})
    with pytest.raises(errors.DeviceFaultError, match="NoWeathermonitorFound"):
        EmsconSensor(srv.url, environment="station").connect()


def test_out_of_range_air_is_refused_before_sending():
    with pytest.raises(ValueError, match="temperature_c"):
        EmsconSensor("emscon://127.0.0.1:1", environment={"temperature_c": 99, "pressure_hpa": 1000, "humidity_pct": 5})


def test_reflector_is_selected_by_name_and_its_offset_checked(make_server):
    srv = make_server()
    with EmsconSensor(srv.url, reflector={"type": "tbr05", "offset_mm": 6.35}) as s:
        assert s.reflector_in_use[1] == "TBR05"
        assert srv.device.tracker.reflector_kind.name == "TBR05"
        with pytest.raises(errors.LimitError, match="19.0500 mm in the emScon database"):
            s.select_reflector("RRR15", 12.7)
        with pytest.raises(errors.LimitError, match="no reflector 'SMR-7/8'.*RRR15"):
            s.select_reflector("SMR-7/8")
        assert srv.device.tracker.reflector_kind.name == "TBR05"  # nothing changed on a refusal


def test_a_cold_tracker_refuses_with_warming_up(make_server):
    srv = make_server(tracker={"warmup_s": 3600.0})
    with EmsconSensor(srv.url) as s:
        assert not s.status().warmed_up
        with pytest.raises(errors.TrackerWarmingUpError, match="SensorNotWarmedUp"):
            s.measure("smr", 5, 5.0)


def test_never_initialising_a_fresh_server_is_refused_with_the_fix(make_server):
    srv = make_server()
    with EmsconSensor(srv.url, initialize="never") as s:
        with pytest.raises(errors.DeviceFaultError, match="TrackerNotInitialized.*Initialize"):
            s.measure("smr", 5, 5.0)


def test_a_stalled_server_times_out_and_the_next_command_reconnects(sensor, server):
    server.stall(1.0)
    with pytest.raises(errors.DeviceTimeoutError):
        sensor.request(es.Request(es.Cmd.GetTrackerStatus), timeout=0.2)
    assert not sensor.connected  # the late answer cannot be taken for the next command's
    assert sensor.measure("smr", 5, 5.0).count == 5


def test_a_dropped_connection_is_reopened_by_the_next_command(sensor, server):
    server.drop()
    with pytest.raises(errors.ConnectionLostError):
        sensor.measure("smr", 5, 5.0)
    assert sensor.measure("smr", 5, 5.0).count == 5


def test_garbled_answers_raise_only_driver_errors(sensor, server):
    outcomes = {"ok": 0, "error": 0}
    for _ in range(150):
        server.garble(1)
        try:
            sensor.read(1.0)
            sensor.status()
            outcomes["ok"] += 1
        except errors.DriverError:
            outcomes["error"] += 1
    assert outcomes["error"] > 0  # the garbling reached the client
    assert sensor.measure("smr", 5, 5.0).count == 5  # and it recovers


def test_the_fake_answers_every_garbled_request_with_readable_packets(server):
    rng = np.random.default_rng(4)
    from test_emscon_codec import _mutate, _valid_requests

    pool = _valid_requests()
    dev = server.device
    answered = 0
    for k in range(10_000):
        data = _mutate(rng, pool[k % len(pool)])
        if len(data) >= 8 and not es.MIN_PACKET <= int.from_bytes(data[:4], "little", signed=True) <= es.MAX_PACKET:
            continue  # framing refuses it before the device sees it
        out = bytearray(dev.handle(data))
        frames = es.split_frames(out)
        assert frames and not out
        for f in frames:
            assert isinstance(es.decode(f), (es.Answer, es.ErrorAnswer, es.DataResult, es.StatusChange))
        answered += 1
    assert answered > 5_000


def test_bad_urls_and_refused_connections():
    assert parse_url("emscon://10.0.0.5") == ("10.0.0.5", 700)
    for bad in ("socket://h:700", "emscon://", "emscon://h:99999", "emscon://h/x"):
        with pytest.raises(ValueError, match="emscon://host"):
            EmsconSensor(bad)
    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    with pytest.raises(errors.ConnectionLostError, match="default 700"):
        EmsconSensor(f"emscon://127.0.0.1:{port}").connect()


def test_fake_server_refuses_what_it_does_not_emulate(sensor):
    with pytest.raises(errors.ProtocolError, match="NotImplemented"):
        sensor.request(es.Request(es.Cmd.SetCoordinateSystemType, {"coordSysType": int(es.CoordinateSystem.SCW)}))
    with pytest.raises(errors.LimitError, match="Parameter1OutOfRangeNOK"):
        sensor.request(es.Request(es.Cmd.SetStationaryModeParams, {"lMeasTime": 0, "bUseADM": 1}))


@pytest.mark.hil
@pytest.mark.skipif(os.environ.get("REMASTER_HIL") != "1" or not os.environ.get("REMASTER_EMSCON_URL"),
                    reason="needs REMASTER_HIL=1 and REMASTER_EMSCON_URL (emscon://host:700) of a real emScon server")
def test_real_emscon_server_reports_status_and_measures():
    with EmsconSensor(os.environ["REMASTER_EMSCON_URL"], initialize_timeout=180.0) as s:
        st = s.status()
        assert st.initialized and st.server_version[0] >= 3
        assert s.reflectors()  # the server's reflector database is readable
        if st.ready:
            m = s.measure("smr", 1000, timeout=30.0)
            assert np.all(np.isfinite(m.mean_mm)) and np.all(m.std_mm < 1.0)
