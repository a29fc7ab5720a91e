"""Protocol-buffers (proto2) wire primitives, hand-written for the few FRI messages.

Only what the FRI messages need: varints (uint32, int32, enum), length-delimited fields
(embedded messages, packed repeated scalars), fixed64 doubles, and skipping of every wire type
(including proto2 groups) for unknown fields. Anything that does not follow the wire format
raises ``ProtocolError`` and nothing else.

Wire types (https://protobuf.dev/programming-guides/encoding/):
0 VARINT, 1 I64, 2 LEN, 3 SGROUP, 4 EGROUP, 5 I32.
"""

from __future__ import annotations

import struct
from typing import Iterator

from drivers.errors import ProtocolError

VARINT = 0
I64 = 1
LEN = 2
SGROUP = 3
EGROUP = 4
I32 = 5

UINT32_MAX = 0xFFFF_FFFF
INT32_MIN = -(1 << 31)
INT32_MAX = (1 << 31) - 1
_U64_MASK = (1 << 64) - 1
_MAX_FIELD_NUMBER = (1 << 29) - 1
_MAX_GROUP_DEPTH = 32

_DOUBLE = struct.Struct("<d")


# --------------------------------------------------------------------------- encoding


def encode_varint(value: int) -> bytes:
    """Base-128 varint of a non-negative integer below 2**64."""
    if value < 0 or value > _U64_MASK:
        raise ValueError(f"varint must be in [0, 2**64), got {value}")
    if value < 0x80:
        return bytes((value,))
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def tag(field_number: int, wire_type: int) -> bytes:
    """The key of a field: ``(field_number << 3) | wire_type`` as a varint."""
    if not 1 <= field_number <= _MAX_FIELD_NUMBER:
        raise ValueError(f"field number must be in [1, {_MAX_FIELD_NUMBER}], got {field_number}")
    return encode_varint((field_number << 3) | wire_type)


def encode_uint32(field_number: int, value: int) -> bytes:
    """A ``uint32`` field (wire type 0)."""
    if not 0 <= value <= UINT32_MAX:
        raise ValueError(f"uint32 field {field_number} must be in [0, {UINT32_MAX}], got {value}")
    return tag(field_number, VARINT) + encode_varint(value)


def encode_int32(field_number: int, value: int) -> bytes:
    """An ``int32`` or enum field (wire type 0); negatives take ten bytes (sign-extended)."""
    if not INT32_MIN <= value <= INT32_MAX:
        raise ValueError(
            f"int32 field {field_number} must be in [{INT32_MIN}, {INT32_MAX}], got {value}"
        )
    return tag(field_number, VARINT) + encode_varint(value & _U64_MASK)


def encode_double(field_number: int, value: float) -> bytes:
    """A ``double`` field (wire type 1, little-endian IEEE 754)."""
    return tag(field_number, I64) + _DOUBLE.pack(value)


def encode_bytes(field_number: int, payload: bytes) -> bytes:
    """A length-delimited field (wire type 2): an embedded message or a packed array."""
    return tag(field_number, LEN) + encode_varint(len(payload)) + payload


_repeated_double_structs: dict[tuple[int, int], struct.Struct] = {}


def encode_repeated_double(field_number: int, values) -> bytes:
    """A non-packed ``repeated double``: one key and eight bytes per value (proto2 default)."""
    n = len(values)
    if n == 0:
        return b""
    key = tag(field_number, I64)
    if len(key) != 1:  # FRI's field numbers are all small; keep the fast path simple
        return b"".join(encode_double(field_number, float(v)) for v in values)
    st = _repeated_double_structs.get((key[0], n))
    if st is None:
        st = struct.Struct("<" + "Bd" * n)
        _repeated_double_structs[(key[0], n)] = st
    args: list = []
    k = key[0]
    for v in values:
        args.append(k)
        args.append(float(v))
    return st.pack(*args)


def encode_packed_double(field_number: int, values) -> bytes:
    """A packed ``repeated double`` (wire type 2). We never send it; tests use it to check
    that the decoder accepts what a proto3-style peer would send."""
    payload = struct.pack(f"<{len(values)}d", *(float(v) for v in values))
    return encode_bytes(field_number, payload)


# --------------------------------------------------------------------------- decoding


def decode_varint(buf: bytes | memoryview, pos: int, end: int) -> tuple[int, int]:
    """Read a varint at ``pos``; return ``(value, new_pos)``. At most ten bytes, < 2**64."""
    result = 0
    shift = 0
    start = pos
    while True:
        if pos >= end:
            raise ProtocolError(f"truncated varint at byte {start} (message ends at {end})")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            break
        shift += 7
        if shift >= 70:
            raise ProtocolError(f"varint at byte {start} is longer than 10 bytes")
    if result > _U64_MASK:
        raise ProtocolError(f"varint at byte {start} does not fit in 64 bits")
    return result, pos


def as_uint32(value: int, what: str) -> int:
    """Check a decoded varint is a valid ``uint32``."""
    if value > UINT32_MAX:
        raise ProtocolError(f"{what}: {value} does not fit a uint32")
    return value


