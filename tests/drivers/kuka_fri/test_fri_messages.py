"""FRI messages: hand-computed bytes, round trips, proto2 decode rules, malformed input."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import ProtocolError
from drivers.kuka_fri import wire
from drivers.kuka_fri.messages import (
    COMMAND_MESSAGE_ID,
    MONITORING_MESSAGE_ID,
    CommandData,
    ConnectionInfo,
    ConnectionQuality,
    DriveState,
    EndOfMessage,
    FRICommandMessage,
    FRIMonitoringMessage,
    IpoData,
    MessageHeader,
    MonitorData,
    RobotInfo,
    SafetyState,
    SessionState,
    TimeStamp,
    decode_command,
    decode_monitoring,
)

# Hand-computed (see PROTOCOL.md): header {id 0x34001 = 81 80 0d, seq 1, reflected 2},
# commandData {jointPosition {value 1.0, value -2.5}} with unpacked doubles (key 0x09).
COMMAND_HEX = (
    "0a08" "0881800d" "1001" "1802"
    "1214" "0a12" "09000000000000f03f" "0900000000000004c0"
)
# header {id 0x245142 = c2 a2 91 01, seq 7, reflected 3},
# connectionInfo (field 4) {COMMANDING_ACTIVE 4, GOOD 2, sendPeriod 5, receiveMultiplier 1}.
MONITORING_HEX = "0a09" "08c2a29101" "1007" "1803" "2208" "0804" "1002" "1805" "2001"


def test_command_message_encodes_to_the_hand_computed_bytes():
    msg = FRICommandMessage(
        MessageHeader(COMMAND_MESSAGE_ID, 1, 2), CommandData(joint_position=(1.0, -2.5))
    )
    assert msg.encode().hex() == COMMAND_HEX
    assert decode_command(bytes.fromhex(COMMAND_HEX)) == msg


def test_monitoring_message_encodes_to_the_hand_computed_bytes():
    msg = FRIMonitoringMessage(
        MessageHeader(MONITORING_MESSAGE_ID, 7, 3),
        connection_info=ConnectionInfo(SessionState.COMMANDING_ACTIVE, ConnectionQuality.GOOD, 5, 1),
    )
    assert msg.encode().hex() == MONITORING_HEX
    decoded = decode_monitoring(bytes.fromhex(MONITORING_HEX))
    assert decoded == msg
    assert decoded.connection_info.session_state is SessionState.COMMANDING_ACTIVE


# ----------------------------------------------------------------------------- round trips

u32 = st.integers(0, 0xFFFF_FFFF)
finite = st.floats(allow_nan=False, allow_infinity=True, width=64)
joints = st.none() | st.lists(finite, max_size=8).map(tuple)


def maybe(strategy):
    return st.none() | strategy


headers = st.builds(MessageHeader, u32, u32, u32)
monitoring = st.builds(
    FRIMonitoringMessage,
    header=headers.map(lambda h: MessageHeader(MONITORING_MESSAGE_ID, h.sequence_counter, h.reflected_sequence_counter)),
    robot_info=maybe(st.builds(
        RobotInfo,
        number_of_joints=maybe(st.integers(-(1 << 31), (1 << 31) - 1)),
        safety_state=maybe(st.sampled_from(list(SafetyState))),
        drive_state=st.lists(st.sampled_from(list(DriveState)), max_size=8).map(tuple),
        operation_mode=maybe(st.integers(0, 2)),
        control_mode=maybe(st.integers(0, 3)),
    )),
    monitor_data=maybe(st.builds(
        MonitorData, joints, joints, joints, joints, joints,
        maybe(st.builds(TimeStamp, u32, st.integers(0, 999_999_999))),
    )),
    connection_info=maybe(st.builds(
        ConnectionInfo, st.sampled_from(list(SessionState)), st.sampled_from(list(ConnectionQuality)),
        maybe(u32), maybe(u32),
    )),
    ipo_data=maybe(st.builds(IpoData, joints, maybe(st.integers(0, 3)), maybe(st.integers(0, 2)), maybe(finite))),
    end_of_message=maybe(st.builds(EndOfMessage, maybe(st.integers(-(1 << 31), (1 << 31) - 1)),
                                   maybe(st.integers(-(1 << 31), (1 << 31) - 1)))),
)


@settings(max_examples=150)
@given(monitoring)
def test_monitoring_messages_round_trip(msg):
    assert decode_monitoring(msg.encode()) == msg


@settings(max_examples=100)
@given(u32, u32, maybe(st.builds(CommandData, joints, joints)))
def test_command_messages_round_trip(seq, reflected, data):
    msg = FRICommandMessage(MessageHeader(COMMAND_MESSAGE_ID, seq, reflected), data)
    assert decode_command(msg.encode()) == msg


# ----------------------------------------------------------------------------- proto2 rules


def _header(seq=1, reflected=0, ident=COMMAND_MESSAGE_ID) -> bytes:
    return wire.encode_bytes(
        1, wire.encode_uint32(1, ident) + wire.encode_uint32(2, seq) + wire.encode_uint32(3, reflected)
    )


def test_packed_and_unpacked_doubles_decode_to_the_same_values():
    values = [0.1, -0.2, 0.3, 1.5, -2.0, 0.0, 3.0]
    packed = _header() + wire.encode_bytes(2, wire.encode_bytes(1, wire.encode_packed_double(1, values)))
    # a mix: first three unpacked, the rest packed, in one JointValues
    mixed_jv = wire.encode_repeated_double(1, values[:3]) + wire.encode_packed_double(1, values[3:])
    mixed = _header() + wire.encode_bytes(2, wire.encode_bytes(1, mixed_jv))
    assert decode_command(packed).command_data.joint_position == tuple(values)
    assert decode_command(mixed).command_data.joint_position == tuple(values)


def test_unknown_fields_of_every_wire_type_are_skipped():
    msg = FRICommandMessage(MessageHeader(COMMAND_MESSAGE_ID, 5, 4), CommandData(joint_position=(1.0, 2.0)))
    noise = (
        wire.encode_uint32(9, 77)
        + wire.encode_bytes(20, b"\x01\x02")
        + bytes.fromhex("3d01020304")  # field 7, 32-bit
        + bytes.fromhex("a306" "0805" "a406")  # field 100 group
        + wire.encode_bytes(4, b"\x08\x01")  # commandedTransformations: not modelled
    )
    data = noise + msg.encode() + noise
    assert decode_command(data) == msg


def test_a_repeated_singular_submessage_is_merged_last_scalar_wins():
    data = _header(seq=1, reflected=9) + wire.encode_bytes(1, wire.encode_uint32(2, 42))
    h = decode_command(data).header
    assert (h.sequence_counter, h.reflected_sequence_counter) == (42, 9)


def test_unknown_drive_and_safety_values_are_kept_as_integers():
    ri = wire.encode_int32(2, 9) + wire.encode_int32(5, 2) + wire.encode_bytes(5, bytes([7, 2]))
    data = _header(ident=MONITORING_MESSAGE_ID) + wire.encode_bytes(2, ri)
    info = decode_monitoring(data).robot_info
    assert info.safety_state == 9 and not isinstance(info.safety_state, SafetyState)
    assert info.drive_state == (DriveState.ACTIVE, 7, DriveState.ACTIVE)


@pytest.mark.parametrize(
    "data, message",
    [
        (b"", "header \\(1\\) is missing"),
        (wire.encode_bytes(1, wire.encode_uint32(1, COMMAND_MESSAGE_ID) + wire.encode_uint32(3, 0)),
         "sequenceCounter \\(2\\) is missing"),
        (_header(ident=MONITORING_MESSAGE_ID), "identifier 0x245142, expected 0x34001"),
        (wire.encode_uint32(1, 5), "wire type varint, expected length-delimited"),
        (_header() + wire.encode_bytes(2, wire.encode_bytes(1, wire.encode_uint32(1, 3))),
         "jointPosition.value: wire type varint"),
        (_header() + wire.encode_bytes(2, wire.encode_bytes(1, wire.encode_bytes(1, b"\x00" * 9))),
         "not a multiple of 8"),
        (_header()[:-1], "past the end|truncated"),
    ],
)
def test_bad_command_messages_raise_protocol_error(data, message):
    with pytest.raises(ProtocolError, match=message):
        decode_command(data)


@pytest.mark.parametrize(
    "sub, message",
    [
        (wire.encode_bytes(4, wire.encode_int32(1, 4)), "quality \\(2\\) is missing"),
        (wire.encode_bytes(4, wire.encode_int32(1, 9) + wire.encode_int32(2, 0)),
         "sessionState: unknown value 9; allowed: 0 IDLE"),
        (wire.encode_bytes(3, wire.encode_bytes(15, wire.encode_uint32(1, 3))), "nanosec \\(2\\) is missing"),
        (wire.encode_bytes(4, wire.encode_int32(1, 1) + wire.encode_int32(2, 0) + bytes.fromhex("18ffffffff1f")),
         "does not fit a uint32"),
    ],
)
def test_bad_monitoring_messages_raise_protocol_error(sub, message):
    with pytest.raises(ProtocolError, match=message):
        decode_monitoring(_header(ident=MONITORING_MESSAGE_ID) + sub)


GOOD_MONITORING = FRIMonitoringMessage(
    MessageHeader(MONITORING_MESSAGE_ID, 12, 11),
    RobotInfo(7, SafetyState.NORMAL_OPERATION, (DriveState.ACTIVE,) * 7, 2, 0),
    MonitorData(tuple(0.1 * i for i in range(7)), (0.0,) * 7, tuple(0.1 * i for i in range(7)),
                timestamp=TimeStamp(100, 5000)),
    ConnectionInfo(SessionState.COMMANDING_ACTIVE, ConnectionQuality.EXCELLENT, 5, 1),
    IpoData((0.2,) * 7, 1, 1, 1.0),
).encode()


@settings(max_examples=300)
@given(st.data())
def test_corrupted_messages_decode_or_raise_protocol_error_only(data):
    raw = bytearray(GOOD_MONITORING)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    for candidate in (bytes(raw), bytes(raw[:cut])):
        try:
            decode_monitoring(candidate)
        except ProtocolError:
            pass


def test_non_bytes_input_is_a_protocol_error():
    with pytest.raises(ProtocolError, match="expected bytes, got str"):
        decode_monitoring("0a00")


def test_doubles_keep_every_bit():
    tricky = (5e-324, -0.0, 1.7976931348623157e308, float("inf"), 0.1 + 0.2)
    msg = FRICommandMessage(MessageHeader(COMMAND_MESSAGE_ID, 0, 0), CommandData(joint_position=tricky))
    out = decode_command(msg.encode()).command_data.joint_position
    assert [struct.pack("<d", v) for v in out] == [struct.pack("<d", v) for v in tricky]
