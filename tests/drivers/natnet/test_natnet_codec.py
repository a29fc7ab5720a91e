"""NatNet codec: real Motive captures decode to what OptiTrack's client printed, every message
round-trips (3.0, 3.1, 4.0, 4.1), and malformed packets raise ProtocolError with a reason."""

from __future__ import annotations

import re
import struct

import numpy as np
import pytest
from natnet_helpers import (
    CAPTURES, V30, V40, V41, VERSIONS, capture, rich_frame, rich_modeldef, small_messages,
)

from drivers.errors import ProtocolError
from drivers.natnet import codec



# ----------------------------------------------------------------------------- real captures


def expected_printout() -> dict:
    """Values OptiTrack's SampleClient printed for frame 162734, parsed from the text."""
    path = CAPTURES / "mocapframe_packet_v3.expected.txt"
    if not path.is_file():
        pytest.skip(f"expected values {path} are absent (shared fixtures not mounted)")
    text = path.read_text()
    num = r"(-?\d+\.?\d*)"
    out = {
        "frame": int(re.search(r"FrameID : (\d+)", text).group(1)),
        "timestamp": float(re.search(r"Timestamp : " + num, text).group(1)),
        "software_ms": float(re.search(r"Software latency : " + num, text).group(1)),
        "system_ms": float(re.search(r"System latency : " + num, text).group(1)),
        "other": [
            [float(v) for v in m.groups()]
            for m in re.finditer(r"Other Marker \d+ : " + r"\s+".join([num] * 3), text)
        ],
        "other_count": int(re.search(r"Other Markers \[Count=(\d+)\]", text).group(1)),
    }
    rb = re.search(r"Rigid Body \[ID=(\d+)\s+Error=" + num + r"\s+Valid=(\d)\]\s*\n.*\n\s*" + r"\s+".join([num] * 7), text)
    out["rb_id"], out["rb_error"], out["rb_valid"] = int(rb.group(1)), float(rb.group(2)), int(rb.group(3))
    out["rb_pose"] = [float(v) for v in rb.groups()[3:]]
    out["labeled"] = [
        dict(model=int(m[0]), marker=int(m[1]), occluded=int(m[2]), pc=int(m[3]), ms=int(m[4]),
             size=float(m[5]), pos=[float(m[6]), float(m[7]), float(m[8])])
        for m in re.findall(
            r"ModelID=(\d+), MarkerID=(\d+), Occluded=(\d), PCSolved=(\d), ModelSolved=(\d)\] "
            r"\[size=" + num + r"\] \[pos=" + num + "," + num + "," + num + r"\]", text)
    ]
    out["labeled_count"] = int(re.search(r"Labeled Markers \[Count=(\d+)\]", text).group(1))
    return out


def close2(ours, printed) -> bool:
    """Agree with a value printed with two decimals."""
    return bool(np.all(np.abs(np.asarray(ours, float) - np.asarray(printed, float)) <= 0.005 + 1e-9))


def test_real_motive_frame_decodes_to_optitracks_printout():
    exp = expected_printout()
    data = capture("mocapframe_packet_v3.bin")
    frame = codec.decode_packet(data, V30)
    assert isinstance(frame, codec.FrameOfData)
    assert frame.frame_number == exp["frame"] == 162734
    assert close2(frame.timestamp, exp["timestamp"])
    assert frame.unlabeled.shape == (exp["other_count"], 3) == (5, 3)
    assert close2(frame.unlabeled, exp["other"])
    assert len(frame.rigid_bodies) == 1
    rb = frame.rigid_bodies[0]
    assert rb["id"] == exp["rb_id"] == 2
    assert close2(rb["mean_error"], exp["rb_error"]) and frame.tracking_valid[0] == bool(exp["rb_valid"])
    assert close2(np.concatenate([rb["pos"], rb["quat"]]), exp["rb_pose"])
    assert len(frame.labeled_markers) == exp["labeled_count"] == 6
    for i, lm in enumerate(exp["labeled"]):
        assert frame.model_ids[i] == lm["model"] and frame.marker_ids[i] == lm["marker"]
        params = int(frame.labeled_markers["params"][i])
        assert (params & codec.MARKER_OCCLUDED != 0) == bool(lm["occluded"])
        assert (params & codec.MARKER_PC_SOLVED != 0) == bool(lm["pc"])
        assert (params & codec.MARKER_MODEL_SOLVED != 0) == bool(lm["ms"])
        assert close2(frame.labeled_markers["size"][i], lm["size"])
        assert close2(frame.labeled_markers["pos"][i], lm["pos"])
    software_s, system_s = frame.latencies_s(3312787)  # clock frequency from the SERVERINFO capture
    assert close2(software_s * 1e3, exp["software_ms"]) and close2(system_s * 1e3, exp["system_ms"])
    # mm helpers are the metre values × 1000
    np.testing.assert_allclose(frame.labeled_positions_mm(), frame.labeled_markers["pos"] * 1000.0)
    np.testing.assert_allclose(frame.rigid_body_positions_mm()[0], rb["pos"] * 1000.0)
    np.testing.assert_allclose(frame.unlabeled_mm(), frame.unlabeled * 1000.0)


