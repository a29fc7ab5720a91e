"""NatNet wire codec: decode and encode every NatNet message, NatNet 3.0 – 4.1 layouts (newer refused).

A packet is ``uint16 message_id, uint16 payload_bytes`` then the payload, little-endian.
``decode_packet(data, version)`` turns one UDP datagram into a message dataclass and
``encode_packet(message, version)`` does the reverse. ``version`` is the NatNet *stream*
version the bytes follow (a 4-tuple; only major/minor matter): frames and model definitions
change layout with it, the other messages do not.

Positions stay in the wire unit (metres with Motive's default streaming settings) as
``float32`` arrays; the ``*_mm`` helpers give millimetres as ``float64``. Frames decode into
numpy structured arrays (one ``np.frombuffer`` per section) so the cost does not grow with a
Python call per field.

Malformed input raises ``drivers.errors.ProtocolError`` only: every count is checked against
the bytes that remain before anything is allocated, strings must end inside their section
and names are decoded as UTF-8 with replacement (never ``UnicodeDecodeError``).

NatNet 4.1 writes an ``int32`` byte count after each section count of a frame and after each
dataset type of a model definition. The decoder parses the section, checks that it used no
more than that many bytes and then skips to its end (so fields a later version appends are
stepped over). *Unverified* against a real Motive 3.1 capture: the count is taken to cover
the section's items only, as OptiTrack's own Python client reads it.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass, field
from typing import ClassVar, Union

import numpy as np

from drivers.errors import ProtocolError

Version = tuple[int, int, int, int]

# Message ids (NatNet SDK ``NatNetTypes.h``).
NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_ECHOREQUEST = 12
NAT_ECHORESPONSE = 13
NAT_DISCOVERY = 14
NAT_UNRECOGNIZED_REQUEST = 100

#: Lowest and highest stream versions whose frame layout this codec knows.
MIN_VERSION: Version = (3, 0, 0, 0)
MAX_VERSION: Version = (4, 1, 0, 0)

# Labeled-marker ``params`` bits (NatNet >= 2.6).
MARKER_OCCLUDED = 0x01
MARKER_PC_SOLVED = 0x02
MARKER_MODEL_SOLVED = 0x04
MARKER_HAS_MODEL = 0x08
MARKER_UNLABELED = 0x10
MARKER_ACTIVE = 0x20
# Rigid-body ``params`` bit 0: tracking valid.
RIGID_BODY_TRACKED = 0x01
# Frame ``params`` bits.
FRAME_RECORDING = 0x01
FRAME_MODELS_CHANGED = 0x02

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_I32x2 = struct.Struct("<ii")
_I32x3 = struct.Struct("<iii")
_U64 = struct.Struct("<Q")
_U64x2 = struct.Struct("<QQ")
_VEC3 = struct.Struct("<fff")
_VEC3_QUAT = struct.Struct("<fffffff")
_VERSION = struct.Struct("<BBBB")
_SERVERINFO_TAIL = struct.Struct("<QHB4s")
_F32 = struct.Struct("<f")
_F32x2 = struct.Struct("<ff")
_FP_FLOATS = struct.Struct("<144f12f")  # force-plate calibration matrix and corners
_SUFFIX3 = struct.Struct("<IIdQQQh")  # timecode, subframe, timestamp, 3 ticks, params
_SUFFIX4 = struct.Struct("<IIdQQQIIh")  # ... plus precision seconds / fraction
_END = struct.Struct("<i")
_ASSET_MARKER = struct.Struct("<iffffh")  # id, initial position, size, params

#: One labeled marker on the wire (NatNet >= 3.0): 26 bytes, packed.
LABELED_MARKER_DTYPE = np.dtype(
    [("id", "<u4"), ("pos", "<f4", (3,)), ("size", "<f4"), ("params", "<i2"), ("residual", "<f4")]
)
#: One rigid body on the wire (NatNet >= 3.0): 38 bytes, packed. quat is x, y, z, w.
RIGID_BODY_DTYPE = np.dtype(
    [("id", "<i4"), ("pos", "<f4", (3,)), ("quat", "<f4", (4,)), ("mean_error", "<f4"), ("params", "<i2")]
)
_LM_SIZE = LABELED_MARKER_DTYPE.itemsize
_RB_SIZE = RIGID_BODY_DTYPE.itemsize

_EMPTY_VEC3 = np.zeros((0, 3), dtype="<f4")
_EMPTY_VEC3.flags.writeable = False
_EMPTY_LM = np.zeros(0, dtype=LABELED_MARKER_DTYPE)
_EMPTY_LM.flags.writeable = False
_EMPTY_RB = np.zeros(0, dtype=RIGID_BODY_DTYPE)
_EMPTY_RB.flags.writeable = False


def version_tuple(version) -> Version:
    """Normalise ``(3, 0)``, ``(4, 1, 0, 0)`` or ``"4.1"`` to a 4-tuple of ints."""
    if isinstance(version, str):
        parts = version.strip().split(".")
        try:
            nums = [int(p) for p in parts if p != ""]
        except ValueError as exc:
            raise ValueError(f"NatNet version must look like '4.1', got {version!r}") from exc
    else:
        try:
            nums = [int(p) for p in version]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"NatNet version must be 1-4 numbers 0..255, got {version!r}") from exc
    if not 1 <= len(nums) <= 4 or any(not 0 <= n <= 255 for n in nums):
        raise ValueError(f"NatNet version must be 1-4 numbers 0..255, got {version!r}")
    return tuple(nums + [0] * (4 - len(nums)))  # type: ignore[return-value]


def check_supported(version) -> Version:
    """Return ``version`` as a 4-tuple or raise ValueError if its frame layout is unknown.

    Known layouts: NatNet 3.0 up to ``MAX_VERSION`` (4.1, Motive 3.1). A newer version is
    refused rather than read with an older layout (NatNet 4.1 already added byte counts and
    assets to 4.0; a later one may change a frame again)."""
    v = version_tuple(version)
    if v[:2] < MIN_VERSION[:2]:
        raise ValueError(
            f"NatNet {v[0]}.{v[1]} is not supported; this codec reads NatNet "
            f"{MIN_VERSION[0]}.{MIN_VERSION[1]} to {MAX_VERSION[0]}.{MAX_VERSION[1]} (Motive 2.0 and later)"
        )
    if v[:2] > MAX_VERSION[:2]:
        raise ValueError(
            f"NatNet {v[0]}.{v[1]} is newer than the newest layout this codec implements "
            f"({MAX_VERSION[0]}.{MAX_VERSION[1]}); supported: NatNet {MIN_VERSION[0]}.{MIN_VERSION[1]} "
            f"to {MAX_VERSION[0]}.{MAX_VERSION[1]}"
        )
    return v


_LAYOUTS: dict = {}  # version argument as given (hashable) -> checked 4-tuple


def layout_version(version) -> Version:
    """``version`` checked as the layout argument of the decode/encode functions: a NatNet
    version between ``MIN_VERSION`` and ``MAX_VERSION`` (4-tuple, 2-tuple or ``"4.1"``).
    Raises ValueError (a wrong argument, not bad wire data) naming what is allowed."""
    try:
        return _LAYOUTS[version]
    except KeyError:
        pass
    except TypeError:  # unhashable (a list): check every time
        return _check_layout(version)
    v = _check_layout(version)
    if len(_LAYOUTS) < 256:
        _LAYOUTS[version] = v
    return v


def _check_layout(version) -> Version:
    try:
        return check_supported(version)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"NatNet layout version {version!r} is not usable: {exc}. Pass the stream version "
            "as a tuple such as (4, 1, 0, 0) or a string such as '4.1'"
        ) from exc


def _has_byte_counts(version: Version) -> bool:
    return version[:2] >= (4, 1)


# --------------------------------------------------------------------------- equality helper


class _ArrayEq:
    """Field-wise ``==`` for dataclasses holding numpy arrays (bit-exact on arrays)."""

    __slots__ = ()

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            if not _values_equal(getattr(self, f.name), getattr(other, f.name)):
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


def _values_equal(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b))
    return bool(a == b)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Connect:
    """NAT_CONNECT from a client. Servers accept any of three layouts (``layout``):

    ``"natnetlib"``: 264 bytes, 256-byte name + app version + NatNet version (NatNetLib 3.0);
    ``"python"``: 271 bytes, ``"Ping"`` with the requested version at byte 265 (OptiTrack's
    4.1 Python client); ``"ping"``: a bare NUL-terminated name.
    """

    MESSAGE_ID: ClassVar[int] = NAT_CONNECT
    name: str = "Ping"
    app_version: Version = (0, 0, 0, 0)
    natnet_version: Version = (0, 0, 0, 0)
    layout: str = "natnetlib"


@dataclass(frozen=True, slots=True)
class Discovery(Connect):
    """NAT_DISCOVERY (broadcast by clients looking for servers); same payload as Connect."""

    MESSAGE_ID: ClassVar[int] = NAT_DISCOVERY


@dataclass(frozen=True, slots=True)
class ServerInfo:
    """NAT_SERVERINFO. ``clock_frequency`` (ticks per second of the frame tick stamps),
    ``data_port``, ``multicast`` and ``multicast_address`` exist from NatNet 3.0 on and are
    None when the server sent the short (264-byte) form."""

    MESSAGE_ID: ClassVar[int] = NAT_SERVERINFO
    app_name: str
    app_version: Version
    natnet_version: Version
    clock_frequency: int | None = None
    data_port: int | None = None
    multicast: bool | None = None
    multicast_address: str | None = None


@dataclass(frozen=True, slots=True)
class Request:
    """NAT_REQUEST: a text command, e.g. ``"Bitstream,4.1"``."""

    MESSAGE_ID: ClassVar[int] = NAT_REQUEST
    command: str


@dataclass(frozen=True, slots=True)
class Response:
    """NAT_RESPONSE: either a 4-byte value ``code`` or a ``text`` reply.

    A 4-byte payload is what the request makes it (NatNet SDK ``NatNetRequests.h``): an
    ``int32`` result (0 = success, e.g. ``Bitstream,4.1``, ``AnalogSamplesPerMocapFrame``) or
    a ``float32`` (``FrameRate`` in frames per second, ``UnitsToMillimeters``). The wire does
    not say which, so it decodes as ``code`` (the int32 reading of the bytes) and
    ``float32`` reads the same four bytes as a float; ``Response.of_float32(x)`` builds one.
    """

    MESSAGE_ID: ClassVar[int] = NAT_RESPONSE
    code: int | None = None
    text: str | None = None

    def __post_init__(self) -> None:
        if (self.code is None) == (self.text is None):
            raise ValueError("Response needs exactly one of code or text")

    @classmethod
    def of_float32(cls, value: float) -> "Response":
        """A 4-byte reply holding ``value`` as a little-endian float32 (e.g. FrameRate)."""
        return cls(code=_I32.unpack(_F32.pack(value))[0])

    @property
    def float32(self) -> float:
        """The 4-byte reply read as a float32; ValueError for a text reply."""
        if self.code is None:
            raise ValueError(f"a text reply {self.text!r} has no float32 value")
        return _F32.unpack(_I32.pack(self.code))[0]


@dataclass(frozen=True, slots=True)
class RequestModelDef:
    MESSAGE_ID: ClassVar[int] = NAT_REQUEST_MODELDEF


@dataclass(frozen=True, slots=True)
class RequestFrameOfData:
    MESSAGE_ID: ClassVar[int] = NAT_REQUEST_FRAMEOFDATA


@dataclass(frozen=True, slots=True)
class KeepAlive:
    MESSAGE_ID: ClassVar[int] = NAT_KEEPALIVE


@dataclass(frozen=True, slots=True)
class Disconnect:
    MESSAGE_ID: ClassVar[int] = NAT_DISCONNECT


@dataclass(frozen=True, slots=True)
class UnrecognizedRequest:
    MESSAGE_ID: ClassVar[int] = NAT_UNRECOGNIZED_REQUEST


@dataclass(frozen=True, slots=True)
class MessageString:
    MESSAGE_ID: ClassVar[int] = NAT_MESSAGESTRING
    text: str


@dataclass(frozen=True, slots=True)
class EchoRequest:
    """NAT_ECHOREQUEST: the client's own ``uint64`` time stamp, echoed back."""

    MESSAGE_ID: ClassVar[int] = NAT_ECHOREQUEST
    client_stamp: int


