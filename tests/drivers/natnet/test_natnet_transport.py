"""How frames reach the client as Motive is really configured: the client follows the
multicast announcement in SERVERINFO (fake Motive and a replay of a real Motive 2.1), says what
to set when it cannot, refuses NatNet versions above 4.1 unless the server switches down, and
reads the FrameRate reply as a float32."""

from __future__ import annotations

import dataclasses
import socket
import struct
import threading

import numpy as np
import pytest
from natnet_helpers import PLATE_MM, PLATE_ORIGIN_MM, capture, need_loopback_multicast, wait_until

from drivers.errors import ConnectionLostError, DeviceTimeoutError, ProtocolError
from drivers.natnet import codec
from drivers.natnet.client import NatNetSensor
from drivers.natnet.fake import FakeMotive

TRUE_MM = PLATE_MM + PLATE_ORIGIN_MM
MARKERS = {"far": "lm:1:4", "plate": "rb:tool"}


def plain_sensor(fake, **kwargs) -> NatNetSensor:
    """A sensor given only the server's address, as a plan names Motive."""
    return NatNetSensor.from_url(f"natnet://127.0.0.1:{fake.command_port}", markers=MARKERS, **kwargs)


def by_name(samples):
    return {s.marker: s for s in samples}


# ----------------------------------------------------------------------------- multicast announcement


@pytest.mark.parametrize("version", [(3, 0), (4, 1)], ids=["3.0", "4.1"])
def test_client_without_options_joins_the_announced_multicast_group(still_scene, version):
    need_loopback_multicast()
    with FakeMotive(still_scene, natnet_version=version, multicast=True, rate_hz=240) as fake:
        info = fake.server_info()
        assert (info.multicast, info.multicast_address, info.data_port) == (True, "239.255.42.99", fake.data_port)
        with plain_sensor(fake) as sensor:
            assert (sensor.stream_group, sensor.stream_port) == ("239.255.42.99", fake.data_port)
            assert sensor.local == "127.0.0.1"  # the route to the server leaves from loopback
            for _ in range(3):
                s = by_name(sensor.read(1.0))
                np.testing.assert_allclose(s["far"].position_mm, TRUE_MM[3], atol=1e-3)
                np.testing.assert_allclose(s["plate"].position_mm, TRUE_MM.mean(axis=0), atol=1e-3)
            assert sensor.frames_accepted >= 3
            keepalives = fake.keepalives
        assert fake.keepalives == keepalives  # a multicast client sends no unicast keep-alives


def test_client_without_options_stays_unicast_when_the_server_announces_unicast(still_scene):
    with FakeMotive(still_scene, multicast=False, rate_hz=240) as fake:
        with plain_sensor(fake, keepalive_interval_s=0.05) as sensor:
            assert sensor.stream_group is None and sensor.read(1.0)
            assert wait_until(lambda: fake.keepalives >= 2)


def test_a_frame_begun_before_stall_is_sent_before_stall_returns(still_scene):
    """A test stalls the fake before a client joins so the client's first frame comes after
    SERVERINFO. A frame the stream thread had already begun (the host busy between its stall
    check and its send) must not reach the socket after ``stall()`` has returned."""
    begun, release = threading.Event(), threading.Event()
    observe = still_scene.observe
    test_thread = threading.current_thread()

    def slow_observe(sensor):  # the stream thread pauses inside its first frame
        if threading.current_thread() is not test_thread and not release.is_set():
            begun.set()
            release.wait(10.0)
        return observe(sensor)

    still_scene.observe = slow_observe
    with FakeMotive(still_scene, multicast=True, rate_hz=240) as fake:
        assert begun.wait(10.0), "the fake never began a frame"
        stalled = threading.Event()
        staller = threading.Thread(target=lambda: (fake.stall(), stalled.set()))
        staller.start()
        assert not stalled.wait(0.2), "stall() returned while a frame was still on its way"
        release.set()
        staller.join(10.0)
        assert stalled.is_set()
        sent = fake.frames_sent
        assert sent >= 1  # the begun frame went out before stall() returned
        still_scene.observe = observe
        assert not wait_until(lambda: fake.frames_sent > sent, timeout=0.1)  # 24 periods: nothing more


