"""FRI 2.7 framing (``shared/PROTOCOLS.md``: a little-endian fixed32 length N, the N message
bytes, a little-endian fixed32 IEEE CRC-32 of those bytes, in both directions). The vectors are
built without our encoder: hand-written bytes, or Google's protobuf runtime from the SDK 2.7
tables (``fri_proto``), framed with ``struct`` and ``zlib.crc32``."""

from __future__ import annotations

import socket
import struct
import time
import zlib

import numpy as np
import pytest

pytest.importorskip("google.protobuf")

from fri_helpers import fri_pair  # noqa: E402
from fri_proto import messages  # noqa: E402

from drivers.errors import ProtocolError  # noqa: E402
from drivers.kuka_fri.commander import FriCommander  # noqa: E402
from drivers.kuka_fri.fake import FakeSunrise  # noqa: E402
from drivers.kuka_fri.framing import frame, unframe  # noqa: E402
from drivers.kuka_fri.messages import SessionState, decode_command, decode_monitoring  # noqa: E402

Q0 = np.radians([5.0, 10.0, -5.0, -30.0, 0.0, 20.0, 0.0])
TARGET = np.radians([15.0, 20.0, 5.0, -40.0, 10.0, 30.0, -5.0])

# A header-only monitoring message, by hand: field 1 (0x0A) of 9 bytes = messageIdentifier
# 0x245142 (varint C2 A2 91 01), sequenceCounter 5, reflectedSequenceCounter 3.
HEADER_ONLY = bytes.fromhex("0a09" "08c2a29101" "1005" "1803")


def sdk27_frame(message: bytes) -> bytes:
    """Frame a message as SDK 2.7 does, with struct and zlib only."""
    return struct.pack("<I", len(message)) + message + struct.pack("<I", zlib.crc32(message) & 0xFFFFFFFF)


def sdk27_unframe(datagram: bytes) -> bytes:
    """The message in an SDK 2.7 datagram, checking length and CRC-32 with struct and zlib."""
    (n,) = struct.unpack_from("<I", datagram, 0)
    assert len(datagram) == n + 8, f"frame of {len(datagram)} bytes says its message has {n}"
    body = datagram[4 : 4 + n]
    (crc,) = struct.unpack_from("<I", datagram, 4 + n)
    assert crc == zlib.crc32(body)
    return body


def monitoring_27(seq: int = 7, state: int = 2) -> bytes:
    """An SDK 2.7 monitoring message built by Google's protobuf runtime (bare)."""
    Monitoring, _ = messages("2.7")
    m = Monitoring()
    m.header.messageIdentifier = 0x245142
    m.header.sequenceCounter = seq
    m.header.reflectedSequenceCounter = 0
    m.connectionInfo.sessionState = state
    m.connectionInfo.quality = 3
    m.connectionInfo.sendPeriod = 5
    m.connectionInfo.receiveMultiplier = 1
    m.robotInfo.numberOfJoints = 7
    m.monitorData.measuredJointPosition.value.extend(Q0.tolist())
    m.monitorData.timestamp.sec = 1_795_000_000
    m.monitorData.timestamp.nanosec = 250_000_000
    return m.SerializeToString()


def test_a_hand_written_frame_decodes_and_our_frame_writes_the_same_bytes():
    crc = zlib.crc32(HEADER_ONLY)
    datagram = bytes.fromhex("0b000000") + HEADER_ONLY + crc.to_bytes(4, "little")
    m = decode_monitoring(datagram)
    assert (m.header.message_identifier, m.header.sequence_counter, m.header.reflected_sequence_counter) == (
        0x245142, 5, 3)
    assert unframe(datagram) == (HEADER_ONLY, True)
    assert unframe(HEADER_ONLY) == (HEADER_ONLY, False)  # a bare message is detected as bare
    assert frame(HEADER_ONLY) == datagram


def test_a_27_framed_monitoring_message_from_the_sdk_tables_decodes():
    m = decode_monitoring(sdk27_frame(monitoring_27(seq=42)))
    assert m.header.sequence_counter == 42
    assert m.connection_info.session_state == SessionState.MONITORING_READY
    np.testing.assert_allclose(m.monitor_data.measured_joint_position, Q0)
    assert m.monitor_data.timestamp.sec == 1_795_000_000
    assert m.end_of_message is None


