"""NatNetSensor against FakeMotive over real loopback sockets: handshake, unicast and
multicast, NatNet 3.0 and 4.1, version negotiation, occlusion, loss / duplicates / reordering,
a silent server and a restarted one."""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest
from natnet_helpers import PLATE_MM, PLATE_ORIGIN_MM, PlateScene, need_loopback_multicast, wait_until

from drivers.errors import DeviceTimeoutError, ProtocolError, TargetLostError
from drivers.natnet import codec
from drivers.natnet.client import NatNetSensor
from drivers.natnet.fake import FakeMotive
from drivers.protocols import PositionSensor
from drivers.registry import load_driver

MARKERS = {"corner": "ms:tool:m1", "far": "lm:1:4", "plate": "rb:tool", "plate_by_id": "rb:1"}
TRUE_MM = PLATE_MM + PLATE_ORIGIN_MM


def sensor_for(fake: FakeMotive, markers=MARKERS, **kwargs) -> NatNetSensor:
    url = f"natnet://127.0.0.1:{fake.command_port}?local=127.0.0.1"
    if fake.multicast:
        need_loopback_multicast(fake.multicast_group)
        url += f"&multicast={fake.multicast_group}&data_port={fake.data_port}"
    return NatNetSensor.from_url(url, markers=markers, **kwargs)


def by_name(samples):
    return {s.marker: s for s in samples}


MODES = [
    pytest.param(False, (3, 0), id="unicast-3.0"),
    pytest.param(False, (4, 1), id="unicast-4.1"),
    pytest.param(True, (3, 0), id="multicast-3.0"),
    pytest.param(True, (4, 1), id="multicast-4.1"),
]


@pytest.mark.parametrize("multicast, version", MODES)
def test_reads_every_selected_marker_in_mm(still_scene, multicast, version):
    with FakeMotive(still_scene, natnet_version=version, multicast=multicast, rate_hz=240) as fake:
        with sensor_for(fake) as sensor:
            assert sensor.stream_version[:2] == version
            assert sensor.server_info.data_port == fake.data_port
            assert sensor.marker_names() == list(MARKERS)
            times = []
            for _ in range(5):
                before = time.monotonic()
                s = by_name(sensor.read(1.0))
                assert set(s) == set(MARKERS)
                assert all(x.visible for x in s.values())
                np.testing.assert_allclose(s["corner"].position_mm, TRUE_MM[1], atol=1e-3)
                np.testing.assert_allclose(s["far"].position_mm, TRUE_MM[3], atol=1e-3)
                np.testing.assert_allclose(s["plate"].position_mm, TRUE_MM.mean(axis=0), atol=1e-3)
                np.testing.assert_array_equal(s["plate"].position_mm, s["plate_by_id"].position_mm)
                assert before - 1.0 < s["far"].host_time <= time.monotonic()
                times.append(s["far"].device_time)
            assert np.all(np.diff(times) > 0), "each read must return a newer frame"
            m = sensor.measure("far", 8, 2.0)
            assert m.count == 8
            np.testing.assert_allclose(m.mean_mm, TRUE_MM[3], atol=1e-3)
            if not multicast:
                assert wait_until(lambda: len(fake.clients) == 1)
        if not multicast:  # DISCONNECT on close
            assert wait_until(lambda: fake.clients == [])


def test_sensor_satisfies_the_protocol_and_is_registered():
    sensor = NatNetSensor(markers={"a": "lm:1:1"})
    assert isinstance(sensor, PositionSensor)
    assert load_driver("natnet") is NatNetSensor


def test_occluded_and_missing_markers_are_reported_invisible(still_scene):
    with FakeMotive(still_scene, rate_hz=240) as fake, sensor_for(fake) as sensor:
        still_scene.hidden = {"m3"}
        assert wait_until(lambda: not by_name(sensor.read(1.0))["far"].visible)
        s = by_name(sensor.read(1.0))
        # occluded while the plate is tracked: Motive's model-predicted position
        np.testing.assert_allclose(s["far"].position_mm, TRUE_MM[3], atol=1e-3)
        assert s["corner"].visible and s["plate"].visible
        with pytest.raises(TargetLostError, match="far"):
            sensor.measure("far", 3, 1.0)
        still_scene.hidden = {"m2", "m3"}  # two of four left: the plate is lost
        assert wait_until(lambda: not by_name(sensor.read(1.0))["plate"].visible)
        s = by_name(sensor.read(1.0))
        assert not s["far"].visible and np.all(np.isnan(s["far"].position_mm))  # not sent at all
        assert s["corner"].visible  # a visible marker is still a labeled marker
        still_scene.hidden = set()
        assert wait_until(lambda: all(x.visible for x in sensor.read(1.0)))