def test_real_serverinfo_capture():
    info = codec.decode_packet(capture("serverinfo_packet_v3.bin"))
    assert info == codec.ServerInfo("Motive", (2, 1, 0, 0), (3, 0, 0, 0), 3312787, 1511, True, "239.255.42.99")


def test_real_modeldef_capture():
    md = codec.decode_packet(capture("modeldef_packet_v3.bin"), V30)
    assert [type(d).__name__ for d in md.datasets] == [
        "RigidBodyDescription", "MarkerSetDescription", "MarkerSetDescription"]
    rb = md.rigid_bodies[0]
    assert (rb.name, rb.id, rb.parent_id, len(rb.markers)) == ("RaceQuad", 2, -1, 5)
    assert rb.markers[0].offset == pytest.approx((0.16116, 0.03505, -0.03218), abs=1e-5)
    assert md.marker_sets[0] == codec.MarkerSetDescription("RaceQuad", tuple(f"Marker{i}" for i in range(1, 6)))
    assert md.marker_sets[1].marker_names == tuple(f"RaceQuad_{i}" for i in range(1, 6))


def test_real_occluded_frame_flags_marker_two_and_lacks_marker_one():
    frame = codec.decode_packet(capture("mocapframe_packet_occluded_v3.bin"), V30)
    assert frame.rigid_bodies["id"].tolist() == [7]
    assert frame.model_ids.tolist() == [7, 7, 7, 7]
    assert frame.marker_ids.tolist() == [2, 3, 4, 5]
    assert frame.occluded.tolist() == [True, False, False, False]
    assert [m.name for m in frame.marker_sets] == ["FakeTree", "all"]
    assert frame.marker_sets[0].positions.shape == (5, 3)


@pytest.mark.parametrize("name, expected", [
    ("connect_packet_v3.bin", codec.Connect("NatNetLib", (3, 0, 0, 0), (3, 0, 0, 0), "natnetlib")),
    ("discovery_packet_v3.bin", codec.Discovery("NatNetLib", (3, 0, 0, 0), (3, 0, 0, 0), "natnetlib")),
    ("echorequest_packet_v3.bin", codec.EchoRequest(278554190)),
    ("echoresponse_packet_v3.bin", codec.EchoResponse(278554190, 1416498545924)),
    ("requestmodeldef_packet_v3.bin", codec.RequestModelDef()),
])
def test_real_client_packets(name, expected):
    assert codec.decode_packet(capture(name)) == expected


@pytest.mark.parametrize("name", [
    "mocapframe_packet_v3.bin", "mocapframe_packet_occluded_v3.bin", "modeldef_packet_v3.bin",
    "connect_packet_v3.bin", "echoresponse_packet_v3.bin", "echorequest_packet_v3.bin",
])
def test_real_captures_reencode_byte_for_byte(name):
    data = capture(name)
    assert codec.encode_packet(codec.decode_packet(data, V30), V30) == data


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("version", VERSIONS, ids=lambda v: f"{v[0]}.{v[1]}")
def test_every_message_round_trips(version):
    rng = np.random.default_rng(1)
    messages = small_messages() + [rich_modeldef(version), rich_frame(rng, version), codec.FrameOfData(7)]
    for msg in messages:
        packet = codec.encode_packet(msg, version)
        back = codec.decode_packet(packet, version)
        assert type(back) is type(msg)
        assert back == msg, f"{type(msg).__name__} changed in a {version[:2]} round trip"
        assert codec.encode_packet(back, version) == packet


