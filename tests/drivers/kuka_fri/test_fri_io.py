"""Controller IOs over FRI (``readIORequest``, the SDK's ``FriIOValue``): what a vendor-layout
message carries (built with Google's protobuf runtime from the SDK's tables, ``fri_proto``)
decodes with our codec and the other way round, and the commander reads a button the fake
Sunrise's robot application shares, over real UDP."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("google.protobuf")

from fri_helpers import fri_pair  # noqa: E402
from fri_proto import messages  # noqa: E402

from drivers.errors import DriverError, ProtocolError  # noqa: E402
from drivers.kuka_fri import wire  # noqa: E402
from drivers.kuka_fri.messages import (  # noqa: E402
    MONITORING_MESSAGE_ID,
    FRIMonitoringMessage,
    IODirection,
    IOType,
    IOValue,
    MessageHeader,
    MonitorData,
    decode_monitoring,
)
from drivers.protocols import DigitalInputs  # noqa: E402

BUTTON = "MediaFlange.UserButton"


@pytest.mark.parametrize("version", ["1.15", "2.5", "2.7"])
def test_vendor_io_values_decode_with_our_codec(version):
    Monitoring, _ = messages(version)
    m = Monitoring()
    m.header.messageIdentifier = MONITORING_MESSAGE_ID
    m.header.sequenceCounter, m.header.reflectedSequenceCounter = 3, 2
    for name, kind, direction, digital, analog in ((BUTTON, 0, 0, 1, None), ("FRI.Out_Integer_Seconds", 1, 1, 2**40, None),
                                                   ("FRI.Out_Analog_Deci_Seconds", 2, 1, None, 0.7)):
        io = m.monitorData.readIORequest.add()
        io.name, io.type, io.direction = name, kind, direction
        if digital is not None:
            io.digitalValue = digital
        if analog is not None:
            io.analogValue = analog
    got = decode_monitoring(m.SerializeToString()).monitor_data.io
    assert got == (IOValue(BUTTON, IOType.BOOLEAN, IODirection.INPUT, 1, None),
                   IOValue("FRI.Out_Integer_Seconds", IOType.DIGITAL, IODirection.OUTPUT, 2**40, None),
                   IOValue("FRI.Out_Analog_Deci_Seconds", IOType.ANALOG, IODirection.OUTPUT, None, 0.7))


@pytest.mark.parametrize("version", ["1.15", "2.5", "2.7"])
def test_our_io_values_decode_with_the_vendor_tables(version):
    msg = FRIMonitoringMessage(MessageHeader(MONITORING_MESSAGE_ID, 1, 0), monitor_data=MonitorData(
        measured_joint_position=(0.0,) * 7,
        io=(IOValue(BUTTON, IOType.BOOLEAN, IODirection.INPUT, 0), IOValue("Gripper.Width", IOType.ANALOG,
                                                                           IODirection.INPUT, None, 12.5))))
    Monitoring, _ = messages(version)
    m = Monitoring.FromString(msg.encode())
    (a, b) = m.monitorData.readIORequest
    assert (a.name, a.type, a.direction, a.HasField("digitalValue"), a.digitalValue) == (BUTTON, 0, 0, True, 0)
    assert (b.name, b.type, b.HasField("digitalValue"), b.analogValue) == ("Gripper.Width", 2, False, 12.5)


def test_an_io_value_without_its_name_is_a_protocol_error():
    io = wire.encode_int32(2, 0) + wire.encode_int32(3, 0)
    monitor = wire.encode_bytes(8, io)
    data = (wire.encode_bytes(1, wire.encode_uint32(1, MONITORING_MESSAGE_ID) + wire.encode_uint32(2, 1)
                              + wire.encode_uint32(3, 0)) + wire.encode_bytes(3, monitor))
    with pytest.raises(ProtocolError, match=r"readIORequest: required field name \(1\) is missing"):
        decode_monitoring(data)


def _until(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


@pytest.mark.parametrize("version", ["1.15", "2.7"])
def test_the_commander_reads_a_button_the_robot_application_shares(limits, version):
    with fri_pair(limits, commanding=False, inputs=(BUTTON,), fri_version=version) as (commander, fake):
        assert isinstance(commander, DigitalInputs)
        assert _until(lambda: commander.session.snapshot() is not None)
        assert commander.digital_input(BUTTON) is False
        fake.set_input(BUTTON, True)
        assert _until(lambda: commander.digital_input(BUTTON))
        fake.set_input(BUTTON, False)
        assert _until(lambda: not commander.digital_input(BUTTON))
        with pytest.raises(DriverError, match=r"shares no IO named 'MediaFlange.Button' over FRI \(it shares: "
                                              r"'MediaFlange.UserButton'\); register it"):
            commander.digital_input("MediaFlange.Button")
        with pytest.raises(ValueError, match="shares no input 'Other'"):
            fake.set_input("Other", True)