def test_options_that_contradict_the_announcement_fail_saying_what_to_change(still_scene):
    need_loopback_multicast()
    with FakeMotive(still_scene, multicast=True) as fake:
        url = f"natnet://127.0.0.1:{fake.command_port}?multicast=239.1.2.3"
        with pytest.raises(ProtocolError, match=r"announces multicast 239\.255\.42\.99:\d+ but the sensor URL "
                                                r"sets multicast=239\.1\.2\.3\. Remove the multicast option"):
            NatNetSensor.from_url(url, markers=MARKERS).connect()
        url = f"natnet://127.0.0.1:{fake.command_port}?data_port=1"
        with pytest.raises(ProtocolError, match=f"sets data_port=1. .* or set it to {fake.data_port}"):
            NatNetSensor.from_url(url, markers=MARKERS).connect()
    with FakeMotive(still_scene, multicast=False) as fake:
        url = f"natnet://127.0.0.1:{fake.command_port}?multicast=239.255.42.99"
        with pytest.raises(ProtocolError, match="streams unicast .* set Motive's Streaming Transmission Type to Multicast"):
            NatNetSensor.from_url(url, markers=MARKERS).connect()


def test_a_group_it_cannot_join_fails_saying_what_to_set(still_scene):
    """Another program holds the announced group and port without sharing it."""
    need_loopback_multicast()
    with FakeMotive(still_scene, multicast=True) as fake:
        port = fake.data_port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as hog:
            hog.bind((fake.multicast_group, port))  # no SO_REUSEADDR
            sensor = plain_sensor(fake)
            with pytest.raises(ConnectionLostError) as info:
                sensor.connect()
    msg = str(info.value)
    assert f"streams multicast to 239.255.42.99:{port}" in msg
    assert "on interface 127.0.0.1" in msg and "local=" in msg
    assert "Transmission Type to Unicast" in msg
    assert not sensor._receiver.running  # cleaned up


def test_silence_on_the_multicast_group_says_where_the_client_listens(still_scene):
    need_loopback_multicast()
    with FakeMotive(still_scene, multicast=True, rate_hz=240) as fake:
        port = fake.data_port
        with plain_sensor(fake, silence_timeout_s=0.2) as sensor:
            sensor.read(1.0)
            fake.stall()
            with pytest.raises(DeviceTimeoutError) as info:
                while True:
                    sensor.read(5.0)
    msg = str(info.value)
    assert f"listening to multicast 239.255.42.99:{port} on interface 127.0.0.1" in msg
    assert "local=" in msg and "Transmission Type to Unicast" in msg


class GarbledAnnouncement(FakeMotive):
    def server_info(self):
        return dataclasses.replace(super().server_info(), multicast_address="10.1.2.3")


def test_an_announced_address_that_is_no_group_is_refused(still_scene):
    with GarbledAnnouncement(still_scene, multicast=True) as fake:
        with pytest.raises(ProtocolError, match=r"announces multicast streaming to 10\.1\.2\.3:\d+, which is not"):
            plain_sensor(fake).connect()


# ----------------------------------------------------------------------------- a real Motive 2.1 announcement


class CaptureReplay:
    """Answers like the real Motive 2.1 of the captures: CONNECT → its SERVERINFO bytes
    (multicast 239.255.42.99:1511), REQUEST_MODELDEF → its MODELDEF bytes, REQUEST "FrameRate"
    → float32 120 (what OptiTrack's SampleClient printed for that server), and sends its
    FRAMEOFDATA bytes to the group it announced, from 127.0.0.1 with TTL 0."""

    def __init__(self) -> None:
        self.serverinfo = capture("serverinfo_packet_v3.bin")
        self.modeldef = capture("modeldef_packet_v3.bin")
        self.frame = capture("mocapframe_packet_v3.bin")
        self.cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.cmd.bind(("127.0.0.1", 0))
        self.cmd.settimeout(0.05)
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        self.tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        self.requests: list[str] = []
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self.serve, daemon=True),
                        threading.Thread(target=self.stream, daemon=True)]

    def serve(self) -> None:
        while not self.stop.is_set():
            try:
                data, addr = self.cmd.recvfrom(65536)
            except TimeoutError:
                continue
            msg = codec.decode_packet(data)
            if isinstance(msg, codec.Connect):
                self.cmd.sendto(self.serverinfo, addr)
            elif isinstance(msg, codec.RequestModelDef):
                self.cmd.sendto(self.modeldef, addr)
            elif isinstance(msg, codec.Request):
                self.requests.append(msg.command)
                reply = codec.Response.of_float32(120.0) if msg.command == "FrameRate" else codec.UnrecognizedRequest()
                self.cmd.sendto(codec.encode_packet(reply), addr)

    def stream(self) -> None:
        while not self.stop.wait(1 / 120):
            self.tx.sendto(self.frame, ("239.255.42.99", 1511))

    def __enter__(self):
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2.0)
        self.cmd.close()
        self.tx.close()