def test_frame_layouts_differ_by_version():
    rng = np.random.default_rng(2)
    sizes = {v[:2]: len(codec.encode_packet(rich_frame(np.random.default_rng(2), v), v)) for v in (V30, V40)}
    assert sizes[(4, 0)] - sizes[(3, 0)] == 8  # two precision-time words
    frame = rich_frame(rng, V30)
    p30 = codec.encode_frame(frame, V30)
    p41 = codec.encode_frame(frame, V41)
    # 4.1 adds a byte count to each of the 7 sections of 3.x, an (empty) asset section with its
    # count and byte count, and (from 4.0) the two precision-time words
    assert len(p41) - len(p30) == 7 * 4 + 8 + 8
    with pytest.raises(ProtocolError):
        codec.decode_frame(p41, V30)


def test_v41_byte_counts_let_the_reader_skip_unknown_trailing_fields():
    """A later version that appends bytes to a section is stepped over, not misread."""
    frame = codec.FrameOfData(5, unlabeled=np.ones((2, 3), "<f4"))
    p = bytearray(codec.encode_frame(frame, V41))
    # marker sets section: count 0, bytes 0 at offset 4; unlabeled: count 2, bytes 24 at 12
    assert struct.unpack_from("<ii", p, 12) == (2, 24)
    struct.pack_into("<ii", p, 12, 2, 28)
    p[20 + 24:20 + 24] = b"XTRA"
    assert codec.decode_frame(bytes(p), V41) == frame
    struct.pack_into("<ii", p, 12, 2, 20)  # byte count smaller than the items
    with pytest.raises(ProtocolError, match="byte count"):
        codec.decode_frame(bytes(p), V41)


def test_natnetsdk_style_trailing_nul_is_accepted():
    # OptiTrack's Python client sends KEEPALIVE/REQUEST_MODELDEF with size 0 plus a NUL byte
    assert codec.decode_packet(b"\x0a\x00\x00\x00\x00") == codec.KeepAlive()
    assert codec.decode_packet(b"\x04\x00\x00\x00\x00") == codec.RequestModelDef()


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("data, match", [
    (b"\x07\x00", "shorter than its 4-byte header"),
    (b"\x07\x00\x10\x00abc", "declares 16 payload bytes"),
    (b"\x63\x00\x00\x00", "message id 99 is unknown"),
    (b"\x07\x00\x02\x00ab", "shorter than a frame number"),
    (b"\x07\x00\x08\x00\x01\x00\x00\x00\xff\xff\xff\x7f", "count 2147483647 does not fit"),
    (b"\x07\x00\x08\x00\x01\x00\x00\x00\xff\xff\xff\xff", "count -1 does not fit"),
    (b"\x02\x00\x03\x00abc", "not NUL-terminated"),
    (b"\x01\x00\x04\x00abcd", "at least 264 expected"),
    (b"\x0c\x00\x02\x00ab", "8 expected"),
    (b"\x05\x00\x10\x00\x01\x00\x00\x00\x63\x00\x00\x00" + bytes(8), "dataset type 99 cannot be read"),
])
def test_malformed_packets_raise_protocol_error_saying_why(data, match):
    with pytest.raises(ProtocolError, match=match):
        codec.decode_packet(data, V30)


def test_truncated_real_frame_raises_protocol_error_at_every_length():
    data = capture("mocapframe_packet_v3.bin")
    for n in range(len(data) - 4):  # the end-of-data marker is optional; cut before it
        cut = data[:n]
        if n >= 4:
            cut = cut[:2] + struct.pack("<H", n - 4) + cut[4:]
        with pytest.raises(ProtocolError):
            codec.decode_packet(cut, V30)


def test_frame_with_nonzero_end_marker_is_refused():
    payload = bytearray(codec.encode_frame(codec.FrameOfData(1), V30))
    payload[-4:] = b"\x01\x00\x00\x00"
    with pytest.raises(ProtocolError, match="end-of-data"):
        codec.decode_frame(bytes(payload), V30)


