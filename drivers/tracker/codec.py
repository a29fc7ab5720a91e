"""The tracker line protocol (``PROTOCOL.md`` next to this file) as pure data and functions.

Commands (host → device) and replies / events (device → host) are frozen dataclasses; the
``LineCodec`` turns them into ASCII lines and back. Nothing here touches a transport, so a vendor
protocol can be added as another codec with the same four methods (``encode_request``,
``decode_request``, ``encode_reply``, ``decode_reply``) plus a framer (``split_frames``).

Every malformed input raises only ``drivers.errors.ProtocolError`` (on the device side a
``RequestError`` subclass that carries the numeric error code to answer with).

Units on the wire: millimetres and seconds.
"""

from __future__ import annotations

import math
import re
from dataclasses import MISSING, dataclass, field, fields
from enum import Enum
from typing import Any, ClassVar, Protocol, Union, runtime_checkable

import numpy as np

from drivers.errors import ProtocolError

#: Longest line (without its newline) either side accepts.
MAX_LINE = 1024
#: Highest request id; ids 1..MAX_RID are the host's, 0 means "the device could not read it".
MAX_RID = 999_999_999
#: Longest averaged measurement a device must accept.
MAX_AVERAGE = 100_000
PROTOCOL_VERSION = 1


class Mode(str, Enum):
    """Distance measurement: absolute distance meter or (relative) interferometer."""

    ADM = "ADM"
    IFM = "IFM"


class ErrorCode(int, Enum):
    """Numeric codes of ``ERR`` replies (see PROTOCOL.md)."""

    SYNTAX = 1
    UNKNOWN_COMMAND = 2
    BAD_ARGUMENT = 3
    BEAM_LOST = 10
    DISTANCE_INVALID = 11
    NOT_6DOF = 12
    WARMING_UP = 20
    NO_WEATHER_STATION = 30
    INTERNAL = 50


class RequestError(ProtocolError):
    """A request line the device must refuse, with the code and request id to answer with."""

    def __init__(self, code: ErrorCode, rid: int, message: str) -> None:
        super().__init__(message)
        self.code = ErrorCode(code)
        self.rid = rid


# --------------------------------------------------------------------------- field kinds
# Each dataclass field names its wire key and kind in its metadata; the codec is table-driven.

_NUM_RE = re.compile(r"[+-]?[0-9]{1,12}(\.[0-9]{1,9})?")
_INT_RE = re.compile(r"[0-9]{1,9}")
_TOKEN_RE = re.compile(r"[A-Za-z0-9._:+-]{1,32}")
_KEY_RE = re.compile(r"[a-z][a-z_]{0,15}")
_UNPRINTABLE_RE = re.compile(r"[^\x20-\x29\x2b-\x7e]")  # not printable ASCII, or '*'


def _parse_float(text: str) -> float:
    if not _NUM_RE.fullmatch(text):
        raise ValueError(f"not a decimal number (digits with an optional '.' fraction): {text!r}")
    return float(text)


def _parse_int(text: str) -> int:
    if not _INT_RE.fullmatch(text):
        raise ValueError(f"not an unsigned integer of at most 9 digits: {text!r}")
    return int(text)


def _parse_bool(text: str) -> bool:
    if text not in ("0", "1"):
        raise ValueError(f"not a flag (0 or 1): {text!r}")
    return text == "1"


def _parse_mode(text: str) -> Mode:
    try:
        return Mode(text)
    except ValueError:
        raise ValueError(f"not a mode (ADM or IFM): {text!r}") from None


def _parse_beam(text: str) -> bool:
    if text not in ("LOCKED", "LOST"):
        raise ValueError(f"not a beam state (LOCKED or LOST): {text!r}")
    return text == "LOCKED"


def _parse_token(text: str) -> str:
    if not _TOKEN_RE.fullmatch(text):
        raise ValueError(f"not a token (1-32 of A-Z a-z 0-9 . _ : + -): {text!r}")
    return text


def _fmt_fixed(decimals: int):
    def fmt(value: Any) -> str:
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"cannot put a non-finite number on the wire: {value!r}")
        text = f"{v:.{decimals}f}"
        return "0." + "0" * decimals if text == "-0." + "0" * decimals else text

    return fmt