def test_client_follows_a_real_motive_21_announcement_to_its_multicast_frames():
    need_loopback_multicast()
    expected = codec.decode_packet(capture("mocapframe_packet_v3.bin"), (3, 0, 0, 0))
    with CaptureReplay() as motive:
        sensor = NatNetSensor.from_url(
            f"natnet://127.0.0.1:{motive.cmd.getsockname()[1]}",
            markers={"quad": "rb:RaceQuad", "m1": "ms:RaceQuad:Marker1", "m5": "lm:2:5"},
        )
        try:
            sensor.connect()
        except ConnectionLostError as exc:
            if "Address already in use" in str(exc):
                pytest.skip(f"UDP 1511 on 239.255.42.99 is held by another program: {exc}")
            raise
        with sensor:
            assert (sensor.stream_group, sensor.stream_port) == ("239.255.42.99", 1511)
            assert sensor.server_info.app_version == (2, 1, 0, 0) and sensor.stream_version[:2] == (3, 0)
            assert sensor.frame_rate_hz == 120.0 and motive.requests == ["FrameRate"]
            s = by_name(sensor.read(2.0))
    np.testing.assert_array_equal(s["quad"].position_mm, expected.rigid_bodies["pos"][0].astype(float) * 1000.0)
    np.testing.assert_array_equal(s["m1"].position_mm, expected.labeled_markers["pos"][0].astype(float) * 1000.0)
    np.testing.assert_array_equal(s["m5"].position_mm, expected.labeled_markers["pos"][4].astype(float) * 1000.0)
    # OptiTrack's SampleClient printed marker 2:1 at (0.13, 1.51, -0.89) m
    np.testing.assert_allclose(s["m1"].position_mm, [130.0, 1510.0, -890.0], atol=5.0)
    assert all(x.visible for x in s.values()) and s["quad"].device_time == pytest.approx(1356.12, abs=0.005)


# ----------------------------------------------------------------------------- NatNet above 4.1


class NewerMotive(FakeMotive):
    """A Motive announcing a NatNet newer than 4.1. Like a 4.x Motive it switches its stream
    on 'Bitstream,4.1' (unless ``refuses``) and streams 4.1 then; before that it says so."""

    def __init__(self, scene, announce, *, refuses: bool = False, **kwargs) -> None:
        super().__init__(scene, natnet_version=(4, 1), **kwargs)
        self.announce = announce
        self.refuses = refuses
        self.switched = False

    def server_info(self):
        return dataclasses.replace(super().server_info(), natnet_version=self.announce)

    def _answer_request(self, command):
        if command == "Bitstream" and not self.switched:
            return codec.Response(text=f"Bitstream,{self.announce[0]}.{self.announce[1]}")
        if command.startswith("Bitstream,"):
            if self.refuses:
                return codec.Response(code=1)
            self.switched = True
        return super()._answer_request(command)


@pytest.mark.parametrize("announce", [(4, 2, 0, 0), (5, 0, 0, 0)], ids=["4.2", "5.0"])
def test_a_server_above_41_is_refused_with_what_to_set(still_scene, announce):
    with NewerMotive(still_scene, announce, rate_hz=240) as fake:
        sensor = plain_sensor(fake)
        with pytest.raises(ProtocolError) as info:
            sensor.connect()
        assert sensor.stream_version is None and sensor.frames_accepted == 0
    msg = str(info.value)
    assert f"streams NatNet {announce[0]}.{announce[1]}, newer than the newest layout this driver reads (4.1)" in msg
    assert "Add bitstream=4.1 to the sensor URL" in msg


def test_a_42_server_is_read_after_it_accepts_bitstream_41(still_scene):
    with NewerMotive(still_scene, (4, 2, 0, 0), rate_hz=240) as fake:
        with plain_sensor(fake, bitstream="4.1") as sensor:
            assert "Bitstream,4.1" in fake.requests and sensor.stream_version[:2] == (4, 1)
            np.testing.assert_allclose(by_name(sensor.read(1.0))["far"].position_mm, TRUE_MM[3], atol=1e-3)


