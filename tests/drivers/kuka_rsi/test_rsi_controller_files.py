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
    assert SHIPPED.name in notes and "Out7" in notes and "STOP1" in notes


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
RSI3 = CONTROLLER / "remaster_rsi.rsi.xml"
RSI3_MODEL = CONTROLLER / "remaster_rsi.rsi"
#: The namespaces of a context RSIVisual (WorkVisual, RSI 4.x/5.x) writes.
NS = {"ctx": "RsiContext", "drv": "RsiDriver", "con": "RsiConstruct"}
#: Object type ids of the RSI toolbox (the same in RSI 3.x and 4.x/5.x contexts).
TYPE_IDS = {"ETHERNET": "64", "AXISCORR": "33", "AXISCORRMON": "82", "STOP": "18"}
#: STOP's modes, in the toolbox's order: the value is the index.
STOP_MODES = ("InfoMessage", "PathNormal", "Velocity", "PathFast", "ExitMoveCorr")


def _rsix():
    """(objects by id, construct inputs {(object, port): (source object, source port)}) of the
    RSI 4.x/5.x context."""
    root = ET.parse(RSIX).getroot()
    assert root.tag == "{RsiContext}RsiContext" and root.get("SchemaVersion") == "2.0.0"
    objects = {o.get("ObjId"): o for o in root.find("drv:RsiObjects", NS).findall("drv:RsiObject", NS)}
    links = {}
    for con in root.find("con:Constructs", NS).findall("con:Construct", NS):
        for i in con.iter("{RsiConstruct}Input"):
            links[(con.get("Name"), i.get("Name"))] = (i.get("SourceObject"), i.get("SourcePort"))
    return objects, links


def _rsi3():
    """Objects by id of the RSI 3.x object list (the file the KSS 8.3 controller loads)."""
    root = ET.parse(RSI3).getroot()
    assert root.tag == "RSIObjects"
    return {o.get("ObjID"): o for o in root.findall("RSIObject")}


def _of_type(objects: dict, kind: str, attr: str = "ObjType"):
    (obj,) = [o for o in objects.values() if o.get(attr).upper() == kind]
    return obj


def _params(obj, ns: str = "", pid: str = "ParamId") -> dict:
    return {p.get("Name"): (int(p.get(pid)), p.get("ParamValue")) for p in obj.iter(f"{ns}Parameter")}


def _inputs(obj, ns: str = "", out: str = "OutObjId") -> dict:
    return {int(i.get("InIdx")): (i.get(out), int(i.get("OutIdx"))) for i in obj.iter(f"{ns}Input")}


def test_both_contexts_read_the_shipped_ethernet_configuration_and_the_program_loads_them():
    objects, _ = _rsix()
    eth = _of_type(objects, "ETHERNET")
    assert eth.get("ObjTypeId") == TYPE_IDS["ETHERNET"]
    assert _params(eth, "{RsiDriver}")["ConfigFile"] == (0, SHIPPED.name)  # the file RSI_CREATE's context loads
    eth3 = _of_type(_rsi3(), "ETHERNET")
    assert eth3.get("ObjTypeID") == TYPE_IDS["ETHERNET"]
    assert _params(eth3, pid="ParamID")["ConfigFile"] == (1, SHIPPED.name)
    src = (CONTROLLER / "remaster_rsi.src").read_text()
    assert 'RSI_CREATE("remaster_rsi", CONTID, TRUE)' in src  # RSI 4.x/5.x add .rsix
    assert 'RSI_CREATE("remaster_rsi.rsi", CONTID, TRUE)' in src  # the KSS 8.3 line, named in the notes
    notes = (CONTROLLER / "README.md").read_text()
    for f in (RSIX, RSI3, RSI3_MODEL, SHIPPED):
        assert f"`{f.name}`" in notes