def _fmt_int(value: Any) -> str:
    v = int(value)
    if not 0 <= v <= MAX_RID:
        raise ValueError(f"integer {value!r} outside 0..{MAX_RID}")
    return str(v)


def _fmt_token(value: Any) -> str:
    return _parse_token(str(value))


_KINDS: dict[str, tuple[Any, Any]] = {
    "mm": (_fmt_fixed(4), _parse_float),  # 0.1 µm resolution
    "s": (_fmt_fixed(6), _parse_float),  # 1 µs resolution
    "ms3": (_fmt_fixed(3), _parse_float),  # three decimals (timeouts, warm-up left, turns)
    "env": (_fmt_fixed(3), _parse_float),  # three decimals (°C, hPa, %)
    "unit": (_fmt_fixed(9), _parse_float),  # quaternion components, 1e-9
    "deg": (_fmt_fixed(6), _parse_float),  # angles in degrees, 1e-6°
    "int": (_fmt_int, _parse_int),
    "bool": (lambda v: "1" if v else "0", _parse_bool),
    "mode": (lambda v: Mode(v).value, _parse_mode),
    "beam": (lambda v: "LOCKED" if v else "LOST", _parse_beam),
    "token": (_fmt_token, _parse_token),
}


def _f(key: str, kind: str, **kw):
    return field(metadata={"key": key, "kind": kind}, **kw)


def _finite(name: str, value: float, lo: float = -math.inf, hi: float = math.inf) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} must be a finite number in [{lo}, {hi}], got {value!r}")


# --------------------------------------------------------------------------- commands


@dataclass(frozen=True)
class Identify:
    """``ID``: who is the device."""

    verb: ClassVar[str] = "ID"


@dataclass(frozen=True)
class GetStatus:
    """``STATUS``: beam lock, mode, warm-up, distance validity."""

    verb: ClassVar[str] = "STATUS"


@dataclass(frozen=True)
class SetMode:
    """``MODE``: choose ADM or IFM distance measurement."""

    verb: ClassVar[str] = "MODE"
    mode: Mode = _f("mode", "mode")

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "mode", Mode(self.mode))
        except ValueError:
            raise ValueError(f"mode must be ADM or IFM, got {self.mode!r}") from None


@dataclass(frozen=True)
class MeasurePoint:
    """``MEAS``: one point of the locked reflector."""

    verb: ClassVar[str] = "MEAS"


@dataclass(frozen=True)
class MeasureAverage:
    """``AVG``: the mean of ``n`` consecutive points (1..MAX_AVERAGE)."""

    verb: ClassVar[str] = "AVG"
    n: int = _f("n", "int")

    def __post_init__(self) -> None:
        if not (isinstance(self.n, int) and not isinstance(self.n, bool) and 1 <= self.n <= MAX_AVERAGE):
            raise ValueError(f"n must be an integer in 1..{MAX_AVERAGE}, got {self.n!r}")


@dataclass(frozen=True)
class MeasurePose:
    """``POSE``: a 6-DoF target's mean position and orientation over ``n`` consecutive
    measurements (1..MAX_AVERAGE)."""

    verb: ClassVar[str] = "POSE"
    n: int = _f("n", "int")

    def __post_init__(self) -> None:
        if not (isinstance(self.n, int) and not isinstance(self.n, bool) and 1 <= self.n <= MAX_AVERAGE):
            raise ValueError(f"n must be an integer in 1..{MAX_AVERAGE}, got {self.n!r}")


@dataclass(frozen=True)
class Aim:
    """``AIM``: point the beam at (x, y, z), tracker frame, mm; locks if a reflector is caught."""

    verb: ClassVar[str] = "AIM"
    x: float = _f("x", "mm")
    y: float = _f("y", "mm")
    z: float = _f("z", "mm")

    def __post_init__(self) -> None:
        for name in ("x", "y", "z"):
            _finite(name, getattr(self, name), -1e6, 1e6)
        if math.hypot(self.x, self.y, self.z) < 1.0:
            raise ValueError(f"aim point ({self.x}, {self.y}, {self.z}) mm is within 1 mm of the tracker head")


