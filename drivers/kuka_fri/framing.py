"""FRI 2.7 datagram framing: a length and a CRC-32 around every protobuf message.

KUKA's FRI client SDK 2.7 (``friMonitoringMessageDecoder.cpp``, ``friCommandMessageEncoder.cpp``;
facts in ``shared/PROTOCOLS.md`` and ``PROTOCOL.md``) wraps every datagram, in both directions:

    offset 0      fixed32 little-endian  N = length of the protobuf message
    offset 4      N bytes                the message (``FRIMonitoringMessage``/``FRICommandMessage``)
    offset 4 + N  fixed32 little-endian  CRC-32 (IEEE, as ``zlib.crc32``) of those N bytes

SDK 1.x and 2.5 send the bare message. We tell them apart per datagram: a datagram is a frame
when its first four bytes, read as a little-endian ``uint32``, equal its length minus 8. A bare
FRI message can never look like that: it opens with its header field (``0x0A``, the header's
length, then ``0x08`` and the identifier's varint), so its first four bytes read as a number far
larger than any datagram. A datagram whose prefix has the two high bytes zero (a plausible
length) but does not match the datagram's size is refused as a cut or padded frame.
"""

from __future__ import annotations

import struct
import zlib

from drivers.errors import ProtocolError

#: Bytes a frame adds to the message: the length prefix and the CRC-32 suffix.
FRAME_OVERHEAD = 8
_U32 = struct.Struct("<I")


def frame(message: bytes) -> bytes:
    """Wrap one encoded protobuf message as SDK 2.7 sends it (length, message, CRC-32)."""
    body = bytes(message)
    return _U32.pack(len(body)) + body + _U32.pack(zlib.crc32(body))


def unframe(datagram: bytes | bytearray | memoryview) -> tuple[bytes, bool]:
    """The protobuf message in one datagram and whether it came framed (FRI 2.7).

    Returns ``(message_bytes, framed)``; a bare datagram comes back whole with ``False``.
    Raises ``ProtocolError`` for a frame whose CRC-32 does not match its message (the SDK
    refuses those too) or whose length prefix does not match the datagram's size.
    """
    data = bytes(datagram)
    n = len(data)
    if n < 4:
        return data, False
    (length,) = _U32.unpack_from(data, 0)
    if n >= FRAME_OVERHEAD and length == n - FRAME_OVERHEAD:
        body = data[4 : 4 + length]
        (sent,) = _U32.unpack_from(data, 4 + length)
        computed = zlib.crc32(body)
        if sent != computed:
            raise ProtocolError(
                f"FRI 2.7 frame of {n} bytes: CRC-32 0x{sent:08X} in the datagram, 0x{computed:08X} computed "
                f"over its {length} message bytes; datagram refused (corrupted on the way, or the sender "
                f"computes the checksum over something else)"
            )
        return body, True
    if data[2] == 0 and data[3] == 0:
        raise ProtocolError(
            f"datagram of {n} bytes opens with an FRI 2.7 length prefix of {length} bytes, which needs "
            f"{length + FRAME_OVERHEAD} bytes (prefix, message, CRC-32): a cut or padded frame; refused"
        )
    return data, False
