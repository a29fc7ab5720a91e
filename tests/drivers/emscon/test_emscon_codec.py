"""The emScon codec: every layout round-trips and matches the bytes of the independent CESAPI
1.1.3 packet classes; every status maps to a typed error; garbled packets raise only
ProtocolError."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from drivers import errors
from drivers.emscon import codec as es
from drivers.emscon.codec import LAYOUTS, RESULT_LAYOUTS, Cmd, SSC, Status
from drivers.emscon.status import ERROR_CLASSES, WARNINGS, error_for

P = pytest.importorskip("CESAPI.packet", reason="CESAPI 1.1.3 (the test extra) is the independent peer")


def _values(fields, rng) -> dict:
    out = {}
    for name, code in fields:
        if code == "d":
            out[name] = float(rng.normal(0, 1000))
        elif code == "i":
            out[name] = int(rng.integers(-(2 ** 31), 2 ** 31))
        elif code == "I":
            out[name] = int(rng.integers(0, 2 ** 32))
        else:
            out[name] = "RRR 1.5in Ω"[: int(rng.integers(1, 12))]
    return out


def _cesapi_name(cmd: Cmd) -> str:
    return cmd.name.replace("SystemParameter", "SystemParam")


def _cesapi_set(obj, name, value) -> bool:
    """Set field ``name`` wherever it sits in a CESAPI packet object (nested structs too)."""
    for key, sub in vars(obj).items():
        if key == name:
            setattr(obj, name, value.encode("utf-16-le") if isinstance(value, str) else value)
            return True
        if hasattr(sub, "__dict__") and key not in ("packetInfo", "packetHeader") and _cesapi_set(sub, name, value):
            return True
    return False


def _cesapi_get(obj, name):
    for key, sub in vars(obj).items():
        if key == name:
            return sub
        if hasattr(sub, "__dict__") and key not in ("packetInfo", "packetHeader"):
            found = _cesapi_get(sub, name)
            if found is not None:
                return found
    return None


#: 6-DoF packets: CESAPI is generated from the AT4xx (3D) extract of the header, which has none of
#: them; tests/drivers/emscon/test_emscon_6dof.py checks them against the full header's layout.
SIX_DOF_COMMANDS = (Cmd.GetMeasurementProbeInfo,)
SIX_DOF_RESULTS = (es.DataType.StationaryProbeMeasResult,)
CESAPI_COMMANDS = [c for c in LAYOUTS if c not in SIX_DOF_COMMANDS]


@pytest.mark.parametrize("cmd", CESAPI_COMMANDS, ids=lambda c: c.name)
def test_every_request_round_trips_and_matches_cesapi_bytes(cmd):
    rng = np.random.default_rng(int(cmd))
    req = es.Request(cmd, _values(LAYOUTS[cmd][0], rng))
    data = es.encode(req)
    assert len(data) == es.request_size(cmd) == struct.unpack_from("<i", data)[0]
    assert es.decode_request(data) == req
    theirs = getattr(P, _cesapi_name(cmd) + "CT")()
    for name, value in req.params.items():
        assert _cesapi_set(theirs, name, value), name
    assert theirs.pack() == data


@pytest.mark.parametrize("cmd", CESAPI_COMMANDS, ids=lambda c: c.name)
def test_every_answer_round_trips_and_cesapi_reads_our_values(cmd):
    rng = np.random.default_rng(1000 + int(cmd))
    values = _values(LAYOUTS[cmd][1], rng)
    ans = es.Answer(cmd, Status.AllOK, values)
    data = es.encode(ans)
    assert len(data) == es.answer_size(cmd)
    assert es.decode(data) == ans
    theirs = getattr(P, _cesapi_name(cmd) + "RT")()
    theirs.unpack(data)
    assert theirs.packetInfo.command == cmd and theirs.packetInfo.status == 0
    for name, value in values.items():
        got = _cesapi_get(theirs, name)
        if isinstance(value, str):
            got = got.decode("utf-16-le").split("\0", 1)[0]
        assert got == value, name


@pytest.mark.parametrize("kind", [t for t in RESULT_LAYOUTS if t not in SIX_DOF_RESULTS], ids=lambda t: t.name)
def test_result_packets_match_cesapi(kind):
    rng = np.random.default_rng(int(kind))
    res = es.DataResult(kind, Status.AllOK, _values(RESULT_LAYOUTS[kind], rng))
    data = es.encode(res)
    assert es.decode(data) == res
    theirs = {es.DataType.SingleMeasResult: P.SingleMeasResultT, es.DataType.SingleMeasResult2: P.SingleMeasResult2T,
              es.DataType.NivelResult: P.NivelResultT, es.DataType.ReflectorPosResult: P.ReflectorPosResultT}[kind]()
    for name, value in res.values.items():
        assert _cesapi_set(theirs, name, value)
    theirs.packetInfo.packetHeader.lPacketSize = len(data)
    assert theirs.pack() == data


def test_status_change_and_error_packets_match_cesapi():
    ssc = P.SystemStatusChangeT()
    ssc.systemStatusChange = P.ES_SSC_MeasStatus_Ready
    assert es.encode(es.StatusChange(SSC.MeasStatus_Ready)) == ssc.pack()
    err = P.ErrorResponseT()
    err.command, err.status = P.ES_C_StartMeasurement, P.ES_RS_NoTPFound
    assert es.decode(err.pack()) == es.ErrorAnswer(Cmd.StartMeasurement, Status.NoTPFound)


@pytest.mark.parametrize(("prefix", "enum"), [("ES_RS_", Status), ("ES_C_", Cmd), ("ES_SSC_", SSC),
                                              ("ES_DT_", es.DataType), ("ES_SP_", es.SystemParameter),
                                              ("ES_TT_", es.TargetType)])
def test_enums_agree_with_cesapi_by_name_and_value(prefix, enum):
    theirs = {k[len(prefix):]: v for k, v in vars(P).items() if k.startswith(prefix)}
    if prefix == "ES_TT_":  # CESAPI mixes ES_TargetType and ES_TrackerProcessorType under ES_TT_
        theirs = {k: v for k, v in theirs.items() if k in es.TargetType.__members__}
    ours = {m: int(getattr(enum, m)) for m in enum.__members__}
    aliases = {"SystemParam": "SystemParameter"}
    checked = 0
    for name, value in theirs.items():
        for variant in (name, name.replace("6D", "SixD"), *[name.replace(a, b) for a, b in aliases.items()]):
            if variant in ours:
                assert ours[variant] == value, (name, ours[variant], value)
                checked += 1
                break
        else:
            pytest.fail(f"{prefix}{name} = {value} (CESAPI) is missing from {enum.__name__}")
    assert checked == len(theirs)


def test_every_status_maps_to_a_typed_error_or_is_a_warning():
    for s in Status:
        if s is Status.AllOK:
            continue
        assert (s in WARNINGS) != (s in ERROR_CLASSES), s
        if s in ERROR_CLASSES:
            exc = error_for(s, "tracker: StartMeasurement")
            assert isinstance(exc, errors.DriverError) and exc.status == s
            assert f"ES_RS_{s.name}" in str(exc) and "StartMeasurement" in str(exc)
    expected = {
        Status.MeasurementStatusNotReady: errors.TargetLostError,
        Status.NoStationaryResult: errors.TargetLostError,
        Status.NoDistanceSet: errors.DistanceLostError,
        Status.SensorNotWarmedUp: errors.TrackerWarmingUpError,
        Status.WrongParameter3: errors.LimitError,
        Status.MeteoDataOutOfRange: errors.LimitError,
        Status.NotImplemented: errors.ProtocolError,
        Status.ModuleTimedOut: errors.DeviceTimeoutError,
        Status.NoTrackerConnected: errors.DeviceFaultError,
        Status.TrackerNotInitialized: errors.DeviceFaultError,
    }
    for s, cls in expected.items():
        assert type(error_for(s, "x")) is cls, s
    unknown = error_for(77777, "tracker: GoPosition")
    assert type(unknown) is errors.DeviceFaultError and "77777" in str(unknown)


def test_server_side_refusals_carry_the_status_to_answer():
    good = es.encode(es.Request(Cmd.GoPosition, {"dVal1": 1.0, "dVal2": 2.0, "dVal3": 3.0, "bUseADM": 1}))
    with pytest.raises(es.RequestRefused) as exc:
        es.decode_request(good[:-4] + struct.pack("<i", 1)[:0])  # 4 bytes short, header still says 40
    assert exc.value.as_error and exc.value.status is Status.InvalidInputData
    short = struct.pack("<iII", 12, 0, int(Cmd.GoPosition))
    with pytest.raises(es.RequestRefused) as exc:
        es.decode_request(short)
    assert (exc.value.command, exc.value.status, exc.value.as_error) == (Cmd.GoPosition, Status.WrongParameter, False)
    with pytest.raises(es.RequestRefused) as exc:
        es.decode_request(struct.pack("<iII", 12, 0, 141))  # unassigned command id
    assert exc.value.as_error and exc.value.status is Status.NotImplemented
    with pytest.raises(es.RequestRefused) as exc:
        es.decode_request(struct.pack("<iII", 12, 0, int(Cmd.GetStillImage)))  # known, not implemented here
    assert not exc.value.as_error and exc.value.status is Status.NotImplemented
    nan_y = bytearray(good)
    struct.pack_into("<d", nan_y, 20, math.nan)
    with pytest.raises(es.RequestRefused) as exc:
        es.decode_request(bytes(nan_y))
    assert exc.value.status is Status.WrongParameter2


def test_encoder_refuses_values_the_layout_cannot_carry():
    with pytest.raises(ValueError, match="lMeasTime"):
        es.Request(Cmd.SetStationaryModeParams, {"lMeasTime": 2 ** 31, "bUseADM": 1})
    with pytest.raises(ValueError, match="exactly the fields"):
        es.Request(Cmd.FindReflector, {})
    with pytest.raises(ValueError, match="no layout"):
        es.Request(Cmd.GetStillImage)
    with pytest.raises(ValueError, match="at most 32"):
        es.encode(es.Answer(Cmd.GetSystemSoftwareVersion, 0, {"cSoftwareVersion": "x" * 33}))


def test_split_frames_keeps_a_partial_tail_and_refuses_an_impossible_size():
    a = es.encode(es.StatusChange(SSC.DistanceSet))
    b = es.encode(es.Answer(Cmd.GetReflector, 0, {"iInternalReflectorId": 2}))
    buf = bytearray(a + b[:7])
    assert es.split_frames(buf) == [a] and buf == bytearray(b[:7])
    buf += b[7:]
    assert es.split_frames(buf) == [b] and not buf
    buf = bytearray(struct.pack("<iI", 10 ** 6, 0) + b"\0" * 8)
    with pytest.raises(errors.ProtocolError, match="out of step"):
        es.split_frames(buf)
    assert not buf


def _valid_server_packets() -> list[bytes]:
    rng = np.random.default_rng(11)
    out = [es.encode(es.Answer(c, 0, _values(LAYOUTS[c][1], rng))) for c in LAYOUTS]
    out += [es.encode(es.Answer(c, int(Status.NoTPFound))) for c in list(LAYOUTS)[:5]]
    out += [es.encode(es.DataResult(t, 0, _values(f, rng))) for t, f in RESULT_LAYOUTS.items()]
    out += [es.encode(es.StatusChange(SSC.MeasStatus_NotReady)), es.encode(es.ErrorAnswer(Cmd.Unknown, 98))]
    return out


def _valid_requests() -> list[bytes]:
    rng = np.random.default_rng(12)
    return [es.encode(es.Request(c, _values(LAYOUTS[c][0], rng))) for c in LAYOUTS]


def _mutate(rng, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(0, 7))
        i = int(rng.integers(0, max(1, len(b))))
        if op == 0 and b:  # flip a bit
            b[min(i, len(b) - 1)] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:  # truncate
            del b[i:]
        elif op == 2:  # insert junk
            b[i:i] = rng.integers(0, 256, int(rng.integers(1, 9))).astype(np.uint8).tobytes()
        elif op == 3 and len(b) >= 8:  # lie about the size
            struct.pack_into("<i", b, 0, int(rng.integers(-5, 300)))
        elif op == 4 and len(b) >= 8:  # another type
            struct.pack_into("<I", b, 4, int(rng.integers(0, 14)))
        elif op == 5 and len(b) >= 12:  # another command / status change
            struct.pack_into("<I", b, 8, int(rng.integers(0, 160)))
        else:  # random garbage
            b = bytearray(rng.integers(0, 256, int(rng.integers(0, 64))).astype(np.uint8).tobytes())
    return bytes(b)


def test_ten_thousand_garbled_server_packets_raise_only_protocol_error():
    rng = np.random.default_rng(2026)
    pool = _valid_server_packets()
    refused = decoded = 0
    for k in range(10_000):
        data = _mutate(rng, pool[k % len(pool)])
        try:
            packet = es.decode(data)
        except errors.ProtocolError:
            refused += 1
            continue
        decoded += 1
        assert isinstance(packet, (es.Answer, es.ErrorAnswer, es.DataResult, es.StatusChange))
        assert len(es.encode(packet)) == len(data) or isinstance(packet, es.Answer)
    assert refused > 5_000 and decoded > 100  # both paths exercised


def test_ten_thousand_garbled_requests_raise_only_request_refused():
    rng = np.random.default_rng(2027)
    pool = _valid_requests()
    for k in range(10_000):
        data = _mutate(rng, pool[k % len(pool)])
        try:
            req = es.decode_request(data)
        except es.RequestRefused as exc:
            assert isinstance(exc.status, Status) and exc.status != Status.AllOK
            continue
        assert es.encode(req) == data  # what was accepted is exactly what was sent


def test_garbled_byte_streams_split_into_frames_or_raise_protocol_error():
    rng = np.random.default_rng(2028)
    pool = _valid_server_packets()
    for _ in range(2_000):
        stream = b"".join(_mutate(rng, pool[int(rng.integers(0, len(pool)))]) if rng.random() < 0.2
                          else pool[int(rng.integers(0, len(pool)))] for _ in range(5))
        buf = bytearray(stream)
        try:
            frames = es.split_frames(buf)
        except errors.ProtocolError:
            assert not buf
            continue
        assert b"".join(frames) + bytes(buf) == stream
        for f in frames:
            try:
                es.decode(f)
            except errors.ProtocolError:
                pass
