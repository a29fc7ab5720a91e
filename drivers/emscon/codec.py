"""Leica emScon TPI packets (``ES_C_API_Def.h``, TPI/SDK version 3.6) as pure data and functions.

Every packet is a little-endian C struct packed to 4 bytes (``#pragma pack(4)``; ``ES_BOOL`` is a
4-byte int, enums are 4-byte unsigned) that starts with ``PacketHeaderT {long lPacketSize;
ES_DataType type;}``: the size of the whole packet in bytes and what follows.

- ``ES_DT_Command`` host → server: ``BasicCommandCT {header; ES_Command command;}`` then the
  command's parameters (``Request``).
- ``ES_DT_Command`` server → host: ``BasicCommandRT {header; command; ES_ResultStatus status;}``
  then the command's results (``Answer``). A refused command has ``status != ES_RS_AllOK``.
- ``ES_DT_Error`` server → host: ``ErrorResponseT {header; command; status;}`` (``ErrorAnswer``).
- ``ES_DT_SingleMeasResult`` / ``ES_DT_SingleMeasResult2`` / ``ES_DT_NivelResult`` /
  ``ES_DT_ReflectorPosResult``: ``ReturnDataT {header; status;}`` then values (``DataResult``).
- ``ES_DT_StationaryProbeMeasResult``: ``ProbeStationaryResultT {ReturnDataT; ...}``, the result of
  a 6-DoF stationary measurement (``ES_MM_6DStationary``): status words, the probe and tip, the
  position with its std devs and covariances (measured and a-priori), the orientation as a
  quaternion ``dQuaternion0..3`` (scalar ``dQuaternion0`` first; the header's SDK sample builds
  the probe's x, y, z axes in tracker coordinates as the columns of its rotation matrix, so it is
  ``R_tracker←probe``) and as rotation angles with their std devs, and the air (``DataResult``).
- ``ES_DT_SystemStatusChange``: ``{header; ES_SystemStatusChange systemStatusChange;}``
  (``StatusChange``), unsolicited.

The enums are in ``drivers.emscon.enums`` (re-exported here). Layouts come from Leica's public
``ES_C_API_Def.h`` (V3.6) and agree with the MIT-licensed
``CESAPI`` 1.1.3 client generated from the AT4xx extract of the same header. Field names are the
header's (``dVal1``, ``lMeasTime`` ...) so the manual can be read beside this code.

Malformed bytes raise only ``drivers.errors.ProtocolError``; on the server side a
``RequestRefused`` (a ProtocolError) that carries the command id and the ``ES_ResultStatus`` to
answer with.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Any, Mapping, Union

from drivers.emscon.enums import (  # noqa: F401 - re-exported: the codec speaks in these
    DataType,
    Cmd,
    Status,
    SSC,
    LengthUnit,
    AngleUnit,
    TemperatureUnit,
    PressureUnit,
    HumidityUnit,
    CoordinateSystem,
    MeasMode,
    TriggerStatus,
    MeasurementTipStatus,
    ProbeType,
    ProbeConnectionType,
    ProbeButtonType,
    TargetType,
    TrackerStatus,
    SystemParameter,
    WeatherMonitorStatus,
    TrackerProcessorStatus,
    LaserProcessorStatus,
    ADMStatus,
)
from drivers.errors import ProtocolError

#: Smallest packet: a header plus one 4-byte word (a command, a status change).
MIN_PACKET = 12
#: Largest packet either side accepts (emScon's largest fixed structs are a few hundred bytes).
MAX_PACKET = 4096
HEADER = struct.Struct("<iI")
#: Default TCP port of the emScon server.
DEFAULT_PORT = 700
#: Characters of a ``unsigned short name[32]`` (UTF-16LE) field.
NAME_CHARS = 32

API_VERSION = (3, 6)


# --------------------------------------------------------------------------- layouts
# Field codes: "i" int32 (long / int / ES_BOOL), "I" uint32 (an enum), "d" double,
# "w" unsigned short[32] (UTF-16LE text, 64 bytes).
Fields = tuple[tuple[str, str], ...]

_UNITS: Fields = (("lenUnitType", "I"), ("angUnitType", "I"), ("tempUnitType", "I"),
                  ("pressUnitType", "I"), ("humUnitType", "I"))
_ENV: Fields = (("dTemperature", "d"), ("dPressure", "d"), ("dHumidity", "d"))
_STATIONARY: Fields = (("lMeasTime", "i"), ("bUseADM", "i"))
_SEARCH: Fields = (("dSearchRadius", "d"), ("lTimeOut", "i"))
_XYZ: Fields = (("dVal1", "d"), ("dVal2", "d"), ("dVal3", "d"))

#: (request parameters, answer values) per command this codec knows the layout of.
LAYOUTS: dict[Cmd, tuple[Fields, Fields]] = {
    Cmd.ExitApplication: ((), ()),
    Cmd.GetSystemStatus: ((), (
        ("lastResultStatus", "I"), ("trackerProcessorStatus", "I"), ("laserStatus", "I"), ("admStatus", "I"),
        ("iMajorVersionNumber", "i"), ("iMinorVersionNumber", "i"), ("iBuildNumber", "i"),
        ("weatherMonitorStatus", "I"), ("lFlagsValue", "i"), ("lTrackerSerialNumber", "i"))),
    Cmd.GetTrackerStatus: ((), (("trackerStatus", "I"),)),
    Cmd.SetUnits: (_UNITS, ()),
    Cmd.GetUnits: ((), _UNITS),
    Cmd.Initialize: ((), ()),
    Cmd.Park: ((), ()),
    Cmd.SetEnvironmentParams: (_ENV, ()),
    Cmd.GetEnvironmentParams: ((), _ENV),
    Cmd.SetMeasurementMode: ((("measMode", "I"),), ()),
    Cmd.GetMeasurementMode: ((), (("measMode", "I"),)),
    Cmd.SetCoordinateSystemType: ((("coordSysType", "I"),), ()),
    Cmd.GetCoordinateSystemType: ((), (("coordSysType", "I"),)),
    Cmd.SetStationaryModeParams: (_STATIONARY, ()),
    Cmd.GetStationaryModeParams: ((), _STATIONARY),
    Cmd.SetReflector: ((("iInternalReflectorId", "i"),), ()),
    Cmd.GetReflector: ((), (("iInternalReflectorId", "i"),)),
    Cmd.GetReflectors: ((), (("iTotalReflectors", "i"), ("iInternalReflectorId", "i"), ("targetType", "I"),
                             ("dSurfaceOffset", "d"), ("cReflectorName", "w"))),
    Cmd.SetSearchParams: (_SEARCH, ()),
    Cmd.GetSearchParams: ((), _SEARCH),
    Cmd.StartMeasurement: ((), ()),
    Cmd.StopMeasurement: ((), ()),
    Cmd.GoBirdBath: ((), ()),
    Cmd.GoPosition: (_XYZ + (("bUseADM", "i"),), ()),
    Cmd.PointLaser: (_XYZ, ()),
    Cmd.GoLastMeasuredPoint: ((), ()),
    Cmd.FindReflector: ((("dAproxDistance", "d"),), ()),
    Cmd.SetLongSystemParameter: ((("systemParam", "I"), ("lParameter", "i")), ()),
    Cmd.GetLongSystemParameter: ((("systemParam", "I"),), (("systemParam", "I"), ("lParameter", "i"))),
    Cmd.GetMeasurementStatusInfo: ((), (("lastResultStatus", "I"), ("lMeasurementStatusInfo", "i"))),
    Cmd.GetSystemSoftwareVersion: ((), (("cSoftwareVersion", "w"),)),
    Cmd.GetMeasurementProbeInfo: ((), (
        ("iFirmwareMajorVersionNumber", "i"), ("iFirmwareMinorVersionNumber", "i"), ("lSerialNumber", "i"),
        ("probeType", "I"), ("lCompensationIdNumber", "i"), ("lActiveField", "i"), ("connectionType", "I"),
        ("lNumberOfTipAdapters", "i"), ("probeButtonType", "I"), ("lNumberOfFields", "i"),
        ("bHasWideAngleReceiver", "i"), ("lNumberOfTipDataSets", "i"), ("lNumberOfMelodies", "i"),
        ("lNumberOfLoudnesSteps", "i"))),
}

#: Values after ``ReturnDataT`` (header + status) of each result packet type.
RESULT_LAYOUTS: dict[DataType, Fields] = {
    DataType.SingleMeasResult: (
        ("measMode", "I"), ("bIsTryMode", "i"), *_XYZ, ("dStd1", "d"), ("dStd2", "d"), ("dStd3", "d"),
        ("dStdTotal", "d"), ("dPointingError1", "d"), ("dPointingError2", "d"), ("dPointingError3", "d"),
        ("dAprioriStd1", "d"), ("dAprioriStd2", "d"), ("dAprioriStd3", "d"), ("dAprioriStdTotal", "d"),
        *_ENV),
    DataType.SingleMeasResult2: (
        ("measMode", "I"), ("bIsTryMode", "i"), *_XYZ, ("dStd1", "d"), ("dStd2", "d"), ("dStd3", "d"),
        ("dStdTotal", "d"), ("dCovar12", "d"), ("dCovar13", "d"), ("dCovar23", "d"),
        ("dPointingErrorH", "d"), ("dPointingErrorV", "d"), ("dPointingErrorD", "d"),
        ("dAprioriStd1", "d"), ("dAprioriStd2", "d"), ("dAprioriStd3", "d"), ("dAprioriStdTotal", "d"),
        ("dAprioriCovar12", "d"), ("dAprioriCovar13", "d"), ("dAprioriCovar23", "d"), *_ENV),
    DataType.StationaryProbeMeasResult: (  # ProbeStationaryResultT, 376 bytes with its ReturnDataT
        ("measMode", "I"), ("bIsTryMode", "i"), ("triggerStatus", "I"), ("lRotationStatus", "i"),
        ("iInternalProbeId", "i"), ("iFieldNumber", "i"), ("tipStatus", "I"), ("iInternalTipAdapterId", "i"),
        ("iTipAdapterInterface", "i"),
        ("dPosition1", "d"), ("dPosition2", "d"), ("dPosition3", "d"),
        ("dStdDevPosition1", "d"), ("dStdDevPosition2", "d"), ("dStdDevPosition3", "d"), ("dStdDevPositionTotal", "d"),
        ("dCovarPosition12", "d"), ("dCovarPosition13", "d"), ("dCovarPosition23", "d"),
        ("dAprioriStdDevPosition1", "d"), ("dAprioriStdDevPosition2", "d"), ("dAprioriStdDevPosition3", "d"),
        ("dAprioriStdDevPositionTotal", "d"),
        ("dAprioriCovarPosition12", "d"), ("dAprioriCovarPosition13", "d"), ("dAprioriCovarPosition23", "d"),
        ("dQuaternion0", "d"), ("dQuaternion1", "d"), ("dQuaternion2", "d"), ("dQuaternion3", "d"),
        ("dRotationAngleX", "d"), ("dRotationAngleY", "d"), ("dRotationAngleZ", "d"),
        ("dStdDevRotationAngleX", "d"), ("dStdDevRotationAngleY", "d"), ("dStdDevRotationAngleZ", "d"),
        ("dStdDevRotationAngleTotal", "d"),
        ("dCovarRotationAngleXY", "d"), ("dCovarRotationAngleXZ", "d"), ("dCovarRotationAngleYZ", "d"),
        ("dAprioriStdDevRotationAngleX", "d"), ("dAprioriStdDevRotationAngleY", "d"),
        ("dAprioriStdDevRotationAngleZ", "d"), ("dAprioriStdDevRotationAngleTotal", "d"),
        ("dAprioriCovarRotationAngleXY", "d"), ("dAprioriCovarRotationAngleXZ", "d"),
        ("dAprioriCovarRotationAngleYZ", "d"), *_ENV),
    DataType.NivelResult: (("nivelStatus", "I"), ("dXTilt", "d"), ("dYTilt", "d"), ("dNivelTemperature", "d")),
    DataType.ReflectorPosResult: _XYZ,
}


def _struct(fields: Fields) -> struct.Struct:
    return struct.Struct("<" + "".join("64s" if code == "w" else code for _, code in fields))


_CT = {c: _struct(ct) for c, (ct, _) in LAYOUTS.items()}
_RT = {c: _struct(rt) for c, (_, rt) in LAYOUTS.items()}
_RESULT = {t: _struct(f) for t, f in RESULT_LAYOUTS.items()}
_WORD = struct.Struct("<I")
_WORD2 = struct.Struct("<II")
_LIMITS = {"i": (-(2 ** 31), 2 ** 31 - 1), "I": (0, 2 ** 32 - 1)}


def request_size(command: Cmd) -> int:
    """Bytes of the request packet (``BasicCommandCT`` + parameters) for ``command``."""
    return 12 + _CT[command].size


def answer_size(command: Cmd) -> int:
    """Bytes of the answer packet (``BasicCommandRT`` + results) for ``command``."""
    return 16 + _RT[command].size


# --------------------------------------------------------------------------- packets


def _check_values(what: str, fields: Fields, values: Mapping[str, Any]) -> dict[str, Any]:
    names = [n for n, _ in fields]
    if set(values) != set(names):
        raise ValueError(f"{what}: needs exactly the fields {names}, got {sorted(values)}")
    out = {}
    for name, code in fields:
        v = values[name]
        if code == "d":
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"{what}: {name} must be a number, got {v!r}")
            v = float(v)
        elif code == "w":
            if not isinstance(v, str) or len(v) > NAME_CHARS or "\0" in v:
                raise ValueError(f"{what}: {name} must be text of at most {NAME_CHARS} characters, got {v!r}")
        else:
            lo, hi = _LIMITS[code]
            if isinstance(v, bool):
                v = int(v)
            if not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{what}: {name} must be an integer in [{lo}, {hi}], got {v!r}")
            v = int(v)
        out[name] = v
    return out


def _pack(fields: Fields, st: struct.Struct, values: Mapping[str, Any]) -> bytes:
    args = []
    for name, code in fields:
        v = values[name]
        args.append(v.encode("utf-16-le").ljust(64, b"\0") if code == "w" else v)
    return st.pack(*args)


def _unpack(fields: Fields, st: struct.Struct, data: bytes) -> dict[str, Any]:
    out = {}
    for (name, code), v in zip(fields, st.unpack(data)):
        if code == "w":
            v = v.decode("utf-16-le", errors="replace").split("\0", 1)[0]
        out[name] = v
    return out


@dataclass(frozen=True)
class Request:
    """A command from the host: ``command`` and its parameters by header field name."""

    command: Cmd
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            cmd = Cmd(self.command)
        except ValueError:
            raise ValueError(f"not an ES_Command: {self.command!r}") from None
        if cmd not in LAYOUTS:
            raise ValueError(f"command {cmd.name} ({int(cmd)}) has no layout in this codec; "
                             f"known: {', '.join(c.name for c in LAYOUTS)}")
        object.__setattr__(self, "command", cmd)
        object.__setattr__(self, "params", _check_values(f"{cmd.name} request", LAYOUTS[cmd][0], self.params))


@dataclass(frozen=True)
class Answer:
    """The server's answer to a command (``ES_DT_Command``); ``values`` are all zero/empty when
    ``status`` is not ``AllOK``. ``values`` is empty for a command without a layout here."""

    command: int
    status: int
    values: Mapping[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == Status.AllOK


@dataclass(frozen=True)
class ErrorAnswer:
    """``ES_DT_Error``: the server could not execute ``command``; ``status`` says why."""

    command: int
    status: int


@dataclass(frozen=True)
class DataResult:
    """A result packet (single measurement, nivel, reflector position) with its status."""

    type: DataType
    status: int
    values: Mapping[str, Any]


@dataclass(frozen=True)
class StatusChange:
    """``ES_DT_SystemStatusChange``: an unsolicited notification."""

    change: int


ServerPacket = Union[Answer, ErrorAnswer, DataResult, StatusChange]


def _status_word(status: int) -> int:
    if isinstance(status, bool) or not isinstance(status, int) or not 0 <= status <= 2 ** 32 - 1:
        raise ValueError(f"status must be an ES_ResultStatus (uint32), got {status!r}")
    return int(status)


def _frame(type_: DataType, body: bytes) -> bytes:
    size = 8 + len(body)
    return HEADER.pack(size, int(type_)) + body


def encode(packet: Request | ServerPacket) -> bytes:
    """The bytes of one packet (little-endian, header first)."""
    if isinstance(packet, Request):
        return _frame(DataType.Command, _WORD.pack(packet.command)
                      + _pack(LAYOUTS[packet.command][0], _CT[packet.command], packet.params))
    if isinstance(packet, Answer):
        cmd = packet.command
        head = _WORD2.pack(_status_word(cmd), _status_word(packet.status))
        if cmd in LAYOUTS:
            fields = LAYOUTS[Cmd(cmd)][1]
            values = packet.values
            if not values:
                values = {n: ("" if c == "w" else 0) for n, c in fields}
            values = _check_values(f"{Cmd(cmd).name} answer", fields, values)
            return _frame(DataType.Command, head + _pack(fields, _RT[Cmd(cmd)], values))
        if packet.values:
            raise ValueError(f"command {cmd} has no answer layout in this codec; it cannot carry values")
        return _frame(DataType.Command, head)
    if isinstance(packet, ErrorAnswer):
        return _frame(DataType.Error, _WORD2.pack(_status_word(packet.command), _status_word(packet.status)))
    if isinstance(packet, DataResult):
        t = DataType(packet.type)
        if t not in RESULT_LAYOUTS:
            raise ValueError(f"no layout for result type {t.name}; known: {', '.join(x.name for x in RESULT_LAYOUTS)}")
        values = _check_values(f"{t.name}", RESULT_LAYOUTS[t], packet.values)
        return _frame(t, _WORD.pack(_status_word(packet.status)) + _pack(RESULT_LAYOUTS[t], _RESULT[t], values))
    if isinstance(packet, StatusChange):
        return _frame(DataType.SystemStatusChange, _WORD.pack(_status_word(packet.change)))
    raise TypeError(f"not an emScon packet: {packet!r}")


# --------------------------------------------------------------------------- decoding


class RequestRefused(ProtocolError):
    """A request the server must refuse: answer ``command`` (``Cmd.Unknown`` when unreadable)
    with ``status``; ``as_error`` says whether to answer with ``ES_DT_Error`` (unreadable packet)
    or with the command's own answer (``ES_DT_Command``, readable command, bad parameters)."""

    def __init__(self, command: int, status: Status, message: str, *, as_error: bool) -> None:
        super().__init__(message)
        self.command = command
        self.status = Status(status)
        self.as_error = as_error