def test_a_newer_server_refusing_41_is_refused(still_scene):
    with NewerMotive(still_scene, (5, 0, 0, 0), refuses=True) as fake:
        with pytest.raises(ProtocolError, match=r"streams NatNet 5\.0 and refused 'Bitstream,4\.1'"):
            plain_sensor(fake, bitstream="4.1").connect()


def test_bitstream_option_above_41_is_refused_at_construction():
    with pytest.raises(ValueError, match="newer than the newest layout"):
        NatNetSensor.from_url("natnet://127.0.0.1?bitstream=4.2", markers=MARKERS)


# ----------------------------------------------------------------------------- FrameRate


@pytest.mark.parametrize("rate", [120.0, 239.5, 360.0])
def test_client_reads_motives_frame_rate_as_a_float(still_scene, rate):
    with FakeMotive(still_scene, rate_hz=rate) as fake, plain_sensor(fake) as sensor:
        assert sensor.frame_rate_hz == rate
        assert "FrameRate" in fake.requests


def test_fake_answers_frame_rate_and_analog_samples_in_the_sdk_types(still_scene):
    """NatNetRequests.h: FrameRate → float32, AnalogSamplesPerMocapFrame → int32."""
    with FakeMotive(still_scene, rate_hz=180, analog_samples_per_frame=10) as fake:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
            s.sendto(codec.encode_packet(codec.Request("FrameRate")), ("127.0.0.1", fake.command_port))
            assert s.recv(64) == struct.pack("<HHf", codec.NAT_RESPONSE, 4, 180.0)
            s.sendto(codec.encode_packet(codec.Request("AnalogSamplesPerMocapFrame")), ("127.0.0.1", fake.command_port))
            assert s.recv(64) == struct.pack("<HHi", codec.NAT_RESPONSE, 4, 10)


class MuteOnFrameRate(FakeMotive):
    """An older server that answers unknown requests with UNRECOGNIZED_REQUEST."""

    def _answer_request(self, command):
        return codec.UnrecognizedRequest() if command == "FrameRate" else super()._answer_request(command)


def test_a_server_without_frame_rate_still_connects(still_scene):
    with MuteOnFrameRate(still_scene, rate_hz=240) as fake, plain_sensor(fake) as sensor:
        assert sensor.frame_rate_hz is None and sensor.read(1.0)
        assert fake.requests.count("FrameRate") == 1  # the refusal was taken as the answer


def _silence_error(sensor) -> str:
    for _ in range(500):
        try:
            sensor.read(0.5)
        except DeviceTimeoutError as exc:
            return str(exc)
    raise AssertionError("frames kept coming")


def test_a_server_restarting_above_41_has_its_frames_dropped_not_misread(still_scene):
    with NewerMotive(still_scene, (4, 1, 0, 0), rate_hz=240) as fake:
        with plain_sensor(fake, silence_timeout_s=0.1) as sensor:
            assert sensor.read(1.0)
            fake.announce = (4, 2, 0, 0)  # an upgraded Motive comes back
            fake.restart(forget_clients=True)
            msg = _silence_error(sensor)
            # it re-sent CONNECT, read the new announcement and stopped decoding
            assert wait_until(lambda: sensor.server_info.natnet_version == (4, 2, 0, 0), timeout=10.0)
            accepted = sensor.frames_accepted
            msg = _silence_error(sensor)
            assert "Motive now announces NatNet 4.2" in msg and "set bitstream=4.1" in msg, msg
            assert sensor.frames_accepted == accepted and sensor.stream_version is None


def test_a_restarted_42_server_is_asked_for_41_again_before_frames_are_read(still_scene):
    with NewerMotive(still_scene, (4, 2, 0, 0), rate_hz=240) as fake:
        with plain_sensor(fake, bitstream="4.1", silence_timeout_s=0.1) as sensor:
            assert fake.requests.count("Bitstream,4.1") == 1
            # read until the frame counter is well past where the restarted server starts again
            assert wait_until(lambda: by_name(sensor.read(1.0))["far"].device_time > 0.2)
            fake.switched = False
            fake.restart(forget_clients=True)
            assert wait_until(lambda: fake.requests.count("Bitstream,4.1") == 2, timeout=10.0)
            assert wait_until(lambda: sensor.restarts == 1 and sensor.stream_version == (4, 1, 0, 0), timeout=10.0)
            np.testing.assert_allclose(by_name(sensor.read(1.0))["far"].position_mm, TRUE_MM[3], atol=1e-3)