@dataclass(frozen=True, slots=True)
class EchoResponse:
    """NAT_ECHORESPONSE: the request's stamp and the server's high-resolution tick count."""

    MESSAGE_ID: ClassVar[int] = NAT_ECHORESPONSE
    client_stamp: int
    server_stamp: int


# ---- model definitions


@dataclass(frozen=True, slots=True)
class MarkerSetDescription:
    TYPE_ID: ClassVar[int] = 0
    name: str
    marker_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class RigidBodyMarkerDescription:
    """A marker of a rigid body: ``offset`` (x, y, z) from the body's pivot, wire unit;
    ``name`` is sent from NatNet 4.0 on (empty before)."""

    offset: tuple[float, float, float]
    active_label: int = 0
    name: str = ""


@dataclass(frozen=True, slots=True)
class RigidBodyDescription:
    TYPE_ID: ClassVar[int] = 1
    name: str
    id: int
    parent_id: int = -1
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    markers: tuple[RigidBodyMarkerDescription, ...] = ()


@dataclass(frozen=True, slots=True)
class SkeletonDescription:
    TYPE_ID: ClassVar[int] = 2
    name: str
    id: int
    rigid_bodies: tuple[RigidBodyDescription, ...] = ()


@dataclass(frozen=True, slots=True)
class ForcePlateDescription:
    """A force plate (NatNet >= 3.0). cal_matrix: 144 floats (12×12, row-major);
    corners: 12 floats (4 corners × x, y, z); lengths in the wire unit."""

    TYPE_ID: ClassVar[int] = 3
    id: int
    serial: str
    width: float
    length: float
    origin: tuple[float, float, float]
    cal_matrix: tuple[float, ...]
    corners: tuple[float, ...]
    plate_type: int = 0
    channel_data_type: int = 0
    channel_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class DeviceDescription:
    """A peripheral device such as an analog DAQ (NatNet >= 3.0)."""

    TYPE_ID: ClassVar[int] = 4
    id: int
    name: str
    serial: str
    device_type: int = 0
    channel_data_type: int = 0
    channel_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class CameraDescription:
    TYPE_ID: ClassVar[int] = 5
    name: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class AssetMarkerDescription:
    """A marker of a trained-markerset asset: ``id`` as the asset's frame data labels it,
    ``position`` (x, y, z) its initial position and ``size`` its diameter (wire unit),
    ``params`` its flags."""

    name: str
    id: int
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    size: float = 0.0
    params: int = 0