def split_frames(buffer: bytearray) -> list[bytes]:
    """Remove and return every complete packet at the start of ``buffer``.

    Raises ProtocolError (and clears the buffer: the stream has lost its framing and only a new
    connection can recover it) when a header announces a size outside
    [MIN_PACKET, MAX_PACKET] bytes.
    """
    out = []
    while len(buffer) >= 8:
        size, type_ = HEADER.unpack_from(buffer)
        if not MIN_PACKET <= size <= MAX_PACKET:
            buffer.clear()
            raise ProtocolError(f"packet header announces {size} bytes (type {type_}); allowed "
                                f"{MIN_PACKET}..{MAX_PACKET}: the stream is out of step, reconnect")
        if len(buffer) < size:
            break
        out.append(bytes(buffer[:size]))
        del buffer[:size]
    return out


def _header(frame: bytes, side: str) -> tuple[int, int]:
    if not isinstance(frame, (bytes, bytearray)):
        raise ProtocolError(f"{side}: expected bytes, got {type(frame).__name__}")
    if len(frame) < MIN_PACKET:
        raise ProtocolError(f"{side}: {len(frame)} bytes, a packet has at least {MIN_PACKET}")
    size, type_ = HEADER.unpack_from(frame)
    if size != len(frame):
        raise ProtocolError(f"{side}: header says {size} bytes, the packet has {len(frame)}")
    return size, type_