@pytest.mark.parametrize("where", ["crc", "message"])
def test_a_crc_mismatch_is_refused(where):
    good = bytearray(sdk27_frame(monitoring_27()))
    good[-1 if where == "crc" else 10] ^= 0x01
    with pytest.raises(ProtocolError, match=r"FRI 2.7 frame of \d+ bytes: CRC-32 0x[0-9A-F]{8} in the datagram, "
                                            r"0x[0-9A-F]{8} computed .* refused"):
        decode_monitoring(bytes(good))
    _, Command = messages("2.7")
    c = Command()
    c.header.messageIdentifier, c.header.sequenceCounter, c.header.reflectedSequenceCounter = 0x34001, 1, 7
    bad = bytearray(sdk27_frame(c.SerializeToString()))
    bad[-4] ^= 0x80
    with pytest.raises(ProtocolError, match="CRC-32"):
        decode_command(bytes(bad))


def test_a_cut_frame_is_refused_not_read_as_a_bare_message():
    datagram = sdk27_frame(monitoring_27())
    with pytest.raises(ProtocolError, match=r"length prefix of \d+ bytes, which needs \d+ bytes"):
        decode_monitoring(datagram[:-6])


def test_the_fake_sunrise_27_frames_every_datagram_and_refuses_bare_answers():
    Monitoring, Command = messages("2.7")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    try:
        with FakeSunrise(sock.getsockname(), fri_version="2.7", initial_position_rad=Q0) as fake:
            for i in range(6):
                data, addr = sock.recvfrom(4096)
                theirs = Monitoring()
                theirs.ParseFromString(sdk27_unframe(data))
                c = Command()
                c.header.messageIdentifier = 0x34001
                c.header.sequenceCounter = i
                c.header.reflectedSequenceCounter = theirs.header.sequenceCounter
                body = c.SerializeToString()
                sock.sendto(body if i < 3 else sdk27_frame(body), addr)  # three bare, three framed
            sock.recvfrom(4096)
            sock.recvfrom(4096)
            assert fake.stats.malformed_answers == 3
            assert fake.stats.answers == 3
    finally:
        sock.close()


def test_the_commander_answers_a_framed_controller_in_frames():
    """A controller we write by hand (protobuf + struct + zlib) sends 2.7 frames: every answer
    comes back framed, with a correct CRC, and parses with the SDK 2.7 command table."""
    _, Command = messages("2.7")
    from fri_helpers import iiwa14_limits

    c = FriCommander.from_url("fri://127.0.0.1:0?rt_priority=0", limits=iiwa14_limits())
    c.connect()
    ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctl.bind(("127.0.0.1", 0))
    ctl.settimeout(2.0)
    try:
        answers = []
        for seq in range(40):
            ctl.sendto(sdk27_frame(monitoring_27(seq=seq)), c.address)
            try:
                answers.append(ctl.recv(4096))
            except socket.timeout:
                pass  # the exchange process may still be starting
            time.sleep(0.005)
        assert len(answers) >= 10
        for data in answers:
            theirs = Command()
            theirs.ParseFromString(sdk27_unframe(data))
            assert theirs.header.messageIdentifier == 0x34001
        ctl.sendto(b"\x00\x00\x00\x00\x00\x00\x00\x01", c.address)  # an empty frame with a bad CRC
        ctl.sendto(sdk27_frame(monitoring_27(seq=41)), c.address)
        ctl.recv(4096)  # still answering
        deadline = time.monotonic() + 5.0
        while c.malformed_messages < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert c.malformed_messages == 1
    finally:
        ctl.close()
        c.close()


def test_bad_checksums_from_the_controller_are_counted_and_the_move_goes_on():
    from fri_helpers import iiwa14_limits

    limits = iiwa14_limits()
    with fri_pair(limits, initial_position_rad=Q0, fri_version="2.7") as (c, fake):
        fake.send_malformed(3, kind="bad_crc")
        c.move_to(TARGET, 0.8, timeout=10.0)
        state = c.wait_settled(tolerance_rad=1e-5, window_s=0.05, timeout=5.0)
        np.testing.assert_allclose(state.position_rad, TARGET, atol=1e-4)
        assert c.malformed_messages == 3
        assert fake.stats.malformed_answers == 0  # the commander answers 2.7 in frames
        assert fake.stats.violations == []