def test_encoding_bad_values_raises_value_error():
    with pytest.raises(ValueError, match="shape"):
        codec.encode_frame(codec.FrameOfData(1, unlabeled=np.zeros((2, 2))), V30)
    with pytest.raises(ValueError, match="4.1"):
        codec.encode_frame(rich_frame(np.random.default_rng(0), V41), V30)
    with pytest.raises(ValueError, match="NUL"):
        codec.encode_packet(codec.Request("a\0b"))
    with pytest.raises(ValueError, match="255"):
        codec.encode_packet(codec.ServerInfo("x" * 300, (1, 0, 0, 0), (3, 0, 0, 0)))
    with pytest.raises(ValueError, match="exactly one"):
        codec.Response()


@pytest.mark.parametrize("given, expected", [("4.1", V41), ((3, 0), V30), ((4, 1, 0, 0), V41)])
def test_version_parsing(given, expected):
    assert codec.version_tuple(given) == expected


@pytest.mark.parametrize("bad", ["four", (2, 10), "1.2.3.4.5", (300, 1)])
def test_unsupported_or_malformed_versions_are_refused(bad):
    with pytest.raises(ValueError, match="NatNet"):
        codec.check_supported(bad)


# ----------------------------------------------------------------------------- versions beyond 4.1


@pytest.mark.parametrize("newer", [(4, 2), (4, 3, 0, 0), "5.0", (5, 0, 0, 0)])
def test_versions_above_the_newest_layout_are_refused(newer):
    assert codec.MAX_VERSION[:2] == (4, 1)
    with pytest.raises(ValueError, match=r"newer than the newest layout this codec implements \(4\.1\)"):
        codec.check_supported(newer)


@pytest.mark.parametrize("bad", [(4, 2, 0, 0), (5, 0, 0, 0), (2, 10, 0, 0), "x.y", (4,) * 5, None])
def test_decoders_and_encoders_validate_the_version_they_are_given(bad):
    """A 4.2 or 5.0 stream must not be read (or written) silently with the 4.1 layout."""
    frame = codec.FrameOfData(3)
    payload = codec.encode_frame(frame, V41)
    packet = codec.encode_packet(frame, V41)
    md = codec.encode_modeldef(codec.ModelDef(), V41)
    for call in (
        lambda: codec.decode_frame(payload, bad),
        lambda: codec.decode_packet(packet, bad),
        lambda: codec.decode_modeldef(md, bad),
        lambda: codec.encode_frame(frame, bad),
        lambda: codec.encode_packet(frame, bad),
        lambda: codec.decode_packet(codec.encode_packet(codec.KeepAlive()), bad),
    ):
        with pytest.raises(ValueError, match="NatNet layout version .* is not usable"):
            call()


def test_real_capture_decodes_with_every_spelling_of_its_version():
    data = capture("mocapframe_packet_v3.bin")
    frames = [codec.decode_packet(data, v) for v in ((3, 0, 0, 0), (3, 0), "3.0", [3, 0, 0, 0])]
    assert all(f == frames[0] for f in frames) and frames[0].frame_number == 162734


# ----------------------------------------------------------------------------- request replies


def test_frame_rate_reply_is_a_float32_not_a_code():
    """NatNetRequests.h: "FrameRate" returns a float32 (frames per second); the same four
    bytes read as an int32 code would be 1123024896 for 120 Hz."""
    packet = codec.encode_packet(codec.Response.of_float32(120.0))
    assert packet == struct.pack("<HHf", codec.NAT_RESPONSE, 4, 120.0)
    reply = codec.decode_packet(packet)
    assert reply.float32 == 120.0 and reply.code == 1123024896
    assert codec.decode_packet(struct.pack("<HHf", codec.NAT_RESPONSE, 4, 239.999)).float32 == pytest.approx(239.999, rel=1e-7)
    assert codec.decode_packet(struct.pack("<HHi", codec.NAT_RESPONSE, 4, 10)).code == 10  # int32 replies
    with pytest.raises(ValueError, match="text reply"):
        codec.Response(text="Bitstream,4.1").float32


def test_asset_descriptions_exist_only_from_41():
    md = codec.ModelDef((codec.AssetDescription("arm", 1, 9),))
    assert codec.decode_modeldef(codec.encode_modeldef(md, V41), V41) == md
    with pytest.raises(ValueError, match="only from NatNet 4.1"):
        codec.encode_modeldef(md, V40)
