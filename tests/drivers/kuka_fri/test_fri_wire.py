"""proto2 wire primitives: varints, int32 sign extension, fields, skipping, malformed input."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import ProtocolError
from drivers.kuka_fri import wire


@pytest.mark.parametrize(
    "value, hexbytes",
    [(0, "00"), (1, "01"), (127, "7f"), (128, "8001"), (300, "ac02"), (0x34001, "81800d"),
     (0xFFFFFFFF, "ffffffff0f"), ((1 << 64) - 1, "ffffffffffffffffff01")],
)
def test_varint_matches_the_reference_encoding(value, hexbytes):
    data = bytes.fromhex(hexbytes)
    assert wire.encode_varint(value) == data
    assert wire.decode_varint(data, 0, len(data)) == (value, len(data))


@given(st.integers(min_value=0, max_value=(1 << 64) - 1))
def test_varint_round_trips(value):
    data = wire.encode_varint(value)
    assert wire.decode_varint(data, 0, len(data)) == (value, len(data))


def test_negative_int32_is_a_ten_byte_sign_extended_varint():
    data = wire.encode_int32(1, -1)
    assert data == bytes.fromhex("08ffffffffffffffffff01")
    [(fn, wt, raw)] = list(wire.iter_fields(data))
    assert (fn, wt) == (1, wire.VARINT)
    assert wire.as_int32(raw, "x") == -1


def test_double_field_is_key_09_and_little_endian_ieee754():
    assert wire.encode_double(1, 1.0) == bytes.fromhex("09000000000000f03f")
    assert wire.encode_repeated_double(1, [1.0, -2.5]) == bytes.fromhex(
        "09000000000000f03f" "0900000000000004c0"
    )


@pytest.mark.parametrize(
    "hexbytes, message",
    [
        ("80", "truncated varint"),
        ("ffffffffffffffffffff01", "longer than 10 bytes"),
        ("0a05010203", "runs past the end"),  # length 5, 3 bytes follow
        ("0900", "truncated 8-byte"),
        ("0d0102", "truncated 4-byte"),
        ("0e00", "invalid wire type"),  # wire type 6
        ("0001", "invalid field number 0"),
        ("0c", "unexpected end-group"),
        ("0b0801", "no end-group"),
        ("0b14", "does not match"),  # start group 1, end group 2
    ],
)
def test_malformed_input_raises_protocol_error(hexbytes, message):
    with pytest.raises(ProtocolError, match=message):
        list(wire.iter_fields(bytes.fromhex(hexbytes)))


def test_groups_of_unknown_fields_are_skipped_whole():
    # field 3 group { field 1 varint 5; field 2 group { } } then field 2 varint 7
    data = bytes.fromhex("1b" "0805" "1314" "1c" "1007")
    assert list(wire.iter_fields(data)) == [(2, wire.VARINT, 7)]


def test_out_of_range_values_are_refused_on_both_sides():
    with pytest.raises(ValueError, match="uint32"):
        wire.encode_uint32(1, 1 << 32)
    with pytest.raises(ValueError, match="int32"):
        wire.encode_int32(1, 1 << 31)
    with pytest.raises(ProtocolError, match="uint32"):
        wire.as_uint32(1 << 32, "sequenceCounter")
    with pytest.raises(ProtocolError, match="int32"):
        wire.as_int32(1 << 40, "numberOfJoints")


@settings(max_examples=300)
@given(st.binary(max_size=64))
def test_random_bytes_give_fields_or_protocol_error_only(data):
    try:
        for _ in wire.iter_fields(data):
            pass
    except ProtocolError:
        pass
