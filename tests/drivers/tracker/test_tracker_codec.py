"""The line codec: every command and reply round-trips; bad lines raise only ProtocolError."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.errors import ProtocolError
from drivers.tracker.codec import (
    COMMANDS,
    REPLIES,
    Aim,
    AimReply,
    AverageReply,
    PoseReply,
    ErrorCode,
    Environment,
    EnvironmentReply,
    ErrorReply,
    Event,
    GetStatus,
    Home,
    HomeReply,
    Identify,
    IdentifyReply,
    LineCodec,
    MeasureAverage,
    MeasurePose,
    MeasurePoint,
    Mode,
    ModeReply,
    PointReply,
    ReflectorReply,
    RequestError,
    Search,
    SearchReply,
    SelectReflector,
    SetMode,
    StatusReply,
    checksum,
)

COMMAND_EXAMPLES = [
    Identify(),
    GetStatus(),
    SetMode(Mode.ADM),
    SetMode(Mode.IFM),
    MeasurePoint(),
    MeasureAverage(1),
    MeasurePose(100),
    MeasureAverage(100_000),
    Aim(2000.1234, -300.5, 0.0001),
    Search(50.0, 10.0, 0),
    Search(0.5, 0.25, 12),
    Home(),
    Environment("HOST", 21.5, 1008.25, 45.0),
    Environment("STATION"),
    Environment(),
    SelectReflector("RRR15"),
    SelectReflector("TBR05", 6.35),
    SelectReflector(),
]

REPLY_EXAMPLES = [
    IdentifyReply("remaster", "SIMTRACKER-1", "SIM0001", "1.0.0", 1),
    StatusReply(True, Mode.ADM, True, 0.0, True, True, 12.00025),
    StatusReply(False, Mode.IFM, False, 12.5, False, False, 0.0),
    ModeReply(Mode.IFM, False, 3.25),
    PointReply(2000.0021, 299.9987, -100.0004, 0.027, 12.101),
    AverageReply(-1.5, 2.25, 3e3, 0.0268, 0.0271, 0.0273, 1000, 13.102),
    PoseReply(2000.0002, 300.0001, -99.9999, 0.0268, 0.0271, 0.0273, 0.707106781, 0.0, 0.0, 0.707106781,
              0.010214, 0.009871, 0.010102, 100, 13.202),
    AimReply(True, 13.3),
    EnvironmentReply("HOST", 21.5, 1008.25, 45.0, 14.0),
    EnvironmentReply("STATION", -3.25, 955.0, 0.0, 15.5),
    ReflectorReply("RRR15", 19.05, 16.0),
    AimReply(False, 13.4),
    SearchReply(True, 0.686, 2.954, 14.46621),
    SearchReply(False, 10.0, 3.5, 15.0),
    HomeReply(True, 15.0),
]


def test_examples_cover_every_command_and_reply():
    assert {type(c).verb for c in COMMAND_EXAMPLES} == set(COMMANDS)
    assert {type(r).verb for r in REPLY_EXAMPLES} == set(REPLIES)


@pytest.mark.parametrize("command", COMMAND_EXAMPLES, ids=repr)
def test_every_command_round_trips(command):
    codec = LineCodec(require_checksum=True)
    line = codec.encode_request(42, command)
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    assert codec.decode_request(line) == (42, command)


@pytest.mark.parametrize("reply", REPLY_EXAMPLES, ids=repr)
def test_every_reply_round_trips(reply):
    codec = LineCodec(require_checksum=True)
    line = codec.encode_reply(7, reply)
    assert line.startswith(b"7 OK " + reply.verb.encode() + b" ")
    assert codec.decode_reply(line) == (7, reply)


def test_error_and_event_lines_round_trip():
    codec = LineCodec(require_checksum=True)
    err = ErrorReply(int(ErrorCode.BEAM_LOST), "beam not locked on a reflector; AIM or SEARCH first")
    assert codec.decode_reply(codec.encode_reply(9, err)) == (9, err)
    ev = Event("BEAM_LOST", 12.711587)
    line = codec.encode_reply(0, ev)
    assert line.startswith(b"! BEAM_LOST t=12.711587*")
    assert codec.decode_reply(line) == (None, ev)


def test_error_text_with_a_star_or_control_bytes_is_made_printable():
    codec = LineCodec(require_checksum=True)
    rid, err = codec.decode_reply(codec.encode_reply(3, ErrorReply(50, "bad * thing\there")))
    assert (rid, err.code, err.text) == (3, 50, "bad ? thing?here")


def test_numbers_round_trip_to_their_wire_resolution():
    rng = np.random.default_rng(11)
    codec = LineCodec(require_checksum=True)
    for _ in range(500):
        x, y, z, s = rng.uniform(-5000, 5000, 4)
        t = rng.uniform(0, 1e6)
        _, back = codec.decode_reply(codec.encode_reply(1, PointReply(x, y, z, abs(s), t)))
        assert np.allclose(back.xyz_mm, [x, y, z], atol=0.5e-4, rtol=0)
        assert abs(back.std_mm - abs(s)) <= 0.5e-4
        assert abs(back.device_time - t) <= 0.5e-6 + 1e-9 * t


def test_a_documented_request_line_decodes_without_a_checksum():
    # A person typing at a terminal: CR LF, several spaces, no checksum.
    rid, cmd = LineCodec().decode_request(b"12  AIM x=1.5 y=-2 z=3000\r\n")
    assert (rid, cmd) == (12, Aim(1.5, -2.0, 3000.0))


def test_checksum_is_the_xor_of_the_body():
    assert checksum(b"7 ID") == f"{ord('7') ^ ord(' ') ^ ord('I') ^ ord('D'):02X}"
    assert LineCodec().encode_request(7, Identify()) == b"7 ID*" + checksum(b"7 ID").encode() + b"\n"


@pytest.mark.parametrize(
    ("line", "code", "rid", "fragment"),
    [
        (b"hello", ErrorCode.SYNTAX, 0, "expected '<id> <COMMAND>"),
        (b"0 ID", ErrorCode.SYNTAX, 0, "reserved"),
        (b"5 FIRE", ErrorCode.UNKNOWN_COMMAND, 5, "known: ID STATUS"),
        (b"6 AVG n=0", ErrorCode.BAD_ARGUMENT, 6, "1..100000"),
        (b"6 AVG", ErrorCode.SYNTAX, 6, "missing n="),
        (b"6 AVG n=2 n=3", ErrorCode.SYNTAX, 6, "twice"),
        (b"7 AIM x=1 y=2 z=nan", ErrorCode.SYNTAX, 7, "not a decimal"),
        (b"7 AIM x=0 y=0 z=0.5", ErrorCode.BAD_ARGUMENT, 7, "within 1 mm"),
        (b"8 MODE mode=adm", ErrorCode.SYNTAX, 8, "ADM or IFM"),
        (b"9 SEARCH r=-1 timeout=1", ErrorCode.BAD_ARGUMENT, 9, "radius_mm"),
        (b"9 ID*00", ErrorCode.SYNTAX, 0, "checksum"),
        (b"9 ID\x00", ErrorCode.SYNTAX, 0, "not printable"),
    ],
)
def test_bad_requests_say_what_was_wrong_with_a_code(line, code, rid, fragment):
    with pytest.raises(RequestError) as info:
        LineCodec().decode_request(line)
    assert info.value.code is code
    assert info.value.rid == rid
    assert fragment in str(info.value)
    assert isinstance(info.value, ProtocolError)


def test_host_side_codec_refuses_a_reply_without_checksum():
    with pytest.raises(ProtocolError, match="checksum"):
        LineCodec(require_checksum=True).decode_reply(b"1 OK HOME dist_valid=1 t=1.000000\n")


def test_encoder_refuses_values_it_cannot_put_on_the_wire():
    codec = LineCodec()
    with pytest.raises(ValueError, match="non-finite"):
        codec.encode_reply(1, PointReply(float("nan"), 0, 0, 0, 0))
    with pytest.raises(ValueError, match="request id"):
        codec.encode_request(0, Identify())
    with pytest.raises(ValueError, match="n must be"):
        MeasureAverage(0)


def test_split_frames_keeps_the_partial_tail_and_bounds_a_runaway_line():
    buf = bytearray(b"1 OK A\n2 OK B\n3 OK")
    assert LineCodec.split_frames(buf) == [b"1 OK A\n", b"2 OK B\n"]
    assert buf == bytearray(b"3 OK")
    runaway = bytearray(b"x" * 5000)
    with pytest.raises(ProtocolError, match="without a newline"):
        LineCodec.split_frames(runaway)
    assert runaway == bytearray()


# ----------------------------------------------------------------------------- fuzz

def _valid_lines() -> tuple[list[bytes], list[bytes]]:
    codec = LineCodec()
    replies = [codec.encode_reply(i + 1, r) for i, r in enumerate(REPLY_EXAMPLES)]
    replies += [codec.encode_reply(3, ErrorReply(10, "beam lost")), codec.encode_reply(0, Event("BEAM_LOCKED", 1.0))]
    requests = [codec.encode_request(i + 1, c) for i, c in enumerate(COMMAND_EXAMPLES)]
    return replies, requests


def _mutate(rng: np.random.Generator, line: bytes, pool: list[bytes]) -> bytes:
    b = bytearray(line)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(0, 9))
        i = int(rng.integers(0, len(b) + 1))
        if op == 0 and b:  # substitute any byte
            b[min(i, len(b) - 1)] = int(rng.integers(0, 256))
        elif op == 1:  # insert any byte
            b.insert(i, int(rng.integers(0, 256)))
        elif op == 2 and b:  # delete
            del b[min(i, len(b) - 1)]
        elif op == 3:  # truncate
            del b[i:]
        elif op == 4:  # splice with another valid line
            other = pool[int(rng.integers(0, len(pool)))]
            b = b[:i] + other[int(rng.integers(0, len(other))):]
        elif op == 5:  # duplicate a chunk
            j = int(rng.integers(i, len(b) + 1))
            b[i:i] = b[i:j]
        elif op == 6:  # printable substitution (the hard case for a parser)
            if b:
                b[min(i, len(b) - 1)] = int(rng.integers(0x20, 0x7F))
        elif op == 7:  # swap the digits of a number for junk
            b = bytearray(bytes(b).replace(b"=", b"=" + bytes(rng.choice(list(b"-+.0e9nan"), 3).tolist()), 1))
        else:  # random garbage
            b = bytearray(rng.integers(0, 256, int(rng.integers(0, 40))).astype(np.uint8).tobytes())
    return bytes(b)


def test_ten_thousand_garbled_replies_raise_only_protocol_error():
    rng = np.random.default_rng(2024)
    replies, _ = _valid_lines()
    codec = LineCodec(require_checksum=True)
    refused = 0
    t0 = time.monotonic()
    for k in range(10_000):
        line = _mutate(rng, replies[k % len(replies)], replies)
        try:
            codec.decode_reply(line)
        except ProtocolError:
            refused += 1
    assert time.monotonic() - t0 < 20.0
    assert refused > 9_500  # the checksum catches nearly every mutation


def test_ten_thousand_garbled_requests_raise_only_request_errors():
    rng = np.random.default_rng(7)
    _, requests = _valid_lines()
    codec = LineCodec()
    for k in range(10_000):
        line = _mutate(rng, requests[k % len(requests)], requests)
        try:
            codec.decode_request(line)
        except RequestError as exc:
            assert exc.code in (ErrorCode.SYNTAX, ErrorCode.UNKNOWN_COMMAND, ErrorCode.BAD_ARGUMENT)
            assert 0 <= exc.rid


def test_every_single_byte_edit_of_a_reply_is_detected_by_the_checksum():
    replies, _ = _valid_lines()
    codec = LineCodec(require_checksum=True)
    rng = np.random.default_rng(5)
    for line in replies:
        original = codec.decode_reply(line)
        for i in range(len(line)):
            for new in {int(rng.integers(0x20, 0x7F)), ord("0"), ord(" ")} - {line[i]}:
                edited = line[:i] + bytes([new]) + line[i + 1:]
                try:
                    assert codec.decode_reply(edited) == original  # only a harmless edit may pass
                except ProtocolError:
                    pass
            deleted = line[:i] + line[i + 1:]
            try:
                assert codec.decode_reply(deleted) == original
            except ProtocolError:
                pass


def test_the_fake_device_answers_every_garbled_request_with_one_reply_line(device):
    rng = np.random.default_rng(9)
    _, requests = _valid_lines()
    host = LineCodec(require_checksum=True)
    for k in range(2_000):
        line = _mutate(rng, requests[k % len(requests)], requests)
        if b"\n" in line[:-1]:
            continue  # framing would split it into several requests
        out = device.handle(line)
        assert out.endswith(b"\n") and out.count(b"\n") == 1
        rid, reply = host.decode_reply(out)
        assert rid is not None