def decode_request(frame: bytes) -> Request:
    """The command of one host packet. Raises RequestRefused (a ProtocolError) with the status
    to answer: ``NotImplemented`` for an unknown or unsupported command, ``WrongParameter`` for a
    packet of the wrong size, ``WrongParameterN`` for a bad N-th parameter."""
    try:
        size, type_ = _header(frame, "request")
    except ProtocolError as exc:
        raise RequestRefused(Cmd.Unknown, Status.InvalidInputData, str(exc), as_error=True) from None
    if type_ != DataType.Command:
        raise RequestRefused(Cmd.Unknown, Status.InvalidInputData,
                             f"request: data type {type_} is not ES_DT_Command (0)", as_error=True)
    (cmd_word,) = _WORD.unpack_from(frame, 8)
    try:
        cmd = Cmd(cmd_word)
    except ValueError:
        raise RequestRefused(cmd_word, Status.NotImplemented, f"request: unknown ES_Command {cmd_word}",
                             as_error=True) from None
    if cmd not in LAYOUTS:
        raise RequestRefused(cmd, Status.NotImplemented,
                             f"request: command {cmd.name} ({int(cmd)}) is not implemented by this server",
                             as_error=False)
    fields = LAYOUTS[cmd][0]
    want = request_size(cmd)
    if size != want:
        raise RequestRefused(cmd, Status.WrongParameter,
                             f"request {cmd.name}: {size} bytes, its layout has {want}", as_error=False)
    params = _unpack(fields, _CT[cmd], frame[12:])
    for i, (name, code) in enumerate(fields):
        if code == "d" and not math.isfinite(params[name]):
            status = wrong_parameter(i + 1)
            raise RequestRefused(cmd, status, f"request {cmd.name}: {name} is not finite ({params[name]!r})",
                                 as_error=False)
    return Request(cmd, params)