@dataclass(frozen=True, slots=True)
class AssetDescription:
    """A trained-markerset asset (NatNet >= 4.1, dataset type 6): name, ``asset_type``,
    ``id``, its bones (rigid-body descriptions) and markers. Layout as OptiTrack's NatNet 4.1
    Python client (natnetsdk 4.1.1) reads it: name, int32 type, int32 id, int32 bone count,
    bones, int32 marker count, markers (name, int32 id, vec3, float size, int16 params)."""

    TYPE_ID: ClassVar[int] = 6
    name: str
    asset_type: int
    id: int
    rigid_bodies: tuple[RigidBodyDescription, ...] = ()
    markers: tuple[AssetMarkerDescription, ...] = ()


@dataclass(frozen=True, slots=True)
class UnknownDescription:
    """A dataset this codec does not parse (a type newer than 4.1), kept as raw bytes.
    Only NatNet >= 4.1 lets a reader skip it; earlier layouts raise ProtocolError instead."""

    type_id: int
    raw: bytes


Description = Union[
    MarkerSetDescription, RigidBodyDescription, SkeletonDescription, ForcePlateDescription,
    DeviceDescription, CameraDescription, AssetDescription, UnknownDescription,
]


@dataclass(frozen=True, slots=True)
class ModelDef:
    """NAT_MODELDEF: the data descriptions (marker sets, rigid bodies, …) in server order."""

    MESSAGE_ID: ClassVar[int] = NAT_MODELDEF
    datasets: tuple[Description, ...] = ()

    @property
    def rigid_bodies(self) -> list[RigidBodyDescription]:
        return [d for d in self.datasets if isinstance(d, RigidBodyDescription)]

    @property
    def marker_sets(self) -> list[MarkerSetDescription]:
        return [d for d in self.datasets if isinstance(d, MarkerSetDescription)]

    @property
    def skeletons(self) -> list[SkeletonDescription]:
        return [d for d in self.datasets if isinstance(d, SkeletonDescription)]

    @property
    def assets(self) -> list[AssetDescription]:
        return [d for d in self.datasets if isinstance(d, AssetDescription)]


# ---- frame of data


@dataclass(eq=False, slots=True)
class MarkerSetData(_ArrayEq):
    """A named marker set's positions: ``positions`` shape (n, 3), float32, wire unit."""

    name: str
    positions: np.ndarray


@dataclass(eq=False, slots=True)
class SkeletonData(_ArrayEq):
    """A skeleton: its ``rigid_bodies`` as a RIGID_BODY_DTYPE array (bones)."""

    id: int
    rigid_bodies: np.ndarray


@dataclass(eq=False, slots=True)
class AssetData(_ArrayEq):
    """A trained-markerset asset (NatNet >= 4.1): bones and markers, structured arrays."""

    id: int
    rigid_bodies: np.ndarray
    markers: np.ndarray


@dataclass(eq=False, slots=True)
class AnalogData(_ArrayEq):
    """A force plate or device: per channel, a float32 array of that channel's sub-frames."""

    id: int
    channels: tuple[np.ndarray, ...]


@dataclass(eq=False, slots=True)
class FrameOfData(_ArrayEq):
    """NAT_FRAMEOFDATA, positions in the wire unit (metres by default).

    unlabeled: shape (n, 3) float32 ("other" / legacy markers).
    rigid_bodies: RIGID_BODY_DTYPE array, fields id, pos (3,), quat (x, y, z, w), mean_error,
    params (bit 0 tracking valid).
    labeled_markers: LABELED_MARKER_DTYPE array, fields id (model id << 16 | marker id),
    pos (3,), size, params (MARKER_* bits), residual.
    timestamp: seconds on the server's clock since its start; the three ``stamp_*`` fields are
    ticks of the server's high-resolution clock (``ServerInfo.clock_frequency`` per second).
    """

    MESSAGE_ID: ClassVar[int] = NAT_FRAMEOFDATA
    frame_number: int
    marker_sets: tuple[MarkerSetData, ...] = ()
    unlabeled: np.ndarray = field(default_factory=lambda: _EMPTY_VEC3)
    rigid_bodies: np.ndarray = field(default_factory=lambda: _EMPTY_RB)
    skeletons: tuple[SkeletonData, ...] = ()
    assets: tuple[AssetData, ...] = ()
    labeled_markers: np.ndarray = field(default_factory=lambda: _EMPTY_LM)
    force_plates: tuple[AnalogData, ...] = ()
    devices: tuple[AnalogData, ...] = ()
    timecode: int = 0
    timecode_subframe: int = 0
    timestamp: float = 0.0
    stamp_camera_mid_exposure: int = 0
    stamp_data_received: int = 0
    stamp_transmit: int = 0
    precision_timestamp_secs: int = 0
    precision_timestamp_frac_secs: int = 0
    params: int = 0

    # --- millimetre helpers (float64)
    def unlabeled_mm(self) -> np.ndarray:
        """Unlabeled marker positions, shape (n, 3), mm (wire metres × 1000)."""
        return self.unlabeled.astype(np.float64) * 1000.0

    def rigid_body_positions_mm(self) -> np.ndarray:
        """Rigid-body pivot positions, shape (n_bodies, 3), mm."""
        return self.rigid_bodies["pos"].astype(np.float64) * 1000.0

    def labeled_positions_mm(self) -> np.ndarray:
        """Labeled marker positions, shape (n_markers, 3), mm."""
        return self.labeled_markers["pos"].astype(np.float64) * 1000.0

    # --- labeled-marker decoding
    @property
    def model_ids(self) -> np.ndarray:
        """Model (asset / rigid body) id of each labeled marker, shape (n,), 0 = unlabeled."""
        return (self.labeled_markers["id"] >> 16).astype(np.int64)

    @property
    def marker_ids(self) -> np.ndarray:
        """Marker id within its model, shape (n,)."""
        return (self.labeled_markers["id"] & 0xFFFF).astype(np.int64)

    @property
    def occluded(self) -> np.ndarray:
        """True where a labeled marker is occluded (params bit 0x01), shape (n,)."""
        return (self.labeled_markers["params"] & MARKER_OCCLUDED) != 0

    @property
    def tracking_valid(self) -> np.ndarray:
        """True where a rigid body is tracked (params bit 0x01), shape (n_bodies,)."""
        return (self.rigid_bodies["params"] & RIGID_BODY_TRACKED) != 0

    @property
    def is_recording(self) -> bool:
        return bool(self.params & FRAME_RECORDING)

    @property
    def tracked_models_changed(self) -> bool:
        return bool(self.params & FRAME_MODELS_CHANGED)

    def latencies_s(self, clock_frequency: int) -> tuple[float, float]:
        """(software, system) latency in seconds: transmit − data received, and transmit −
        mid-exposure, from the tick stamps and the server's ``clock_frequency`` (Hz)."""
        if clock_frequency <= 0:
            raise ValueError(f"clock_frequency must be positive, got {clock_frequency}")
        f = float(clock_frequency)
        return (
            (self.stamp_transmit - self.stamp_data_received) / f,
            (self.stamp_transmit - self.stamp_camera_mid_exposure) / f,
        )