@dataclass(frozen=True)
class Search:
    """``SEARCH``: spiral out to ``radius_mm`` around the current beam direction.

    Stops when a reflector locks, after ``timeout_s`` (device seconds) or after ``max_turns``
    turns (0 = no turn limit).
    """

    verb: ClassVar[str] = "SEARCH"
    radius_mm: float = _f("r", "mm")
    timeout_s: float = _f("timeout", "ms3")
    max_turns: int = _f("turns", "int", default=0)

    def __post_init__(self) -> None:
        _finite("radius_mm", self.radius_mm, 0.001, 10_000.0)
        _finite("timeout_s", self.timeout_s, 0.001, 3600.0)
        if not (isinstance(self.max_turns, int) and 0 <= self.max_turns <= 100_000):
            raise ValueError(f"max_turns must be an integer in 0..100000 (0 = no limit), got {self.max_turns!r}")


@dataclass(frozen=True)
class Home:
    """``HOME``: re-establish the interferometer distance (no-op in ADM)."""

    verb: ClassVar[str] = "HOME"


#: Allowed air for the refraction correction: °C, hPa, % relative humidity.
TEMPERATURE_RANGE_C = (-40.0, 60.0)
PRESSURE_RANGE_HPA = (500.0, 1200.0)
HUMIDITY_RANGE_PCT = (0.0, 100.0)
ENV_SOURCES = ("HOST", "STATION")


@dataclass(frozen=True)
class Environment:
    """``ENV``: the air the tracker corrects its distances for (refraction), or a query.

    ``source="HOST"`` with ``temperature_c`` (°C), ``pressure_hpa`` (hPa) and ``humidity_pct``
    (% RH): use these values. ``source="STATION"`` (no values): use the tracker's own weather
    station. ``source=None`` (no values): only ask which air is in use.
    """

    verb: ClassVar[str] = "ENV"
    source: str | None = _f("source", "token", default=None)
    temperature_c: float | None = _f("temp", "env", default=None)
    pressure_hpa: float | None = _f("press", "env", default=None)
    humidity_pct: float | None = _f("hum", "env", default=None)

    def __post_init__(self) -> None:
        values = (self.temperature_c, self.pressure_hpa, self.humidity_pct)
        if self.source is None or self.source == "STATION":
            if any(v is not None for v in values):
                raise ValueError(f"ENV source={self.source or '(query)'} takes no temp/press/hum; "
                                 "give source=HOST with all three to set the air by hand")
            return
        if self.source != "HOST":
            raise ValueError(f"ENV source must be one of {', '.join(ENV_SOURCES)}, got {self.source!r}")
        for name, v, (lo, hi) in (("temp", self.temperature_c, TEMPERATURE_RANGE_C),
                                  ("press", self.pressure_hpa, PRESSURE_RANGE_HPA),
                                  ("hum", self.humidity_pct, HUMIDITY_RANGE_PCT)):
            if v is None:
                raise ValueError(f"ENV source=HOST needs temp=, press= and hum=; {name}= is missing")
            _finite(name, v, lo, hi)


@dataclass(frozen=True)
class SelectReflector:
    """``REFL``: select the reflector by type name, optionally with its surface offset (mm);
    without ``reflector_type`` only ask which one is selected."""

    verb: ClassVar[str] = "REFL"
    reflector_type: str | None = _f("type", "token", default=None)
    offset_mm: float | None = _f("offset", "mm", default=None)

    def __post_init__(self) -> None:
        if self.reflector_type is None:
            if self.offset_mm is not None:
                raise ValueError("REFL offset= needs type=")
            return
        _parse_token(str(self.reflector_type))
        if self.offset_mm is not None:
            _finite("offset", self.offset_mm, 0.0, 1000.0)


Command = Union[Identify, GetStatus, SetMode, MeasurePoint, MeasureAverage, MeasurePose, Aim, Search, Home,
                Environment, SelectReflector]
COMMANDS: dict[str, type] = {c.verb: c for c in (Identify, GetStatus, SetMode, MeasurePoint, MeasureAverage, MeasurePose,
                                                 Aim, Search, Home, Environment, SelectReflector)}

# --------------------------------------------------------------------------- replies


@dataclass(frozen=True)
class IdentifyReply:
    verb: ClassVar[str] = "ID"
    vendor: str = _f("vendor", "token")
    model: str = _f("model", "token")
    serial: str = _f("serial", "token")
    firmware: str = _f("firmware", "token")
    protocol: int = _f("protocol", "int")