def test_every_axis_correction_the_codec_sends_reaches_axiscorr_on_its_own_axis():
    """The codec sends AK.A1..A6; the ethernet configuration maps each to channel INDX n, which
    the Ethernet object outputs as Out<n>: RSI 4.x/5.x number it OutIdx n-1 (0-based), RSI 3.x
    OutIdx n. Each context must route AK.An to AXISCORR's CorrAn — in the objects the controller
    runs and (RSI 4.x/5.x) in the editor's view — within ±20° of the start."""
    cfg = RsiEthernetConfig.load()
    sen = ET.fromstring(SenFormatter(6, 0, cfg.sen_type).format([0.5] * 6, True, 1))
    sent_axes = [f"AK.{k}" for k in sen.find("AK").attrib]
    objects, links = _rsix()
    eth_id = _of_type(objects, "ETHERNET").get("ObjId")
    corr = _of_type(objects, "AXISCORR")
    rsi3 = _rsi3()
    corr3 = _of_type(rsi3, "AXISCORR")
    eth3_id = _of_type(rsi3, "ETHERNET").get("ObjID")
    for tag in sent_axes:
        axis, channel = int(tag[-1]), cfg.receive[tag]
        assert _inputs(corr, "{RsiDriver}")[axis - 1] == (eth_id, channel - 1), tag
        assert links[(corr.get("ObjId"), f"CorrA{axis}")] == (eth_id, f"Out{channel}"), tag
        assert _inputs(corr3, out="OutObjID")[axis] == (eth3_id, channel), tag
    # parameter ids: RSI 4.x/5.x LowerLimA1..A6 = 0..5, UpperLimA1..A6 = 6..11; RSI 3.x
    # LowerLimA1..A6 = 1..6, UpperLimA1..A6 = 13..18 (7..12 are the external axes')
    for obj, ns, pid, lower1, upper1 in ((corr, "{RsiDriver}", "ParamId", 0, 6), (corr3, "", "ParamID", 1, 13)):
        limits = _params(obj, ns, pid)
        for a in range(1, 7):
            (i_lo, lo), (i_hi, hi) = limits[f"LowerLimA{a}"], limits[f"UpperLimA{a}"]
            assert -20 <= float(lo) < 0 < float(hi) <= 20
            assert (i_lo, i_hi) == (lower1 + a - 1, upper1 + a - 1)


def test_the_stop_flag_the_commander_sends_ends_rsi_movecorr_in_both_contexts():
    """``RsiCommander.stop()`` sends <Stop>1</Stop>; the ethernet configuration puts it on a
    channel; that channel must feed a STOP object in ExitMoveCorr mode (RSI_MOVECORR returns and
    the program goes on to RSI_OFF), or the move never ends from our side."""
    cfg = RsiEthernetConfig.load()
    sen = ET.fromstring(SenFormatter(6, 0, cfg.sen_type).format([0.0] * 6, True, 1))
    assert sen.find("Stop").text == "1"
    channel = cfg.receive["Stop"]
    objects, links = _rsix()
    stop = _of_type(objects, "STOP")
    eth_id = _of_type(objects, "ETHERNET").get("ObjId")
    assert stop.get("ObjTypeId") == TYPE_IDS["STOP"]
    assert _inputs(stop, "{RsiDriver}") == {0: (eth_id, channel - 1)}
    assert links[(stop.get("ObjId"), "In1")] == (eth_id, f"Out{channel}")
    params = _params(stop, "{RsiDriver}")
    assert STOP_MODES[int(params["Mode"][1])] == "ExitMoveCorr" and params["Channel"] == (1, "0")
    rsi3 = _rsi3()
    stop3 = _of_type(rsi3, "STOP")
    assert stop3.get("ObjTypeID") == TYPE_IDS["STOP"]
    assert _inputs(stop3, out="OutObjID") == {1: (_of_type(rsi3, "ETHERNET").get("ObjID"), channel)}
    params3 = _params(stop3, pid="ParamID")
    assert STOP_MODES[int(params3["Mode"][1])] == "ExitMoveCorr" and params3["Channel"] == (2, "0")
    src = (CONTROLLER / "remaster_rsi.src").read_text()
    assert src.index("RSI_MOVECORR()") < src.index("RSI_OFF()")


def test_the_rsi3_model_rsi_visual_edits_matches_the_object_list_the_controller_loads():
    ns = "{http://schemas.microsoft.com/dsltools/RSIVisual}"
    model = ET.parse(RSI3_MODEL).getroot()
    assert model.tag == f"{ns}rSIModel"
    elements = {e.get("name"): e for e in model.iter(f"{ns}rSIElement")}
    rsi3 = _rsi3()
    assert {k: e.get("objTypeID") for k, e in elements.items()} == {k: o.get("ObjTypeID") for k, o in rsi3.items()}
    for name, obj in rsi3.items():
        want = {p.get("Name"): (int(p.get("ParamID")), p.get("ParamValue")) for p in obj.iter("Parameter")}
        got = {p.get("name"): (int(p.get("index")), p.get("value")) for p in elements[name].iter(f"{ns}rSIParameter")}
        if name.startswith("STOP"):  # the model names the enum value, the object list its number
            got["Mode"] = (got["Mode"][0], str(STOP_MODES.index(got["Mode"][1])))
        assert got == want, name
        for i in obj.iter("Input"):
            port = elements[name].findall(f"{ns}rSIInPorts/{ns}rSIInPort")[int(i.get("InIdx")) - 1]
            (src,) = port.iter(f"{ns}rSIOutPortMoniker")
            assert src.get("name") == f"//{i.get('OutObjID')}/Out{i.get('OutIdx')}", name


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