Message = Union[
    Connect, Discovery, ServerInfo, Request, Response, RequestModelDef, RequestFrameOfData,
    KeepAlive, Disconnect, UnrecognizedRequest, MessageString, EchoRequest, EchoResponse,
    ModelDef, FrameOfData,
]

MESSAGE_NAMES = {
    NAT_CONNECT: "CONNECT", NAT_SERVERINFO: "SERVERINFO", NAT_REQUEST: "REQUEST",
    NAT_RESPONSE: "RESPONSE", NAT_REQUEST_MODELDEF: "REQUEST_MODELDEF", NAT_MODELDEF: "MODELDEF",
    NAT_REQUEST_FRAMEOFDATA: "REQUEST_FRAMEOFDATA", NAT_FRAMEOFDATA: "FRAMEOFDATA",
    NAT_MESSAGESTRING: "MESSAGESTRING", NAT_DISCONNECT: "DISCONNECT", NAT_KEEPALIVE: "KEEPALIVE",
    NAT_ECHOREQUEST: "ECHOREQUEST", NAT_ECHORESPONSE: "ECHORESPONSE", NAT_DISCOVERY: "DISCOVERY",
    NAT_UNRECOGNIZED_REQUEST: "UNRECOGNIZED_REQUEST",
}


# --------------------------------------------------------------------------- low-level reading


def _need(buf: bytes, off: int, n: int, end: int, what: str) -> None:
    if off + n > end:
        raise ProtocolError(
            f"NatNet {what}: needs {n} bytes at offset {off}, only {max(end - off, 0)} left"
        )


def _cstring(buf: bytes, off: int, end: int, what: str) -> tuple[str, int]:
    """A NUL-terminated string starting at ``off`` that must end before ``end``."""
    nul = buf.find(b"\0", off, end)
    if nul < 0:
        raise ProtocolError(f"NatNet {what}: string at offset {off} has no NUL before byte {end}")
    return buf[off:nul].decode("utf-8", "replace"), nul + 1