@dataclass(frozen=True)
class StatusReply:
    """Tracker state. ``warmup_left_s`` in device seconds; ``device_time`` in seconds."""

    verb: ClassVar[str] = "STATUS"
    locked: bool = _f("beam", "beam")
    mode: Mode = _f("mode", "mode")
    warmed_up: bool = _f("warm", "bool")
    warmup_left_s: float = _f("warmup_left", "ms3")
    temperature_stable: bool = _f("temp_stable", "bool")
    distance_valid: bool = _f("dist_valid", "bool")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class ModeReply:
    verb: ClassVar[str] = "MODE"
    mode: Mode = _f("mode", "mode")
    distance_valid: bool = _f("dist_valid", "bool")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class PointReply:
    """One point, tracker frame, mm; ``std_mm`` is the device's per-axis 1σ estimate."""

    verb: ClassVar[str] = "MEAS"
    x: float = _f("x", "mm")
    y: float = _f("y", "mm")
    z: float = _f("z", "mm")
    std_mm: float = _f("std", "mm")
    device_time: float = _f("t", "s")

    @property
    def xyz_mm(self) -> np.ndarray:
        """shape (3,), mm."""
        return np.array([self.x, self.y, self.z])


class _MeanPosition:
    """The position part of a mean reply (fields ``x y z`` and ``sx sy sz``, mm)."""

    x: float
    y: float
    z: float
    sx: float
    sy: float
    sz: float

    @property
    def xyz_mm(self) -> np.ndarray:
        """shape (3,), mm."""
        return np.array([self.x, self.y, self.z])

    @property
    def std_xyz_mm(self) -> np.ndarray:
        """shape (3,), mm."""
        return np.array([self.sx, self.sy, self.sz])


@dataclass(frozen=True)
class AverageReply(_MeanPosition):
    """Mean of ``n`` points, tracker frame, mm, with per-axis sample standard deviations."""

    verb: ClassVar[str] = "AVG"
    x: float = _f("x", "mm")
    y: float = _f("y", "mm")
    z: float = _f("z", "mm")
    sx: float = _f("sx", "mm")
    sy: float = _f("sy", "mm")
    sz: float = _f("sz", "mm")
    n: int = _f("n", "int")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class PoseReply(_MeanPosition):
    """A 6-DoF target's mean pose over ``n`` measurements, tracker frame: position (mm) with
    per-axis sample standard deviations, orientation ``R_tracker←target`` as a unit quaternion
    (scalar first, Hamilton), and the spread of the orientation as the sample standard deviation
    of each measurement's rotation vector against the mean, per tracker axis, degrees."""

    verb: ClassVar[str] = "POSE"
    x: float = _f("x", "mm")
    y: float = _f("y", "mm")
    z: float = _f("z", "mm")
    sx: float = _f("sx", "mm")
    sy: float = _f("sy", "mm")
    sz: float = _f("sz", "mm")
    qw: float = _f("qw", "unit")
    qx: float = _f("qx", "unit")
    qy: float = _f("qy", "unit")
    qz: float = _f("qz", "unit")
    srx: float = _f("srx", "deg")
    sry: float = _f("sry", "deg")
    srz: float = _f("srz", "deg")
    n: int = _f("n", "int")
    device_time: float = _f("t", "s")

    @property
    def quat_wxyz(self) -> np.ndarray:
        """shape (4,), scalar first."""
        return np.array([self.qw, self.qx, self.qy, self.qz])

    @property
    def std_rot_deg(self) -> np.ndarray:
        """shape (3,), degrees."""
        return np.array([self.srx, self.sry, self.srz])


@dataclass(frozen=True)
class AimReply:
    verb: ClassVar[str] = "AIM"
    locked: bool = _f("beam", "beam")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class SearchReply:
    """``elapsed_s``: device seconds the search took; ``turns``: spiral turns done."""

    verb: ClassVar[str] = "SEARCH"
    found: bool = _f("found", "bool")
    elapsed_s: float = _f("elapsed", "ms3")
    turns: float = _f("turns", "ms3")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class HomeReply:
    verb: ClassVar[str] = "HOME"
    distance_valid: bool = _f("dist_valid", "bool")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class EnvironmentReply:
    """The air in use for the refraction correction and where it comes from (HOST / STATION)."""

    verb: ClassVar[str] = "ENV"
    source: str = _f("source", "token")
    temperature_c: float = _f("temp", "env")
    pressure_hpa: float = _f("press", "env")
    humidity_pct: float = _f("hum", "env")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class ReflectorReply:
    """The selected reflector: its type name and surface offset (mm)."""

    verb: ClassVar[str] = "REFL"
    reflector_type: str = _f("type", "token")
    offset_mm: float = _f("offset", "mm")
    device_time: float = _f("t", "s")