def wrong_parameter(n: int) -> Status:
    """``ES_RS_WrongParameterN`` for the N-th parameter (1..16)."""
    if 1 <= n <= 7:
        return Status(Status.WrongParameter1 + n - 1)
    if 8 <= n <= 16:
        return Status(Status.WrongParameter8 + n - 8)
    return Status.WrongParameter


def decode(frame: bytes) -> ServerPacket:
    """One packet from the server as ``Answer`` / ``ErrorAnswer`` / ``DataResult`` /
    ``StatusChange``. Raises ProtocolError for anything else."""
    size, type_ = _header(frame, "answer")
    try:
        t = DataType(type_)
    except ValueError:
        raise ProtocolError(f"answer: unknown ES_DataType {type_}") from None
    if t is DataType.SystemStatusChange:
        if size != 12:
            raise ProtocolError(f"SystemStatusChange: {size} bytes, its layout has 12")
        return StatusChange(_WORD.unpack_from(frame, 8)[0])
    if size < 16:
        raise ProtocolError(f"{t.name}: {size} bytes, at least 16 needed")
    if t is DataType.Error:
        if size != 16:
            raise ProtocolError(f"ErrorResponse: {size} bytes, its layout has 16")
        cmd, status = _WORD2.unpack_from(frame, 8)
        return ErrorAnswer(cmd, status)
    if t is DataType.Command:
        cmd, status = _WORD2.unpack_from(frame, 8)
        try:
            cmd = Cmd(cmd)
        except ValueError:
            raise ProtocolError(f"answer: unknown ES_Command {cmd}") from None
        if cmd not in LAYOUTS:
            return Answer(cmd, status, {})
        want = answer_size(cmd)
        if size == want:
            return Answer(cmd, status, _unpack(LAYOUTS[cmd][1], _RT[cmd], frame[16:]))
        if size == 16 and status != Status.AllOK:  # a refusal without the result fields
            return Answer(cmd, status, {})
        raise ProtocolError(f"answer {cmd.name}: {size} bytes, its layout has {want}")
    if t in RESULT_LAYOUTS:
        want = 12 + _RESULT[t].size
        if size != want:
            raise ProtocolError(f"{t.name}: {size} bytes, its layout has {want}")
        (status,) = _WORD.unpack_from(frame, 8)
        return DataResult(t, status, _unpack(RESULT_LAYOUTS[t], _RESULT[t], frame[12:]))
    raise ProtocolError(f"answer: {t.name} packets (continuous modes) are not supported by this "
                        "driver; use stationary (3D or 6D) measurements")