def bitstream_requests(fake) -> list[str]:
    return [r for r in fake.requests if r.startswith("Bitstream")]


def reads_cleanly(sensor, n: int = 10) -> bool:
    """After one frame in the agreed layout, ``n`` more decode with no undecodable packet
    (frames sent in the old layout while the switch was answered may precede it)."""
    assert all(x.visible for x in sensor.read(1.0))
    bad = sensor.bad_packets
    return all(all(x.visible for x in sensor.read(1.0)) for _ in range(n)) and sensor.bad_packets == bad


def test_client_requests_bitstream_41_from_a_40_server(still_scene):
    with FakeMotive(still_scene, natnet_version=(4, 0), rate_hz=240) as fake:
        with sensor_for(fake, bitstream="4.1") as sensor:
            assert bitstream_requests(fake) == ["Bitstream,4.1"]
            assert fake.stream_version[:2] == (4, 1) and sensor.stream_version[:2] == (4, 1)
            assert reads_cleanly(sensor)
        # the bitstream is global: a client that asks for nothing must learn it is still 4.1
        with sensor_for(fake) as sensor:
            assert bitstream_requests(fake)[-1] == "Bitstream"
            assert sensor.stream_version[:2] == (4, 1)
            assert reads_cleanly(sensor) and sensor.bad_packets == 0
        fake.restart()  # back to the announced 4.0
        with sensor_for(fake) as sensor:
            assert sensor.stream_version[:2] == (4, 0)
            assert all(x.visible for x in sensor.read(1.0)) and sensor.bad_packets == 0


def test_bitstream_request_to_a_30_server_falls_back_to_its_version(still_scene):
    with FakeMotive(still_scene, natnet_version=(3, 0), rate_hz=240) as fake:
        with sensor_for(fake, bitstream="4.1") as sensor:
            assert bitstream_requests(fake) == []  # a 3.x server cannot switch, so nothing is asked
            assert sensor.stream_version[:2] == (3, 0)
            assert all(x.visible for x in sensor.read(1.0))


@pytest.mark.parametrize("multicast", [False, True], ids=["unicast", "multicast"])
def test_loss_duplicates_and_reordering_yield_only_newer_frames(still_scene, multicast):
    with FakeMotive(still_scene, multicast=multicast, rate_hz=360, seed=3) as fake:
        with sensor_for(fake) as sensor:
            fake.set_faults(drop=0.2, duplicate=0.3, reorder=0.3)
            stamps = [by_name(sensor.read(1.0))["far"].device_time for _ in range(80)]
            assert np.all(np.diff(stamps) > 0)
            # frames are numbered at 360 Hz, so a gap of more than one period is a lost or
            # skipped frame; the stream had duplicates and late frames that were dropped
            assert sensor.frames_stale > 5
            assert sensor.restarts == 0


@pytest.mark.parametrize("multicast", [False, True], ids=["unicast", "multicast"])
def test_silent_server_is_detected_within_the_silence_timeout(still_scene, multicast):
    silence = 0.2
    with FakeMotive(still_scene, multicast=multicast, rate_hz=240) as fake:
        with sensor_for(fake, silence_timeout_s=silence) as sensor:
            sensor.read(1.0)
            fake.stall()
            t_stall = time.monotonic()
            with pytest.raises(DeviceTimeoutError, match="silence limit"):
                while True:  # frames already in flight are still returned
                    sensor.read(10.0)
            detected = time.monotonic() - t_stall
            # the silence limit ended the read, not its own 10 s timeout (no tighter wall-clock
            # bound: a loaded machine may deliver the last in-flight frames late)
            assert detected < 5.0, f"silence noticed after {detected:.3f} s"
            fake.resume()
            assert wait_until(lambda: _reads(sensor))
            assert sensor.restarts == 0  # a pause is not a restart


def _reads(sensor) -> bool:
    try:
        return bool(sensor.read(0.1))
    except DeviceTimeoutError:
        return False


@pytest.mark.parametrize("multicast", [False, True], ids=["unicast", "multicast"])
def test_restart_with_a_large_back_jump_is_detected(still_scene, multicast):
    with FakeMotive(still_scene, multicast=multicast, rate_hz=360) as fake:
        with sensor_for(fake, reorder_window=30) as sensor:
            assert wait_until(lambda: by_name(sensor.read(1.0))["far"].device_time > 0.2)
            fake.restart()
            assert wait_until(lambda: sensor.restarts == 1)
            assert by_name(sensor.read(1.0))["far"].device_time < 0.2  # the new server's clock