@dataclass(frozen=True)
class ErrorReply:
    """``ERR``: the device refused a request. ``text`` is printable ASCII without ``*``."""

    code: int
    text: str

    def __post_init__(self) -> None:
        if not (isinstance(self.code, int) and 1 <= self.code <= 999):
            raise ValueError(f"error code must be in 1..999, got {self.code!r}")


@dataclass(frozen=True)
class Event:
    """An unsolicited line (``! NAME t=...``): ``BEAM_LOST`` or ``BEAM_LOCKED``."""

    name: str
    device_time: float = _f("t", "s")

    def __post_init__(self) -> None:
        if self.name not in EVENT_NAMES:
            raise ValueError(f"unknown event {self.name!r}; known: {', '.join(EVENT_NAMES)}")


EVENT_NAMES = ("BEAM_LOST", "BEAM_LOCKED")

Reply = Union[IdentifyReply, StatusReply, ModeReply, PointReply, AverageReply, PoseReply, AimReply, SearchReply,
              HomeReply, EnvironmentReply, ReflectorReply]
REPLIES: dict[str, type] = {
    r.verb: r
    for r in (IdentifyReply, StatusReply, ModeReply, PointReply, AverageReply, PoseReply, AimReply, SearchReply,
              HomeReply, EnvironmentReply, ReflectorReply)
}
#: The reply type each command expects.
REPLY_FOR: dict[type, type] = {COMMANDS[v]: REPLIES[v] for v in COMMANDS}


# --------------------------------------------------------------------------- helpers


def checksum(body: bytes) -> str:
    """Two upper-case hex digits: the XOR of every byte of ``body`` (NMEA style)."""
    c = 0
    for b in body:
        c ^= b
    return f"{c:02X}"


def _encode_fields(obj: Any) -> list[str]:
    out = []
    for f in fields(obj):
        if "key" not in f.metadata or (getattr(obj, f.name) is None and f.default is None):
            continue  # an optional field left out
        fmt, _ = _KINDS[f.metadata["kind"]]
        out.append(f"{f.metadata['key']}={fmt(getattr(obj, f.name))}")
    return out


def _decode_fields(cls: type, tokens: list[str], what: str, extra: dict[str, Any] | None = None) -> Any:
    """Build ``cls`` from ``key=value`` tokens; unknown keys are ignored (forward compatible)."""
    seen: dict[str, str] = {}
    for tok in tokens:
        key, sep, value = tok.partition("=")
        if not sep or not _KEY_RE.fullmatch(key) or not value:
            raise ProtocolError(f"{what}: expected key=value, got {tok!r}")
        if key in seen:
            raise ProtocolError(f"{what}: key {key!r} given twice")
        seen[key] = value
    kwargs: dict[str, Any] = dict(extra or {})
    for f in fields(cls):
        if "key" not in f.metadata:
            continue
        key = f.metadata["key"]
        if key not in seen:
            if f.default is not MISSING:
                continue
            raise ProtocolError(f"{what}: missing {key}=; required: {', '.join(_keys(cls))}")
        _, parse = _KINDS[f.metadata["kind"]]
        try:
            kwargs[f.name] = parse(seen[key])
        except ValueError as exc:
            raise ProtocolError(f"{what}: {key}= {exc}") from None
    return cls(**kwargs)


def _keys(cls: type) -> list[str]:
    return [f.metadata["key"] for f in fields(cls) if "key" in f.metadata]


