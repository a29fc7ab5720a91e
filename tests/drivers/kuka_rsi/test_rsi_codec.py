"""RSI XML codec: what KUKA controllers and the ROS-Industrial simulator send, what we answer."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import ProtocolError
from drivers.kuka_rsi.codec import RobFormatter, SenFormatter, parse_rob, parse_sen

#: A state packet exactly as ROS-Industrial's kuka_rsi_simulator builds it (ElementTree,
#: upper-case TYPE attribute, str(float) values, IPOC starting at 0 and stepping by 4).
SIMULATOR_ROB = (
    b'<Rob TYPE="KUKA"><RIst A="0.0" B="0.0" C="0.0" X="0.0" Y="0.0" Z="0.0" />'
    b'<RSol A="0.0" B="0.0" C="0.0" X="0.0" Y="0.0" Z="0.0" />'
    b'<AIPos A1="0.0" A2="-90.0" A3="90.0" A4="0.0" A5="90.0" A6="0.0" />'
    b'<ASPos A1="0.0" A2="-90.0" A3="90.0" A4="0.0" A5="90.0" A6="0.0" />'
    b'<Delay D="0" /><IPOC>4</IPOC></Rob>'
)

#: The layout of a KR C4 with a typical RSI config (ETHERNET object with these tags).
KRC4_ROB = (
    b'<?xml version="1.0" encoding="UTF-8"?>\r\n<Rob Type="KUKA">\r\n'
    b'  <RIst X="445.0000" Y="0.0000" Z="890.0000" A="180.0000" B="0.0000" C="180.0000"/>\r\n'
    b'  <RSol X="445.0000" Y="0.0000" Z="890.0000" A="180.0000" B="0.0000" C="180.0000"/>\r\n'
    b'  <AIPos A1="0.0000" A2="-90.0000" A3="90.0000" A4="0.0000" A5="0.0000" A6="0.0000"/>\r\n'
    b'  <ASPos A1="0.0000" A2="-90.0000" A3="90.0000" A4="0.0000" A5="0.0000" A6="0.0000"/>\r\n'
    b'  <EIPos E1="12.5000"/>\r\n'
    b'  <Delay D="3"/>\r\n  <IPOC>4208163</IPOC>\r\n</Rob>\r\n'
)


def test_simulator_packet_decodes_with_every_field():
    s = parse_rob(SIMULATOR_ROB)
    assert s.ipoc == 4
    assert s.axis_actual_deg == (0.0, -90.0, 90.0, 0.0, 90.0, 0.0)
    assert s.axis_setpoint_deg == s.axis_actual_deg
    assert s.cartesian_actual == (0.0,) * 6
    assert s.delay == 0
    assert s.type == "KUKA"
    assert s.external_actual_deg == ()


def test_controller_packet_with_declaration_whitespace_and_external_axis():
    s = parse_rob(KRC4_ROB)
    assert s.ipoc == 4208163
    assert s.cartesian_actual == (445.0, 0.0, 890.0, 180.0, 0.0, 180.0)
    assert s.external_actual_deg == (12.5,)
    assert s.delay == 3


def test_rob_formatter_round_trips_through_the_parser():
    f = RobFormatter(6, 2)
    actual = [1.5, -90.25, 90.125, 0.0, 45.0, -3.0, 100.0, -7.5]
    setpoint = [0.0, -90.0, 90.0, 0.0, 45.0, 0.0, 99.0, -7.0]
    s = parse_rob(f.format(actual, setpoint, (1, 2, 3, 4, 5, 6), (6, 5, 4, 3, 2, 1), 7, 123456))
    assert s.axis_actual_deg == tuple(actual[:6])
    assert s.external_actual_deg == tuple(actual[6:])
    assert s.axis_setpoint_deg == tuple(setpoint[:6])
    assert s.external_setpoint_deg == tuple(setpoint[6:])
    assert s.cartesian_setpoint == (6, 5, 4, 3, 2, 1)
    assert (s.delay, s.ipoc) == (7, 123456)


def test_sen_answer_is_well_formed_xml_that_the_simulator_parser_reads():
    out = SenFormatter(6, 1, "ImFree").format([0.1, -0.2, 0.3, 1e-8, -123.456789012, 5.0, 2.0], True, 4208163)
    root = ET.fromstring(out)  # the simulator parses answers with ElementTree
    assert root.tag == "Sen" and root.get("Type") == "ImFree"
    ak = root.find("AK").attrib
    assert float(ak["A5"]) == pytest.approx(-123.456789, abs=1e-7)
    assert root.find("EK").get("E1") == "2.0000000"
    assert root.find("IPOC").text == "4208163"
    assert root.find("Stop").text == "1"
    cmd = parse_sen(out)
    assert cmd.ipoc == 4208163 and cmd.stop
    assert cmd.axis_correction_deg[:3] == (0.1, -0.2, 0.3)
    assert cmd.external_correction_deg == (2.0,)


@pytest.mark.parametrize(
    "packet, message",
    [
        (b"", "not a flat XML document"),
        (SIMULATOR_ROB[:-4], "not a flat XML document"),
        (SIMULATOR_ROB.replace(b"<IPOC>4</IPOC>", b""), "no <IPOC>"),
        (SIMULATOR_ROB.replace(b"<IPOC>4<", b"<IPOC>-4<"), "non-negative integer"),
        (SIMULATOR_ROB.replace(b'A3="90.0" A4', b'A3="ninety" A4'), "AIPos A3> is not a number"),
        (SIMULATOR_ROB.replace(b'A3="90.0" A4', b'A3="inf" A4'), "AIPos A3> is not a number"),
        (SIMULATOR_ROB.replace(b' A4="0.0" A5="90.0" A6="0.0" />' b"<ASPos", b' A5="90.0" />' b"<ASPos"), "A1..Ak"),
        (SIMULATOR_ROB.replace(b"<AIPos", b"<AXPos"), "no <AIPos>"),
        (SIMULATOR_ROB.replace(b'<Delay D="0" />', b"<Delay D=\"x\" />"), "Delay"),
        (SIMULATOR_ROB.replace(b"Rob", b"Sen"), "expected <Rob>"),
        (b"<Rob><A><B/></A><IPOC>1</IPOC></Rob>", "not a flat XML document"),
        (b"\xff\xfe garbage", "not a flat XML document"),
    ],
)
def test_malformed_state_packets_raise_protocol_error_naming_the_problem(packet, message):
    with pytest.raises(ProtocolError, match=message):
        parse_rob(packet)


def test_non_bytes_input_is_a_protocol_error():
    with pytest.raises(ProtocolError, match="must be bytes"):
        parse_rob("<Rob/>")


@settings(max_examples=300, deadline=None, database=None)
@given(st.binary(max_size=400))
def test_random_bytes_never_raise_anything_but_protocol_error(data):
    try:
        parse_rob(data)
    except ProtocolError:
        pass


@settings(max_examples=300, deadline=None, database=None)
@given(st.integers(0, len(SIMULATOR_ROB) - 1), st.binary(min_size=0, max_size=3), st.integers(0, 3))
def test_mutated_packets_decode_or_raise_protocol_error(pos, insert, cut):
    data = SIMULATOR_ROB[:pos] + insert + SIMULATOR_ROB[pos + cut :]
    try:
        s = parse_rob(data)
    except ProtocolError:
        return
    assert len(s.axis_actual_deg) <= 6


@pytest.mark.parametrize("args", [(0, 0), (7, 0), (6, 7)])
def test_formatter_refuses_axis_counts_rsi_cannot_carry(args):
    with pytest.raises(ValueError, match="RSI carries"):
        SenFormatter(*args)


def test_formatter_refuses_a_type_that_would_break_the_xml():
    with pytest.raises(ValueError, match="XML name"):
        SenFormatter(6, 0, 'Im"Free')