def test_restart_within_the_reorder_window_is_detected_by_a_run_of_older_frames(still_scene):
    with FakeMotive(still_scene, multicast=True, rate_hz=360) as fake:
        with sensor_for(fake, reorder_window=100_000, restart_run=3) as sensor:
            assert wait_until(lambda: by_name(sensor.read(1.0))["far"].device_time > 0.1)
            fake.restart()
            assert wait_until(lambda: sensor.restarts == 1)
            assert sensor.frames_stale == 2  # the first two of the run were held as late frames
            assert by_name(sensor.read(1.0))["far"].device_time < 0.1


def test_unicast_client_rejoins_a_restarted_server_that_forgot_it(still_scene):
    with FakeMotive(still_scene, rate_hz=240) as fake:
        with sensor_for(fake, silence_timeout_s=0.1) as sensor:
            assert wait_until(lambda: by_name(sensor.read(1.0))["far"].device_time > 0.2)
            fake.restart(forget_clients=True)
            # the client notices the silence, sends CONNECT again, gets SERVERINFO and frames
            assert wait_until(lambda: _reads(sensor) and sensor.restarts == 1, timeout=10.0)
            assert len(fake.clients) == 1


def test_handshake_timeout_names_the_missing_reply():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as mute:
        mute.bind(("127.0.0.1", 0))
        sensor = NatNetSensor(markers={"a": "lm:1:1"}, command_port=mute.getsockname()[1],
                              handshake_timeout_s=0.2)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match="no SERVERINFO from 127.0.0.1"):
            sensor.connect()
        assert time.monotonic() - t0 < 1.0
        assert len(mute.recv(1024)) == 4 + 264  # it did send a NatNetLib-style CONNECT


def test_unknown_rigid_body_name_is_refused_at_connect(still_scene):
    with FakeMotive(still_scene) as fake:
        sensor = sensor_for(fake, markers={"x": "rb:wand"})
        with pytest.raises(ValueError, match=r"no rigid body named 'wand'.*\['tool'\]"):
            sensor.connect()
        sensor2 = sensor_for(fake, markers={"x": "ms:tool:m9"})
        with pytest.raises(ValueError, match="no marker 'm9' in marker set 'tool'"):
            sensor2.connect()


def test_from_url_reads_every_option():
    s = NatNetSensor.from_url(
        "natnet://10.0.0.5?command_port=1600&data_port=1601&multicast=239.255.42.99"
        "&local=127.0.0.1&bitstream=4.1&silence_timeout=0.3&units=mm&name=bar",
        markers={"a": "lm:2:1"},
    )
    assert (s.name, s.server, s.command_port, s.data_port, s.multicast, s.local) == (
        "bar", "10.0.0.5", 1600, 1601, "239.255.42.99", "127.0.0.1")
    assert s.bitstream == (4, 1, 0, 0) and s.silence_timeout_s == 0.3 and s.scale_mm == 1.0
    assert NatNetSensor.from_url("natnet://127.0.0.1:1700", markers={"a": "rb:1"}).command_port == 1700


@pytest.mark.parametrize("url, match", [
    ("http://127.0.0.1", "natnet://"),
    ("natnet://127.0.0.1?colour=red", "unknown NatNet URL option 'colour'"),
    ("natnet://127.0.0.1?command_port=abc", "not a number"),
    ("natnet://127.0.0.1?multicast=10.0.0.1", "group address"),
    ("natnet://127.0.0.1?units=inch", "units must be"),
    ("natnet://127.0.0.1?bitstream=2.10", "not supported"),
])
def test_bad_urls_say_what_is_allowed(url, match):
    with pytest.raises(ValueError, match=match):
        NatNetSensor.from_url(url, markers={"a": "lm:1:1"})


@pytest.mark.parametrize("markers, match", [
    ({}, "non-empty"),
    ({"a": "marker7"}, "not one of 'rb:"),
    ({"a": "lm:1"}, "not one of"),
    ({"a": "lm:70000:1"}, "not one of"),
])
def test_bad_marker_selectors_are_refused(markers, match):
    with pytest.raises(ValueError, match=match):
        NatNetSensor(markers=markers)