def _text_of(line: bytes | str, side: str) -> str:
    """Validate framing of one line (newline optional, a single trailing CR tolerated)."""
    if isinstance(line, str):
        try:
            line = line.encode("ascii")
        except UnicodeEncodeError:
            raise ProtocolError(f"{side}: line is not ASCII: {line[:80]!r}") from None
    if not isinstance(line, (bytes, bytearray)):
        raise ProtocolError(f"{side}: expected bytes, got {type(line).__name__}")
    raw = bytes(line)
    if raw.endswith(b"\n"):
        raw = raw[:-1]
    if raw.endswith(b"\r"):
        raw = raw[:-1]
    if len(raw) > MAX_LINE:
        raise ProtocolError(f"{side}: line of {len(raw)} bytes, at most {MAX_LINE} allowed")
    if not raw:
        raise ProtocolError(f"{side}: empty line")
    bad = next((b for b in raw if not 0x20 <= b <= 0x7E), None)
    if bad is not None:
        raise ProtocolError(f"{side}: byte 0x{bad:02X} is not printable ASCII in {raw[:80]!r}")
    return raw.decode("ascii")


def _split_checksum(text: str, side: str, required: bool) -> str:
    star = text.rfind("*")
    if star < 0:
        if required:
            raise ProtocolError(f"{side}: no *HH checksum at the end of {text[:80]!r}")
        return text
    body, given = text[:star], text[star + 1 :]
    if "*" in body:
        raise ProtocolError(f"{side}: more than one '*' in {text[:80]!r}")
    want = checksum(body.encode("ascii"))
    if given.upper() != want or len(given) != 2:
        raise ProtocolError(f"{side}: checksum {given!r} does not match {want} for {body[:80]!r}")
    return body


def _rid(text: str, side: str, allow_zero: bool) -> int:
    if not _INT_RE.fullmatch(text):
        raise ProtocolError(f"{side}: request id must be 1-9 digits, got {text[:20]!r}")
    rid = int(text)
    if rid == 0 and not allow_zero:
        raise ProtocolError(f"{side}: request id 0 is reserved for the device")
    return rid


# --------------------------------------------------------------------------- the codec


@runtime_checkable
class TrackerCodec(Protocol):
    """What the client and the fake need from a codec: framing plus the four conversions.

    A vendor protocol (binary or text) is added by implementing this, not by changing the
    transport code.
    """

    def split_frames(self, buffer: bytearray) -> list[bytes]:
        """Remove and return the complete frames at the start of ``buffer``."""
        ...

    def encode_request(self, rid: int, command: Command) -> bytes: ...

    def decode_request(self, frame: bytes) -> tuple[int, Command]: ...

    def encode_reply(self, rid: int, reply: Reply | ErrorReply | Event) -> bytes: ...

    def decode_reply(self, frame: bytes) -> tuple[int | None, Reply | ErrorReply | Event]: ...