def as_int32(value: int, what: str) -> int:
    """Interpret a decoded varint as ``int32`` (negatives arrive sign-extended to 64 bits)."""
    if value >= 1 << 63:
        value -= 1 << 64
    if not INT32_MIN <= value <= INT32_MAX:
        raise ProtocolError(f"{what}: {value} does not fit an int32")
    return value


def iter_fields(buf: bytes | memoryview, start: int = 0, end: int | None = None) -> Iterator[tuple[int, int, object]]:
    """Walk the fields of one message in ``buf[start:end]``.

    Yields ``(field_number, wire_type, value)`` where value is an ``int`` (VARINT), the raw
    ``bytes`` of eight (I64) or four (I32) bytes, or a ``memoryview`` of the payload (LEN).
    Groups (wire types 3/4) are skipped whole and never yielded.
    """
    if end is None:
        end = len(buf)
    mv = buf if isinstance(buf, memoryview) else memoryview(buf)
    pos = start
    while pos < end:
        key = mv[pos]
        if key < 0x80:  # one-byte key: every FRI field
            pos += 1
        else:
            key, pos = decode_varint(mv, pos, end)
        field_number = key >> 3
        wire_type = key & 7
        if field_number == 0 or field_number > _MAX_FIELD_NUMBER:
            raise ProtocolError(f"invalid field number {field_number} before byte {pos}")
        if wire_type == VARINT:
            if pos < end and mv[pos] < 0x80:  # one-byte value: enums, small counters
                value = mv[pos]
                pos += 1
            else:
                value, pos = decode_varint(mv, pos, end)
            yield field_number, wire_type, value
        elif wire_type == I64:
            if pos + 8 > end:
                raise ProtocolError(f"field {field_number}: truncated 8-byte value at byte {pos}")
            yield field_number, wire_type, bytes(mv[pos : pos + 8])
            pos += 8
        elif wire_type == LEN:
            length, pos = decode_varint(mv, pos, end)
            if pos + length > end:
                raise ProtocolError(
                    f"field {field_number}: length {length} at byte {pos} runs past the end ({end})"
                )
            yield field_number, wire_type, mv[pos : pos + length]
            pos += length
        elif wire_type == I32:
            if pos + 4 > end:
                raise ProtocolError(f"field {field_number}: truncated 4-byte value at byte {pos}")
            yield field_number, wire_type, bytes(mv[pos : pos + 4])
            pos += 4
        elif wire_type == SGROUP:
            pos = _skip_group(mv, pos, end, field_number, 1)
        elif wire_type == EGROUP:
            raise ProtocolError(f"unexpected end-group for field {field_number} at byte {pos}")
        else:
            raise ProtocolError(f"field {field_number}: invalid wire type {wire_type}")


def _skip_group(mv: memoryview, pos: int, end: int, group_field: int, depth: int) -> int:
    """Skip a proto2 group's content up to its matching end-group key; return the position after."""
    if depth > _MAX_GROUP_DEPTH:
        raise ProtocolError(f"groups nested deeper than {_MAX_GROUP_DEPTH}")
    while pos < end:
        key, pos = decode_varint(mv, pos, end)
        field_number, wire_type = key >> 3, key & 7
        if field_number == 0:
            raise ProtocolError(f"invalid field number 0 inside group {group_field}")
        if wire_type == VARINT:
            _, pos = decode_varint(mv, pos, end)
        elif wire_type == I64:
            pos += 8
        elif wire_type == LEN:
            length, pos = decode_varint(mv, pos, end)
            pos += length
        elif wire_type == I32:
            pos += 4
        elif wire_type == SGROUP:
            pos = _skip_group(mv, pos, end, field_number, depth + 1)
            continue
        elif wire_type == EGROUP:
            if field_number != group_field:
                raise ProtocolError(
                    f"end-group {field_number} does not match start-group {group_field}"
                )
            return pos
        else:
            raise ProtocolError(f"field {field_number}: invalid wire type {wire_type} in group")
        if pos > end:
            raise ProtocolError(f"group {group_field}: field {field_number} runs past the end")
    raise ProtocolError(f"group {group_field} has no end-group before the end of the message")


def decode_double(raw: bytes) -> float:
    """The value of an eight-byte little-endian double."""
    return _DOUBLE.unpack(raw)[0]


def decode_packed_doubles(payload: memoryview, what: str) -> tuple[float, ...]:
    """The values of a packed ``repeated double`` payload (a multiple of eight bytes)."""
    n, rest = divmod(len(payload), 8)
    if rest:
        raise ProtocolError(f"{what}: packed doubles of {len(payload)} bytes, not a multiple of 8")
    return struct.unpack(f"<{n}d", payload)


def decode_packed_varints(payload: memoryview) -> list[int]:
    """The values of a packed ``repeated`` varint payload (int32 / enum arrays)."""
    out = []
    pos, end = 0, len(payload)
    while pos < end:
        v, pos = decode_varint(payload, pos, end)
        out.append(v)
    return out