def test_fake_answers_echo_frame_request_and_bitstream_queries(still_scene):
    with FakeMotive(still_scene, natnet_version=(4, 1)) as fake:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
            addr = ("127.0.0.1", fake.command_port)

            def ask(msg):
                s.sendto(codec.encode_packet(msg), addr)
                return codec.decode_packet(s.recv(65536), fake.stream_version)

            assert ask(codec.EchoRequest(42)).client_stamp == 42
            assert ask(codec.Request("Bitstream")) == codec.Response(text="Bitstream,4.1")
            assert ask(codec.Request("Bitstream,3.0")) == codec.Response(code=0)
            assert fake.stream_version[:2] == (3, 0)
            assert ask(codec.Request("Bitstream,2.5")) == codec.Response(code=1)
            assert ask(codec.Request("MakeCoffee")) == codec.UnrecognizedRequest()
            frame = ask(codec.RequestFrameOfData())
            assert isinstance(frame, codec.FrameOfData) and len(frame.labeled_markers) == 4
            assert isinstance(ask(codec.Discovery("x")), codec.ServerInfo)
            assert fake.clients == []  # only CONNECT makes a unicast client


def test_fake_refuses_bad_settings_and_stops_its_threads(still_scene):
    with pytest.raises(ValueError, match="120–360"):
        FakeMotive(still_scene, rate_hz=1000)
    with pytest.raises(ValueError, match="natnet_version"):
        FakeMotive(still_scene, natnet_version=(2, 10))
    fake = FakeMotive(still_scene).start()
    threads = list(fake._threads)
    assert all(t.is_alive() for t in threads)
    fake.close()
    assert not any(t.is_alive() for t in threads)


def test_unicast_keepalives_keep_the_client_subscribed(still_scene):
    # the fake forgets a unicast client after 0.3 s without KEEPALIVE
    with FakeMotive(still_scene, rate_hz=240, client_timeout_s=0.3) as fake:
        with sensor_for(fake, keepalive_interval_s=0.05, silence_timeout_s=0.2) as sensor:
            t_end = time.monotonic() + 0.8
            while time.monotonic() < t_end:
                assert sensor.read(1.0)  # never silent: the subscription held
            assert fake.keepalives >= 8
            assert sensor.restarts == 0


def test_fake_binds_the_ports_it_is_given(still_scene):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with FakeMotive(still_scene, command_port=port, multicast=True) as fake:
        assert fake.command_port == port
        with sensor_for(fake) as sensor:
            assert sensor.command_port == port and sensor.read(1.0)


def test_fake_rigid_body_pose_maps_its_layout_onto_the_markers():
    now = [0.0]
    scene = PlateScene(omega_rad_s=2.0, clock=lambda: now[0])
    fake = FakeMotive(scene, rigid_body_id=7)
    fake.stall()
    fake.start()  # takes the start pose as the body's layout
    try:
        now[0] = 0.4  # the plate turns 0.8 rad
        frame = fake.make_frame()
    finally:
        fake.close()
    x, y, z, w = frame.rigid_bodies["quat"][0].astype(float)
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    assert np.degrees(2 * np.arccos(min(abs(w), 1.0))) == pytest.approx(np.degrees(0.8), abs=0.01)
    layout = np.array([m.offset for m in fake.model_def().rigid_bodies[0].markers])
    predicted_mm = (layout @ r.T + frame.rigid_bodies["pos"][0]) * 1000.0
    np.testing.assert_allclose(predicted_mm, frame.labeled_positions_mm(), atol=0.01)
    assert frame.model_ids.tolist() == [7] * 4 and frame.marker_ids.tolist() == [1, 2, 3, 4]


class BrokenModelDefMotive(FakeMotive):
    """Sends a MODELDEF with a dataset type nobody can read in NatNet 3.0."""

    def _send(self, packet, addr):
        if packet[:2] == struct.pack("<H", codec.NAT_MODELDEF):
            packet = struct.pack("<HHiiii", codec.NAT_MODELDEF, 16, 1, 99, 0, 0)
        super()._send(packet, addr)


def test_unreadable_model_definitions_only_matter_for_markers_chosen_by_name(still_scene):
    with BrokenModelDefMotive(still_scene, rate_hz=240) as fake:
        with sensor_for(fake, markers={"far": "lm:1:4", "plate": "rb:1"}) as sensor:
            assert sensor.model_def is None
            s = by_name(sensor.read(1.0))
            np.testing.assert_allclose(s["far"].position_mm, TRUE_MM[3], atol=1e-3)
        sensor = sensor_for(fake, markers={"corner": "ms:tool:m1"})
        t0 = time.monotonic()
        with pytest.raises(ProtocolError, match=r"model definitions .*dataset type 99.*\['corner'\]"):
            sensor.connect()
        assert time.monotonic() - t0 < sensor.handshake_timeout_s  # told at once, not timed out