def _fixed_string(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("utf-8", "replace")


def _count(buf: bytes, off: int, end: int, min_item: int, what: str) -> tuple[int, int]:
    """Read an int32 count and check ``count * min_item`` bytes can follow."""
    if off + 4 > end:
        raise ProtocolError(f"NatNet {what}: count at offset {off} is cut off (packet ends at {end})")
    (n,) = _I32.unpack_from(buf, off)
    off += 4
    if n < 0 or n * min_item > end - off:
        raise ProtocolError(
            f"NatNet {what}: count {n} does not fit the {end - off} bytes left "
            f"(each item needs at least {min_item})"
        )
    return n, off


def _section(buf: bytes, off: int, end: int, min_item: int, v41: bool, what: str):
    """Section header: count and (NatNet 4.1) byte count. Returns (count, off, section_end)."""
    if not v41:
        n, off = _count(buf, off, end, min_item, what)
        return n, off, end
    if off + 8 > end:
        raise ProtocolError(f"NatNet {what}: section header at offset {off} is cut off")
    n, nbytes = _I32x2.unpack_from(buf, off)
    off += 8
    if nbytes < 0 or nbytes > end - off:
        raise ProtocolError(
            f"NatNet {what}: byte count {nbytes} does not fit the {end - off} bytes left"
        )
    if n < 0 or n * min_item > nbytes:
        raise ProtocolError(
            f"NatNet {what}: count {n} does not fit its byte count {nbytes} "
            f"(each item needs at least {min_item})"
        )
    return n, off, off + nbytes


def _section_done(off: int, sec_end: int, v41: bool, what: str) -> int:
    if not v41:
        return off
    if off > sec_end:
        raise ProtocolError(f"NatNet {what}: items use {off - sec_end} bytes more than the byte count")
    return sec_end


def _vec3_array(buf: bytes, off: int, n: int) -> tuple[np.ndarray, int]:
    if n == 0:
        return _EMPTY_VEC3, off
    return np.frombuffer(buf, dtype="<f4", count=3 * n, offset=off).reshape(n, 3), off + 12 * n


def _records(buf: bytes, off: int, n: int, dtype: np.dtype, empty: np.ndarray):
    if n == 0:
        return empty, off
    return np.frombuffer(buf, dtype=dtype, count=n, offset=off), off + n * dtype.itemsize


# --------------------------------------------------------------------------- frame decode


def decode_frame(payload: bytes, version: Version = MIN_VERSION) -> FrameOfData:
    """Decode a FRAMEOFDATA payload (without the 4-byte header) in the ``version`` layout.

    ``version``: the stream's NatNet version, 3.0 to ``MAX_VERSION`` (ValueError otherwise)."""
    version = layout_version(version)
    buf = payload if type(payload) is bytes else bytes(payload)
    end = len(buf)
    v4 = version[0] >= 4
    v41 = version[:2] >= (4, 1)
    if end < 4:
        raise ProtocolError(f"NatNet frame: payload of {end} bytes is shorter than a frame number")
    (frame_number,) = _I32.unpack_from(buf, 0)
    off = 4

    # marker sets: name, count, vec3s
    n, off, sec = _section(buf, off, end, 5, v41, "marker sets")
    marker_sets = []
    for _ in range(n):
        name, off = _cstring(buf, off, sec, "marker set name")
        k, off = _count(buf, off, sec, 12, f"marker set {name!r}")
        pos, off = _vec3_array(buf, off, k)
        marker_sets.append(MarkerSetData(name, pos))
    off = _section_done(off, sec, v41, "marker sets")

    # legacy unlabeled ("other") markers
    n, off, sec = _section(buf, off, end, 12, v41, "unlabeled markers")
    unlabeled, off = _vec3_array(buf, off, n)
    off = _section_done(off, sec, v41, "unlabeled markers")

    # rigid bodies (>= 3.0: no per-body marker list)
    n, off, sec = _section(buf, off, end, _RB_SIZE, v41, "rigid bodies")
    rigid_bodies, off = _records(buf, off, n, RIGID_BODY_DTYPE, _EMPTY_RB)
    off = _section_done(off, sec, v41, "rigid bodies")

    # skeletons: id, body count, bodies
    n, off, sec = _section(buf, off, end, 8, v41, "skeletons")
    skeletons = []
    for _ in range(n):
        _need(buf, off, 4, sec, "skeleton id")
        (sk_id,) = _I32.unpack_from(buf, off)
        k, off = _count(buf, off + 4, sec, _RB_SIZE, f"skeleton {sk_id} bones")
        bones, off = _records(buf, off, k, RIGID_BODY_DTYPE, _EMPTY_RB)
        skeletons.append(SkeletonData(sk_id, bones))
    off = _section_done(off, sec, v41, "skeletons")

    # assets (>= 4.1): id, bones, markers
    assets = []
    if v41:
        n, off, sec = _section(buf, off, end, 12, v41, "assets")
        for _ in range(n):
            _need(buf, off, 4, sec, "asset id")
            (a_id,) = _I32.unpack_from(buf, off)
            k, off = _count(buf, off + 4, sec, _RB_SIZE, f"asset {a_id} bones")
            bones, off = _records(buf, off, k, RIGID_BODY_DTYPE, _EMPTY_RB)
            k, off = _count(buf, off, sec, _LM_SIZE, f"asset {a_id} markers")
            marks, off = _records(buf, off, k, LABELED_MARKER_DTYPE, _EMPTY_LM)
            assets.append(AssetData(a_id, bones, marks))
        off = _section_done(off, sec, v41, "assets")

    # labeled markers
    n, off, sec = _section(buf, off, end, _LM_SIZE, v41, "labeled markers")
    labeled, off = _records(buf, off, n, LABELED_MARKER_DTYPE, _EMPTY_LM)
    off = _section_done(off, sec, v41, "labeled markers")

    # force plates and devices: id, channel count, per channel frame count + floats
    analog = []
    for what in ("force plates", "devices"):
        n, off, sec = _section(buf, off, end, 8, v41, what)
        items = []
        for _ in range(n):
            _need(buf, off, 8, sec, what)
            a_id, nch = _I32x2.unpack_from(buf, off)
            off += 8
            if nch < 0 or nch * 4 > sec - off:
                raise ProtocolError(f"NatNet {what} {a_id}: channel count {nch} does not fit")
            chans = []
            for _c in range(nch):
                k, off = _count(buf, off, sec, 4, f"{what} {a_id} channel frames")
                chans.append(np.frombuffer(buf, dtype="<f4", count=k, offset=off))
                off += 4 * k
            items.append(AnalogData(a_id, tuple(chans)))
        analog.append(tuple(items))
        off = _section_done(off, sec, v41, what)

    suffix = _SUFFIX4 if v4 else _SUFFIX3
    if off + suffix.size > end:
        raise ProtocolError(
            f"NatNet frame {frame_number}: suffix needs {suffix.size} bytes at offset {off}, "
            f"{end - off} left"
        )
    s = suffix.unpack_from(buf, off)
    off += suffix.size
    if off + 4 <= end:  # end-of-data marker; tolerated when absent
        (eod,) = _END.unpack_from(buf, off)
        if eod != 0:
            raise ProtocolError(f"NatNet frame {frame_number}: end-of-data marker is {eod}, not 0")
    if v4:
        prec_s, prec_frac, params = s[6], s[7], s[8]
    else:
        prec_s, prec_frac, params = 0, 0, s[6]
    return FrameOfData(
        frame_number, tuple(marker_sets), unlabeled, rigid_bodies, tuple(skeletons),
        tuple(assets), labeled, analog[0], analog[1],
        s[0], s[1], s[2], s[3], s[4], s[5], prec_s, prec_frac, params,
    )


# --------------------------------------------------------------------------- frame encode


def _i32(v: int) -> bytes:
    return _I32.pack(v)


def _cstr(s: str) -> bytes:
    raw = s.encode("utf-8")
    if b"\0" in raw:
        raise ValueError(f"NatNet strings cannot contain NUL: {s!r}")
    return raw + b"\0"


def _as_records(arr, dtype: np.dtype, what: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.dtype != dtype:
        raise ValueError(f"{what} must be a {dtype} structured array, got dtype {a.dtype}")
    return np.ascontiguousarray(a)


def _vec3_bytes(arr, what: str) -> tuple[int, bytes]:
    a = np.asarray(arr, dtype="<f4")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must have shape (n, 3), got {a.shape}")
    return a.shape[0], np.ascontiguousarray(a).tobytes()


def _put_section(out: list, count: int, body: bytes, v41: bool) -> None:
    out.append(_i32(count))
    if v41:
        out.append(_i32(len(body)))
    out.append(body)


def encode_frame(frame: FrameOfData, version: Version = MIN_VERSION) -> bytes:
    """The FRAMEOFDATA payload of ``frame`` in the ``version`` layout (no header)."""
    version = layout_version(version)
    v4 = version[0] >= 4
    v41 = version[:2] >= (4, 1)
    out: list[bytes] = [_i32(frame.frame_number)]
    parts = []
    for ms in frame.marker_sets:
        k, raw = _vec3_bytes(ms.positions, f"marker set {ms.name!r} positions")
        parts += [_cstr(ms.name), _i32(k), raw]
    _put_section(out, len(frame.marker_sets), b"".join(parts), v41)
    n, raw = _vec3_bytes(frame.unlabeled, "unlabeled")
    _put_section(out, n, raw, v41)
    rbs = _as_records(frame.rigid_bodies, RIGID_BODY_DTYPE, "rigid_bodies")
    _put_section(out, len(rbs), rbs.tobytes(), v41)
    body = b"".join(
        _I32x2.pack(sk.id, len(sk.rigid_bodies))
        + _as_records(sk.rigid_bodies, RIGID_BODY_DTYPE, "skeleton bones").tobytes()
        for sk in frame.skeletons
    )
    _put_section(out, len(frame.skeletons), body, v41)
    if v41:
        body = b"".join(
            _I32x2.pack(a.id, len(a.rigid_bodies))
            + _as_records(a.rigid_bodies, RIGID_BODY_DTYPE, "asset bones").tobytes()
            + _i32(len(a.markers))
            + _as_records(a.markers, LABELED_MARKER_DTYPE, "asset markers").tobytes()
            for a in frame.assets
        )
        _put_section(out, len(frame.assets), body, v41)
    elif frame.assets:
        raise ValueError(f"assets exist only from NatNet 4.1; cannot encode them as {version[:2]}")
    lms = _as_records(frame.labeled_markers, LABELED_MARKER_DTYPE, "labeled_markers")
    _put_section(out, len(lms), lms.tobytes(), v41)
    for items in (frame.force_plates, frame.devices):
        body = b"".join(
            _I32x2.pack(a.id, len(a.channels))
            + b"".join(
                _i32(len(c)) + np.ascontiguousarray(c, dtype="<f4").tobytes() for c in a.channels
            )
            for a in items
        )
        _put_section(out, len(items), body, v41)
    if v4:
        out.append(_SUFFIX4.pack(
            frame.timecode, frame.timecode_subframe, frame.timestamp,
            frame.stamp_camera_mid_exposure, frame.stamp_data_received, frame.stamp_transmit,
            frame.precision_timestamp_secs, frame.precision_timestamp_frac_secs, frame.params,
        ))
    else:
        out.append(_SUFFIX3.pack(
            frame.timecode, frame.timecode_subframe, frame.timestamp,
            frame.stamp_camera_mid_exposure, frame.stamp_data_received, frame.stamp_transmit,
            frame.params,
        ))
    out.append(_END.pack(0))
    return b"".join(out)


# --------------------------------------------------------------------------- model definitions


def _decode_rigid_body_desc(buf: bytes, off: int, end: int, version: Version):
    name, off = _cstring(buf, off, end, "rigid body description name")
    _need(buf, off, 20, end, f"rigid body description {name!r}")
    rb_id, parent = _I32x2.unpack_from(buf, off)
    offset = _VEC3.unpack_from(buf, off + 8)
    n, off = _count(buf, off + 20, end, 16, f"rigid body {name!r} markers")
    offsets = [_VEC3.unpack_from(buf, off + 12 * i) for i in range(n)]
    off += 12 * n
    labels = struct.unpack_from(f"<{n}i", buf, off) if n else ()
    off += 4 * n
    names = [""] * n
    if version[0] >= 4:
        for i in range(n):
            names[i], off = _cstring(buf, off, end, f"rigid body {name!r} marker name")
    markers = tuple(
        RigidBodyMarkerDescription(offsets[i], labels[i], names[i]) for i in range(n)
    )
    return RigidBodyDescription(name, rb_id, parent, offset, markers), off


def _encode_rigid_body_desc(d: RigidBodyDescription, version: Version) -> bytes:
    parts = [_cstr(d.name), _I32x2.pack(d.id, d.parent_id), _VEC3.pack(*d.offset), _i32(len(d.markers))]
    parts += [_VEC3.pack(*m.offset) for m in d.markers]
    parts += [_i32(m.active_label) for m in d.markers]
    if version[0] >= 4:
        parts += [_cstr(m.name) for m in d.markers]
    return b"".join(parts)


def _decode_dataset(type_id: int, buf: bytes, off: int, end: int, version: Version):
    if type_id == 0:
        name, off = _cstring(buf, off, end, "marker set description name")
        n, off = _count(buf, off, end, 1, f"marker set {name!r} names")
        names = []
        for _ in range(n):
            s, off = _cstring(buf, off, end, f"marker set {name!r} marker name")
            names.append(s)
        return MarkerSetDescription(name, tuple(names)), off
    if type_id == 1:
        return _decode_rigid_body_desc(buf, off, end, version)
    if type_id == 2:
        name, off = _cstring(buf, off, end, "skeleton description name")
        _need(buf, off, 4, end, f"skeleton {name!r} id")
        (sk_id,) = _I32.unpack_from(buf, off)
        n, off = _count(buf, off + 4, end, 25, f"skeleton {name!r} bones")
        bones = []
        for _ in range(n):
            bone, off = _decode_rigid_body_desc(buf, off, end, version)
            bones.append(bone)
        return SkeletonDescription(name, sk_id, tuple(bones)), off
    if type_id == 3:
        _need(buf, off, 4, end, "force plate id")
        (fp_id,) = _I32.unpack_from(buf, off)
        serial, off = _cstring(buf, off + 4, end, f"force plate {fp_id} serial")
        fixed = 8 + 12 + _FP_FLOATS.size + 8
        _need(buf, off, fixed, end, f"force plate {fp_id}")
        width, length = _F32x2.unpack_from(buf, off)
        origin = _VEC3.unpack_from(buf, off + 8)
        floats = _FP_FLOATS.unpack_from(buf, off + 20)
        plate_type, data_type = _I32x2.unpack_from(buf, off + 20 + _FP_FLOATS.size)
        names, off = _channel_names(buf, off + fixed, end, f"force plate {fp_id}")
        return ForcePlateDescription(fp_id, serial, width, length, origin, floats[:144],
                                     floats[144:], plate_type, data_type, names), off
    if type_id == 4:
        _need(buf, off, 4, end, "device id")
        (dev_id,) = _I32.unpack_from(buf, off)
        name, off = _cstring(buf, off + 4, end, f"device {dev_id} name")
        serial, off = _cstring(buf, off, end, f"device {dev_id} serial")
        _need(buf, off, 8, end, f"device {dev_id} types")
        dev_type, data_type = _I32x2.unpack_from(buf, off)
        names, off = _channel_names(buf, off + 8, end, f"device {dev_id}")
        return DeviceDescription(dev_id, name, serial, dev_type, data_type, names), off
    if type_id == 5:
        name, off = _cstring(buf, off, end, "camera description name")
        _need(buf, off, 28, end, f"camera {name!r}")
        v = _VEC3_QUAT.unpack_from(buf, off)
        return CameraDescription(name, v[:3], v[3:]), off + 28
    if type_id == 6 and _has_byte_counts(version):
        name, off = _cstring(buf, off, end, "asset description name")
        _need(buf, off, 8, end, f"asset {name!r} type and id")
        a_type, a_id = _I32x2.unpack_from(buf, off)
        n, off = _count(buf, off + 8, end, 25, f"asset {name!r} bones")
        bones = []
        for _ in range(n):
            bone, off = _decode_rigid_body_desc(buf, off, end, version)
            bones.append(bone)
        n, off = _count(buf, off, end, 1 + _ASSET_MARKER.size, f"asset {name!r} markers")
        markers = []
        for _ in range(n):
            m_name, off = _cstring(buf, off, end, f"asset {name!r} marker name")
            _need(buf, off, _ASSET_MARKER.size, end, f"asset {name!r} marker {m_name!r}")
            m_id, x, y, z, size, params = _ASSET_MARKER.unpack_from(buf, off)
            off += _ASSET_MARKER.size
            markers.append(AssetMarkerDescription(m_name, m_id, (x, y, z), size, params))
        return AssetDescription(name, a_type, a_id, tuple(bones), tuple(markers)), off
    raise ProtocolError(
        f"NatNet model definition: dataset type {type_id} cannot be read in NatNet "
        f"{version[0]}.{version[1]} (known: 0 marker set, 1 rigid body, 2 skeleton, "
        "3 force plate, 4 device, 5 camera, 6 asset (4.1); "
        "other types are skipped only with 4.1 byte counts)"
    )


def _channel_names(buf: bytes, off: int, end: int, what: str) -> tuple[tuple[str, ...], int]:
    n, off = _count(buf, off, end, 1, f"{what} channel names")
    names = []
    for _ in range(n):
        s, off = _cstring(buf, off, end, f"{what} channel name")
        names.append(s)
    return tuple(names), off


def _encode_names(names) -> bytes:
    return _i32(len(names)) + b"".join(_cstr(s) for s in names)


def _encode_dataset(d: Description, version: Version) -> bytes:
    if isinstance(d, MarkerSetDescription):
        return _cstr(d.name) + _encode_names(d.marker_names)
    if isinstance(d, RigidBodyDescription):
        return _encode_rigid_body_desc(d, version)
    if isinstance(d, SkeletonDescription):
        return (
            _cstr(d.name) + _I32x2.pack(d.id, len(d.rigid_bodies))
            + b"".join(_encode_rigid_body_desc(b, version) for b in d.rigid_bodies)
        )
    if isinstance(d, ForcePlateDescription):
        if len(d.cal_matrix) != 144 or len(d.corners) != 12:
            raise ValueError(
                f"force plate {d.id}: cal_matrix needs 144 floats and corners 12, "
                f"got {len(d.cal_matrix)} and {len(d.corners)}"
            )
        return (
            _i32(d.id) + _cstr(d.serial) + _F32x2.pack(d.width, d.length) + _VEC3.pack(*d.origin)
            + _FP_FLOATS.pack(*d.cal_matrix, *d.corners)
            + _I32x2.pack(d.plate_type, d.channel_data_type) + _encode_names(d.channel_names)
        )
    if isinstance(d, DeviceDescription):
        return (
            _i32(d.id) + _cstr(d.name) + _cstr(d.serial)
            + _I32x2.pack(d.device_type, d.channel_data_type) + _encode_names(d.channel_names)
        )
    if isinstance(d, CameraDescription):
        return _cstr(d.name) + _VEC3_QUAT.pack(*d.position, *d.orientation)
    if isinstance(d, AssetDescription):
        if not _has_byte_counts(version):
            raise ValueError(f"asset descriptions exist only from NatNet 4.1; cannot encode them as {version[:2]}")
        return (
            _cstr(d.name) + _I32x2.pack(d.asset_type, d.id) + _i32(len(d.rigid_bodies))
            + b"".join(_encode_rigid_body_desc(b, version) for b in d.rigid_bodies)
            + _i32(len(d.markers))
            + b"".join(_cstr(m.name) + _ASSET_MARKER.pack(m.id, *m.position, m.size, m.params)
                       for m in d.markers)
        )
    if isinstance(d, UnknownDescription):
        if not _has_byte_counts(version):
            raise ValueError("an UnknownDescription can be encoded only with NatNet 4.1 byte counts")
        return bytes(d.raw)
    raise TypeError(f"not a NatNet data description: {type(d).__name__}")


def decode_modeldef(payload: bytes, version: Version = MIN_VERSION) -> ModelDef:
    """Decode a MODELDEF payload in the ``version`` layout (3.0 to ``MAX_VERSION``)."""
    version = layout_version(version)
    buf = payload if type(payload) is bytes else bytes(payload)
    end = len(buf)
    v41 = _has_byte_counts(version)
    n, off = _count(buf, 0, end, 8, "model definition datasets")
    datasets = []
    for _ in range(n):
        if v41:
            _need(buf, off, 8, end, "dataset header")
            type_id, nbytes = _I32x2.unpack_from(buf, off)
            off += 8
            if nbytes < 0 or nbytes > end - off:
                raise ProtocolError(
                    f"NatNet dataset type {type_id}: byte count {nbytes} does not fit the "
                    f"{end - off} bytes left"
                )
            sec = off + nbytes
            if type_id in (0, 1, 2, 3, 4, 5, 6):
                d, used = _decode_dataset(type_id, buf, off, sec, version)
            else:
                d, used = UnknownDescription(type_id, buf[off:sec]), sec
            datasets.append(d)
            off = _section_done(used, sec, True, f"dataset type {type_id}")
        else:
            _need(buf, off, 4, end, "dataset type")
            (type_id,) = _I32.unpack_from(buf, off)
            d, off = _decode_dataset(type_id, buf, off + 4, end, version)
            datasets.append(d)
    return ModelDef(tuple(datasets))


def encode_modeldef(md: ModelDef, version: Version = MIN_VERSION) -> bytes:
    version = layout_version(version)
    v41 = _has_byte_counts(version)
    parts = [_i32(len(md.datasets))]
    for d in md.datasets:
        body = _encode_dataset(d, version)
        type_id = d.type_id if isinstance(d, UnknownDescription) else d.TYPE_ID
        parts.append(_i32(type_id))
        if v41:
            parts.append(_i32(len(body)))
        parts.append(body)
    return b"".join(parts)


# --------------------------------------------------------------------------- small messages

_CONNECT_NATNETLIB_SIZE = 264
_CONNECT_PYTHON_SIZE = 271
_CONNECT_PYTHON_VERSION_AT = 265
_SERVERINFO_SHORT = 264
_SERVERINFO_LONG = 264 + _SERVERINFO_TAIL.size  # 279


def _decode_connect(cls, buf: bytes):
    n = len(buf)
    if n == _CONNECT_NATNETLIB_SIZE:
        return cls(_fixed_string(buf[:256]), _VERSION.unpack_from(buf, 256),
                   _VERSION.unpack_from(buf, 260), "natnetlib")
    if n >= _CONNECT_PYTHON_VERSION_AT + 4:
        return cls(_fixed_string(buf[:_CONNECT_PYTHON_VERSION_AT - 1]), (0, 0, 0, 0),
                   _VERSION.unpack_from(buf, _CONNECT_PYTHON_VERSION_AT), "python")
    return cls(_fixed_string(buf), (0, 0, 0, 0), (0, 0, 0, 0), "ping")


def _encode_connect(m: Connect) -> bytes:
    raw = m.name.encode("utf-8")
    if m.layout == "natnetlib":
        if len(raw) > 255:
            raise ValueError(f"client name is {len(raw)} bytes; at most 255 fit")
        return raw.ljust(256, b"\0") + _VERSION.pack(*m.app_version) + _VERSION.pack(*m.natnet_version)
    if m.layout == "python":
        if len(raw) > _CONNECT_PYTHON_VERSION_AT - 2:
            raise ValueError(f"client name is {len(raw)} bytes; too long for the python layout")
        body = raw.ljust(_CONNECT_PYTHON_VERSION_AT, b"\0") + _VERSION.pack(*m.natnet_version)
        return body.ljust(_CONNECT_PYTHON_SIZE, b"\0")
    if m.layout == "ping":
        return _cstr(m.name)
    raise ValueError(f"Connect layout must be 'natnetlib', 'python' or 'ping', got {m.layout!r}")


def _decode_serverinfo(buf: bytes) -> ServerInfo:
    n = len(buf)
    if n < _SERVERINFO_SHORT:
        raise ProtocolError(f"NatNet SERVERINFO: payload is {n} bytes, at least 264 expected")
    name = _fixed_string(buf[:256])
    app = _VERSION.unpack_from(buf, 256)
    nn = _VERSION.unpack_from(buf, 260)
    if n < _SERVERINFO_LONG:
        return ServerInfo(name, app, nn)
    freq, port, mc, addr = _SERVERINFO_TAIL.unpack_from(buf, 264)
    return ServerInfo(name, app, nn, freq, port, bool(mc), ".".join(str(b) for b in addr))


def _encode_serverinfo(m: ServerInfo) -> bytes:
    raw = m.app_name.encode("utf-8")
    if len(raw) > 255:
        raise ValueError(f"server name is {len(raw)} bytes; at most 255 fit")
    head = raw.ljust(256, b"\0") + _VERSION.pack(*m.app_version) + _VERSION.pack(*m.natnet_version)
    if m.clock_frequency is None:
        return head
    addr = bytes(int(p) for p in (m.multicast_address or "0.0.0.0").split("."))
    if len(addr) != 4:
        raise ValueError(f"multicast_address must be dotted IPv4, got {m.multicast_address!r}")
    return head + _SERVERINFO_TAIL.pack(m.clock_frequency, m.data_port or 0, int(bool(m.multicast)), addr)


def _decode_text(buf: bytes, what: str) -> str:
    nul = buf.find(b"\0")
    if nul < 0:
        raise ProtocolError(f"NatNet {what}: text is not NUL-terminated")
    return buf[:nul].decode("utf-8", "replace")


# --------------------------------------------------------------------------- packets


def decode_packet(data: bytes, version: Version = MIN_VERSION) -> Message:
    """Decode one datagram. ``version``: the stream's NatNet version (4-tuple).

    Bytes after the declared payload are ignored (some clients append a NUL). Raises
    ProtocolError for anything that does not follow the protocol, and ValueError when
    ``version`` is not a layout this codec implements (3.0 to ``MAX_VERSION``).
    """
    version = layout_version(version)
    buf = data if type(data) is bytes else bytes(data)
    if len(buf) < 4:
        raise ProtocolError(f"NatNet packet of {len(buf)} bytes is shorter than its 4-byte header")
    msg_id, size = _HEADER.unpack_from(buf, 0)
    if size > len(buf) - 4:
        raise ProtocolError(
            f"NatNet {MESSAGE_NAMES.get(msg_id, msg_id)}: header declares {size} payload bytes, "
            f"datagram carries {len(buf) - 4}"
        )
    p = buf[4:4 + size]
    if msg_id == NAT_FRAMEOFDATA:
        return decode_frame(p, version)
    if msg_id == NAT_MODELDEF:
        return decode_modeldef(p, version)
    if msg_id == NAT_SERVERINFO:
        return _decode_serverinfo(p)
    if msg_id == NAT_CONNECT:
        return _decode_connect(Connect, p)
    if msg_id == NAT_DISCOVERY:
        return _decode_connect(Discovery, p)
    if msg_id == NAT_REQUEST:
        return Request(_decode_text(p, "REQUEST"))
    if msg_id == NAT_RESPONSE:
        if size == 4:
            return Response(code=_I32.unpack_from(p, 0)[0])
        return Response(text=_decode_text(p, "RESPONSE"))
    if msg_id == NAT_MESSAGESTRING:
        return MessageString(_decode_text(p, "MESSAGESTRING"))
    if msg_id == NAT_ECHOREQUEST:
        if size < 8:
            raise ProtocolError(f"NatNet ECHOREQUEST: payload is {size} bytes, 8 expected")
        return EchoRequest(_U64.unpack_from(p, 0)[0])
    if msg_id == NAT_ECHORESPONSE:
        if size < 16:
            raise ProtocolError(f"NatNet ECHORESPONSE: payload is {size} bytes, 16 expected")
        return EchoResponse(*_U64x2.unpack_from(p, 0))
    if msg_id == NAT_REQUEST_MODELDEF:
        return RequestModelDef()
    if msg_id == NAT_REQUEST_FRAMEOFDATA:
        return RequestFrameOfData()
    if msg_id == NAT_KEEPALIVE:
        return KeepAlive()
    if msg_id == NAT_DISCONNECT:
        return Disconnect()
    if msg_id == NAT_UNRECOGNIZED_REQUEST:
        return UnrecognizedRequest()
    raise ProtocolError(
        f"NatNet message id {msg_id} is unknown; known ids: "
        + ", ".join(f"{k} {v}" for k, v in sorted(MESSAGE_NAMES.items()))
    )


def encode_payload(msg: Message, version: Version = MIN_VERSION) -> bytes:
    """The payload bytes of ``msg`` (no header); ValueError for a version outside 3.0 – 4.1."""
    version = layout_version(version)
    if isinstance(msg, FrameOfData):
        return encode_frame(msg, version)
    if isinstance(msg, ModelDef):
        return encode_modeldef(msg, version)
    if isinstance(msg, ServerInfo):
        return _encode_serverinfo(msg)
    if isinstance(msg, Connect):  # and Discovery
        return _encode_connect(msg)
    if isinstance(msg, Request):
        return _cstr(msg.command)
    if isinstance(msg, Response):
        if msg.code is not None:
            return _I32.pack(msg.code)
        raw = _cstr(msg.text or "")
        return raw + b"\0" if len(raw) == 4 else raw  # a 4-byte payload would read as a code
    if isinstance(msg, MessageString):
        return _cstr(msg.text)
    if isinstance(msg, EchoRequest):
        return _U64.pack(msg.client_stamp)
    if isinstance(msg, EchoResponse):
        return _U64x2.pack(msg.client_stamp, msg.server_stamp)
    if isinstance(msg, (RequestModelDef, RequestFrameOfData, KeepAlive, Disconnect, UnrecognizedRequest)):
        return b""
    raise TypeError(f"not a NatNet message: {type(msg).__name__}")


def encode_packet(msg: Message, version: Version = MIN_VERSION) -> bytes:
    """One datagram: header + payload of ``msg`` in the ``version`` layout."""
    payload = encode_payload(msg, version)
    if len(payload) > 0xFFFF:
        raise ValueError(f"NatNet payload of {len(payload)} bytes exceeds the 65535 a header can declare")
    return _HEADER.pack(msg.MESSAGE_ID, len(payload)) + payload


def peek_message_id(data: bytes) -> int:
    """The message id of a datagram without decoding it (ProtocolError if too short)."""
    if len(data) < 2:
        raise ProtocolError(f"NatNet packet of {len(data)} bytes has no message id")
    return data[0] | (data[1] << 8)