@dataclass(frozen=True)
class LineCodec:
    """The documented ASCII line protocol, version 1.

    ``require_checksum``: refuse lines without a ``*HH`` suffix when decoding. The device side
    leaves it False so a person can type commands in a terminal; the host side sets it True
    (every device line carries one) so a garbled reply is always detected.
    """

    require_checksum: bool = False
    name: ClassVar[str] = "line"

    # framing ---------------------------------------------------------------
    @staticmethod
    def split_frames(buffer: bytearray) -> list[bytes]:
        """Remove and return every complete line (with its ``\\n``) from ``buffer``.

        Raises ProtocolError (after clearing the buffer) if more than MAX_LINE bytes arrive
        without a newline.
        """
        out = []
        while True:
            i = buffer.find(b"\n")
            if i < 0:
                break
            out.append(bytes(buffer[: i + 1]))
            del buffer[: i + 1]
        if len(buffer) > MAX_LINE + 2:
            n = len(buffer)
            buffer.clear()
            raise ProtocolError(f"{n} bytes without a newline (at most {MAX_LINE} per line)")
        return out

    @staticmethod
    def _finish(body: str) -> bytes:
        return f"{body}*{checksum(body.encode('ascii'))}\n".encode("ascii")

    # host → device ---------------------------------------------------------
    def encode_request(self, rid: int, command: Command) -> bytes:
        """``<rid> <VERB> key=value ...*HH\\n``."""
        if not (isinstance(rid, int) and 1 <= rid <= MAX_RID):
            raise ValueError(f"request id must be in 1..{MAX_RID}, got {rid!r}")
        if type(command) not in REPLY_FOR:
            raise TypeError(f"not a tracker command: {command!r}")
        return self._finish(" ".join([str(rid), command.verb, *_encode_fields(command)]))

    def decode_request(self, line: bytes | str) -> tuple[int, Command]:
        """The request id and command of one request line.

        Raises RequestError (a ProtocolError) with the code to answer: SYNTAX, UNKNOWN_COMMAND
        or BAD_ARGUMENT, and the request id (0 when it could not be read).
        """
        rid = 0
        try:
            text = _split_checksum(_text_of(line, "request"), "request", self.require_checksum)
            tokens = text.split()
            if len(tokens) < 2:
                raise ProtocolError(f"request: expected '<id> <COMMAND> [key=value ...]', got {text[:80]!r}")
            rid = _rid(tokens[0], "request", allow_zero=False)
        except RequestError:
            raise
        except ProtocolError as exc:
            raise RequestError(ErrorCode.SYNTAX, rid, str(exc)) from None
        verb = tokens[1]
        cls = COMMANDS.get(verb)
        if cls is None:
            raise RequestError(
                ErrorCode.UNKNOWN_COMMAND, rid,
                f"unknown command {verb[:20]!r}; known: {' '.join(COMMANDS)}",
            )
        try:
            return rid, _decode_fields(cls, tokens[2:], f"request {verb}")
        except ProtocolError as exc:
            raise RequestError(ErrorCode.SYNTAX, rid, str(exc)) from None
        except ValueError as exc:
            raise RequestError(ErrorCode.BAD_ARGUMENT, rid, f"request {verb}: {exc}") from None

    # device → host ---------------------------------------------------------
    def encode_reply(self, rid: int, reply: Reply | ErrorReply | Event) -> bytes:
        """``<rid> OK <VERB> ...``, ``<rid> ERR <code> <text>`` or ``! <EVENT> t=...``."""
        if isinstance(reply, Event):
            return self._finish(" ".join(["!", reply.name, *_encode_fields(reply)]))
        if not (isinstance(rid, int) and 0 <= rid <= MAX_RID):
            raise ValueError(f"request id must be in 0..{MAX_RID}, got {rid!r}")
        if isinstance(reply, ErrorReply):
            text = _UNPRINTABLE_RE.sub("?", reply.text)
            text = text[: MAX_LINE - 32]
            return self._finish(f"{rid} ERR {reply.code} {text}".rstrip())
        if type(reply) not in REPLIES.values():
            raise TypeError(f"not a tracker reply: {reply!r}")
        return self._finish(" ".join([str(rid), "OK", reply.verb, *_encode_fields(reply)]))

    def decode_reply(self, line: bytes | str) -> tuple[int | None, Reply | ErrorReply | Event]:
        """The request id (None for an event) and typed reply of one device line."""
        text = _split_checksum(_text_of(line, "reply"), "reply", self.require_checksum)
        tokens = text.split(" ")
        if tokens[0] == "!":
            if len(tokens) < 2 or tokens[1] not in EVENT_NAMES:
                raise ProtocolError(f"event: unknown or missing name in {text[:80]!r}; known: {', '.join(EVENT_NAMES)}")
            return None, _decode_fields(Event, tokens[2:], "event", {"name": tokens[1]})
        if len(tokens) < 3:
            raise ProtocolError(f"reply: expected '<id> OK <VERB> ...' or '<id> ERR <code> <text>', got {text[:80]!r}")
        rid = _rid(tokens[0], "reply", allow_zero=True)
        if tokens[1] == "ERR":
            code = tokens[2]
            if not re.fullmatch(r"[1-9][0-9]{0,2}", code):
                raise ProtocolError(f"reply ERR: code must be 1..999, got {code[:20]!r}")
            return rid, ErrorReply(int(code), " ".join(tokens[3:]))
        if tokens[1] != "OK":
            raise ProtocolError(f"reply: second word must be OK or ERR, got {tokens[1][:20]!r}")
        cls = REPLIES.get(tokens[2])
        if cls is None:
            raise ProtocolError(f"reply: unknown verb {tokens[2][:20]!r}; known: {' '.join(REPLIES)}")
        try:
            return rid, _decode_fields(cls, tokens[3:], f"reply {cls.verb}")
        except ValueError as exc:
            if isinstance(exc, ProtocolError):
                raise
            raise ProtocolError(f"reply {cls.verb}: {exc}") from None
