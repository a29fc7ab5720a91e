"""The controller-side files shipped with the RSI commander agree with what the codec sends and
reads, and the fake KR C4 is driven by the same configuration."""

from __future__ import annotations

import re
import socket
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from drivers.kuka_rsi.codec import RobFormatter, SenFormatter, parse_rob
from drivers.kuka_rsi.ethernet_config import SHIPPED, RsiEthernetConfig
from drivers.kuka_rsi.fake import FakeKrc4

CONTROLLER = SHIPPED.parent


def test_the_shipped_configuration_sends_what_the_codec_reads():
    cfg = RsiEthernetConfig.load()
    packet = RobFormatter(6, 0, elements=cfg.send).format(
        [1, 2, 3, 4, 5, 6], [0] * 6, [100, 0, 500, 0, 90, 0], [0] * 6, 3, 4_000_004)
    rob = parse_rob(packet)
    assert rob.axis_actual_deg == (1, 2, 3, 4, 5, 6)
    assert rob.axis_setpoint_deg == (0,) * 6  # ASPos: the reference of absolute corrections
    assert rob.delay == 3 and rob.ipoc == 4_000_004  # DEF_Delay: the controller's late count
    assert rob.cartesian_actual == (100, 0, 500, 0, 90, 0)


def test_every_element_of_our_answer_is_read_by_the_shipped_configuration():
    cfg = RsiEthernetConfig.load()
    sen = ET.fromstring(SenFormatter(6, 0, cfg.sen_type).format([0.5] * 6, True, 4_000_004))
    assert sen.get("Type") == cfg.sen_type
    tags = set()
    for child in sen:
        if child.tag == "IPOC":
            continue  # RSI matches the IPOC itself
        tags |= {f"{child.tag}.{k}" for k in child.attrib} if child.attrib else {child.tag}
    assert tags == set(cfg.receive), "each value we send must reach a channel, and only those"
    assert sorted(cfg.receive.values()) == list(range(1, 8))
    assert cfg.reads_stop and cfg.axes_read() == 6 and not cfg.only_send


def test_the_krl_program_and_the_notes_name_the_shipped_files():
    src = (CONTROLLER / "remaster_rsi.src").read_text()
    notes = (CONTROLLER / "README.md").read_text()
    assert re.search(r"RSI_ON\(#ABSOLUTE, #IPO_FAST\)", src)  # absolute AK from ASPos, 4 ms
    assert "RSI_MOVECORR()" in src and "RSI_OFF()" in src
    assert SHIPPED.name in notes and "Out7" in notes and "STOP" in notes


def _config(tmp_path: Path, *, sen_type="ImFree", stop=True) -> RsiEthernetConfig:
    text = SHIPPED.read_text().replace("<SENTYPE>ImFree</SENTYPE>", f"<SENTYPE>{sen_type}</SENTYPE>")
    if not stop:  # ROS-I's KR C4 setup: AK.A1..A6 only
        text = text.replace('<ELEMENT TAG="Stop" TYPE="BOOL" INDX="7" HOLDON="1" />', "")
    path = tmp_path / "rsi.xml"
    path.write_text(text)
    return RsiEthernetConfig.load(path)


def _answer(fake: FakeKrc4, sock: socket.socket, n: int, *, stop: bool, sen_type="ImFree") -> int:
    """Answer up to ``n`` state packets; returns how many came (the fake may stop sending)."""
    fmt = SenFormatter(6, 0, sen_type)
    for k in range(n):
        try:
            rob = parse_rob(sock.recv(4096))
        except TimeoutError:
            return k
        sock.sendto(fmt.format([0.0] * 6, stop, rob.ipoc), fake.address)
    return n


@pytest.mark.parametrize("reads_stop", [True, False])
def test_the_fake_honours_stop_only_when_its_configuration_maps_it(tmp_path, reads_stop):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)
    try:
        with FakeKrc4(sock.getsockname(), ethernet_config=_config(tmp_path, stop=reads_stop), lockstep=True) as fake:
            served = _answer(fake, sock, 20, stop=True)
            reason = fake.stats().stopped_reason
    finally:
        sock.close()
    if reads_stop:
        assert served < 20 and reason == "Stop flag from the sensor"
    else:  # the flag reaches no channel: the session goes on
        assert served == 20 and reason is None


def test_the_fake_ignores_answers_of_another_sensor_type(tmp_path):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    try:
        with FakeKrc4(sock.getsockname(), ethernet_config=_config(tmp_path, sen_type="Remaster"),
                      lockstep=True) as fake:
            _answer(fake, sock, 5, stop=False, sen_type="ImFree")
            time.sleep(0.05)
            stats = fake.stats()
    finally:
        sock.close()
    assert stats.answers_on_time == 0 and stats.malformed_answers >= 4
    assert "is not the configured SENTYPE 'Remaster'" in stats.errors[0]


def test_a_broken_configuration_is_refused_with_its_file_and_element(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text(SHIPPED.read_text().replace('TAG="DEF_Delay"', 'TAG="DEF_Dealy"'))
    with pytest.raises(ValueError, match=r"bad.xml: SEND element TAG='DEF_Dealy' is not one we know"):
        RsiEthernetConfig.load(bad)
    with pytest.raises(ValueError, match="reads 6 AK corrections; the robot has 5 axes"):
        FakeKrc4(("127.0.0.1", 9), n_axes=5, ethernet_config=RsiEthernetConfig.load())


RSIX = CONTROLLER / "remaster_rsi.rsix"


def _rsix_objects():
    root = ET.parse(RSIX).getroot()
    assert root.tag == "RsiContext"
    return {o.get("ObjId"): o for o in root.find("RsiObjects")}, root


def test_the_rsi_context_reads_the_shipped_ethernet_configuration():
    objects, _ = _rsix_objects()
    eth = [o for o in objects.values() if o.get("ObjType") == "Ethernet"]
    assert len(eth) == 1
    params = {p.get("Name"): p.get("ParamValue") for p in eth[0].iter("Parameter")}
    assert params["ConfigFile"] == SHIPPED.name  # the file RSI_CREATE's context loads
    src = (CONTROLLER / "remaster_rsi.src").read_text()
    assert f'RSI_CREATE("{RSIX.name}"' in src


def test_every_axis_correction_the_codec_sends_reaches_axiscorr_on_its_own_axis():
    """The codec sends AK.A1..A6; the ethernet configuration maps each to channel INDX n, which
    the Ethernet object outputs as Out<n> (input index n-1): the context must route Out<n> of
    AK.An to AxisCorr's CorrAn, in both the object list and the editor's links."""
    cfg = RsiEthernetConfig.load()
    sen = ET.fromstring(SenFormatter(6, 0, cfg.sen_type).format([0.5] * 6, True, 1))
    sent_axes = [f"AK.{k}" for k in sen.find("AK").attrib]
    objects, root = _rsix_objects()
    eth_id = next(k for k, o in objects.items() if o.get("ObjType") == "Ethernet")
    corr = next(o for o in objects.values() if o.get("ObjType") == "AxisCorr")
    inputs = {int(i.get("InIdx")): (i.get("OutObjId"), int(i.get("OutIdx"))) for i in corr.iter("Input")}
    links = {(ln.get("From"), ln.get("FromPort")): (ln.get("To"), ln.get("ToPort")) for ln in root.iter("Link")}
    for tag in sent_axes:
        axis = int(tag[-1])
        channel = cfg.receive[tag]
        assert inputs[axis - 1] == (eth_id, channel - 1), tag
        assert links[(eth_id, f"Out{channel}")] == (corr.get("ObjId"), f"CorrA{axis}"), tag
    limits = {p.get("Name"): float(p.get("ParamValue")) for p in corr.iter("Parameter")}
    for a in range(1, 7):
        assert -20 <= limits[f"LowerLimA{a}"] < 0 < limits[f"UpperLimA{a}"] <= 20
    # Stop (channel 7) goes to the STOP object the README has the integrator add
    notes = (CONTROLLER / "README.md").read_text()
    assert f"Out{cfg.receive['Stop']}" in notes and "STOP" in notes
    assert (eth_id, f"Out{cfg.receive['Stop']}") not in links or links[(eth_id, "Out7")][0].startswith("Stop")


def test_the_krl_program_is_written_as_a_kuka_integrator_writes_it():
    src = (CONTROLLER / "remaster_rsi.src").read_text()
    lines = [ln.strip() for ln in src.splitlines()]
    assert "INI" not in lines  # INI is a fold, not a statement
    assert lines.index(";FOLD INI") < lines.index(";ENDFOLD (INI)")
    assert re.search(r"INTERRUPT DECL \d+ WHEN \$STOPMESS==TRUE DO IR_STOPM", src)
    assert re.search(r"BAS \(#INITMOV,0 \)", src)
    for call in ("RSI_CREATE", "RSI_ON", "RSI_MOVECORR", "RSI_OFF", "RSI_DELETE"):
        i = next(k for k, ln in enumerate(lines) if ln.startswith(f"ret = {call}("))
        assert lines[i + 1] == "IF (ret <> RSIOK) THEN" and lines[i + 2].startswith("HALT"), call
