"""FRI messages as dataclasses, with their proto2 encoding and decoding.

The field numbers and wire types are ours to state (``drivers/kuka_fri/PROTOCOL.md``), taken
from the public facts in ``PROTOCOLS.md`` and the generated tables (``FRIMessages.pb.h/.c``)
of KUKA's FRI client SDK, versions 1.x and 2.x. One set of dataclasses covers both: FRI 1.x
(Sunrise.OS 1.11–1.16) sends ``commandedJointPosition`` (monitor data field 3); FRI 2.x drops it
and adds the measured/ipo Cartesian pose and redundancy information (monitor data 9 and 10,
ipo data 2 and 3, command data 6 and 7) and the client command mode 4 (Cartesian pose); FRI 2.7
sends no ``endOfMessageData``. ``layout_of`` tells which one a controller speaks. Joint values are tuples of floats (radians for
positions, N·m for torques); ``None`` means the field was absent, ``()`` that it was present
but empty. Enumerations decode to their ``IntEnum`` when the value is known; an unknown value
of a state the client acts on (session state, quality) is a ``ProtocolError``, an unknown value
of the others is kept as a plain ``int`` (a newer controller may add values; the commander
treats anything but the known good value as not good).

Decoding follows proto2: fields in any order, the last value of a repeated scalar wins,
a singular embedded message given twice is merged (we parse the concatenation of its parts,
which is the same thing), unknown fields are skipped, required fields are checked, and
``repeated double`` is accepted packed or not. Nothing but ``ProtocolError`` escapes a decode.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Optional

from drivers.errors import ProtocolError
from drivers.kuka_fri import wire
from drivers.kuka_fri.framing import unframe
from drivers.kuka_fri.wire import I64, LEN, VARINT

MONITORING_MESSAGE_ID = 0x245142
COMMAND_MESSAGE_ID = 0x34001


class SessionState(IntEnum):
    IDLE = 0
    MONITORING_WAIT = 1
    MONITORING_READY = 2
    COMMANDING_WAIT = 3
    COMMANDING_ACTIVE = 4


class ConnectionQuality(IntEnum):
    POOR = 0
    FAIR = 1
    GOOD = 2
    EXCELLENT = 3


class SafetyState(IntEnum):
    NORMAL_OPERATION = 0
    SAFETY_STOP_LEVEL_0 = 1
    SAFETY_STOP_LEVEL_1 = 2
    SAFETY_STOP_LEVEL_2 = 3


class DriveState(IntEnum):
    OFF = 0
    TRANSITIONING = 1
    ACTIVE = 2


class OperationMode(IntEnum):
    TEST_MODE_1 = 0
    TEST_MODE_2 = 1
    AUTOMATIC_MODE = 2


class ControlMode(IntEnum):
    POSITION_CONTROL_MODE = 0
    CARTESIAN_IMPEDANCE_CONTROL_MODE = 1
    JOINT_IMPEDANCE_CONTROL_MODE = 2
    NO_CONTROL = 3


class ClientCommandMode(IntEnum):
    NO_COMMAND_MODE = 0
    POSITION = 1
    WRENCH = 2
    TORQUE = 3
    CARTESIAN_POSE = 4  # FRI 2.x


class RedundancyStrategy(IntEnum):
    """FRI 2.x: E1 means the redundancy value is the A3 joint position (rad)."""

    E1 = 0
    NONE = 4


class OverlayType(IntEnum):
    NO_OVERLAY = 0
    JOINT = 1
    CARTESIAN = 2


class IOType(IntEnum):
    BOOLEAN = 0
    DIGITAL = 1
    ANALOG = 2


class IODirection(IntEnum):
    INPUT = 0
    OUTPUT = 1


JointValues = tuple[float, ...]


@dataclass(frozen=True, slots=True)
class MessageHeader:
    """All three fields required: identifier, the sender's counter, the peer's counter echoed."""

    message_identifier: int
    sequence_counter: int
    reflected_sequence_counter: int


@dataclass(frozen=True, slots=True)
class TimeStamp:
    """Controller time: whole seconds and nanoseconds (both required)."""

    sec: int
    nanosec: int

    @property
    def seconds(self) -> float:
        return self.sec + self.nanosec * 1e-9

    @classmethod
    def from_seconds(cls, t: float) -> "TimeStamp":
        sec = int(t)
        return cls(sec, min(int(round((t - sec) * 1e9)), 999_999_999))


@dataclass(frozen=True, slots=True)
class QuaternionTransformation:
    """FRI 2.x Cartesian pose of the TCP in the robot base frame.

    element: shape (7,) ``[t_x, t_y, t_z, q_w, q_x, q_y, q_z]``: translation in mm, unit
    quaternion. name (required on the wire): the frame's name.
    """

    name: str
    element: tuple[float, ...]
    timestamp: Optional[TimeStamp] = None


@dataclass(frozen=True, slots=True)
class RedundancyInformation:
    """FRI 2.x redundancy: ``strategy`` (``RedundancyStrategy``) and its ``value`` (E1: rad)."""

    strategy: int
    value: float


@dataclass(frozen=True, slots=True)
class ConnectionInfo:
    """Session state and quality are required; send period in ms."""

    session_state: SessionState
    quality: ConnectionQuality
    send_period: Optional[int] = None
    receive_multiplier: Optional[int] = None


@dataclass(frozen=True, slots=True)
class RobotInfo:
    number_of_joints: Optional[int] = None
    safety_state: Optional[int] = None
    drive_state: tuple[int, ...] = ()
    operation_mode: Optional[int] = None
    control_mode: Optional[int] = None


@dataclass(frozen=True, slots=True)
class IOValue:
    """One controller IO the robot application shares over FRI (``FriIOValue``; the application
    registers it in its ``FRIConfiguration``). name: ``<IO group>.<IO>`` as Sunrise names it
    (e.g. ``FRI.In_Bool_Clock_Enabled`` in KUKA's IOAccess example; at most 63 bytes);
    ``digital_value`` carries BOOLEAN (0/1) and DIGITAL values, ``analog_value`` ANALOG ones."""

    name: str
    type: int
    direction: int
    digital_value: Optional[int] = None
    analog_value: Optional[float] = None


@dataclass(frozen=True, slots=True)
class MonitorData:
    """Joint positions in radians, torques in N·m, each shape (n_joints,) when present;
    ``io``: the IOs the robot application shares (``readIORequest``), in the order sent."""

    measured_joint_position: Optional[JointValues] = None
    measured_torque: Optional[JointValues] = None
    commanded_joint_position: Optional[JointValues] = None
    commanded_torque: Optional[JointValues] = None
    external_torque: Optional[JointValues] = None
    timestamp: Optional[TimeStamp] = None
    measured_cartesian_pose: Optional[QuaternionTransformation] = None  # FRI 2.x
    measured_redundancy: Optional[RedundancyInformation] = None  # FRI 2.x
    io: tuple[IOValue, ...] = ()


@dataclass(frozen=True, slots=True)
class IpoData:
    """The controller's interpolated set-point (radians) and the commanding mode it expects."""

    joint_position: Optional[JointValues] = None
    client_command_mode: Optional[int] = None
    overlay_type: Optional[int] = None
    tracking_performance: Optional[float] = None
    cartesian_pose: Optional[QuaternionTransformation] = None  # FRI 2.x
    redundancy: Optional[RedundancyInformation] = None  # FRI 2.x


@dataclass(frozen=True, slots=True)
class EndOfMessage:
    message_length: Optional[int] = None
    crc32: Optional[int] = None


@dataclass(frozen=True, slots=True)
class FRIMonitoringMessage:
    header: MessageHeader
    robot_info: Optional[RobotInfo] = None
    monitor_data: Optional[MonitorData] = None
    connection_info: Optional[ConnectionInfo] = None
    ipo_data: Optional[IpoData] = None
    end_of_message: Optional[EndOfMessage] = None

    def encode(self) -> bytes:
        return encode_monitoring(self)

    @staticmethod
    def decode(data: bytes) -> "FRIMonitoringMessage":
        return decode_monitoring(data)


@dataclass(frozen=True, slots=True)
class CommandData:
    """Joint positions to command (radians) or joint torques (N·m), shape (n_joints,)."""

    joint_position: Optional[JointValues] = None
    joint_torque: Optional[JointValues] = None
    cartesian_pose: Optional[QuaternionTransformation] = None  # FRI 2.x
    redundancy: Optional[RedundancyInformation] = None  # FRI 2.x


@dataclass(frozen=True, slots=True)
class FRICommandMessage:
    header: MessageHeader
    command_data: Optional[CommandData] = None
    end_of_message: Optional[EndOfMessage] = None

    def encode(self) -> bytes:
        return encode_command(self)

    @staticmethod
    def decode(data: bytes) -> "FRICommandMessage":
        return decode_command(data)


@dataclass(frozen=True, slots=True)
class FriLayout:
    """Which FRI message layout a controller speaks, as far as its monitoring messages tell.

    major: 1 (Sunrise.OS 1.11–1.16: ``commandedJointPosition`` present) or 2 (Sunrise.OS 2.x:
    absent). end_of_message: whether ``endOfMessageData`` is sent (FRI 2.7 dropped it).
    """

    major: int
    end_of_message: bool

    def __str__(self) -> str:
        if self.major == 1:
            return "FRI 1.x"
        return "FRI 2.x" + ("" if self.end_of_message else " (2.7, no end-of-message)")


def layout_of(msg: "FRIMonitoringMessage") -> FriLayout:
    """The layout of one monitoring message (see ``FriLayout``)."""
    md = msg.monitor_data
    major = 1 if md is not None and md.commanded_joint_position is not None else 2
    return FriLayout(major, msg.end_of_message is not None)


# ============================================================================ encoding


def _enc_joint_values(field_number: int, values: Optional[JointValues]) -> bytes:
    if values is None:
        return b""
    return wire.encode_bytes(field_number, wire.encode_repeated_double(1, values))


def _enc_message(field_number: int, payload: Optional[bytes]) -> bytes:
    return b"" if payload is None else wire.encode_bytes(field_number, payload)


def _enc_enum(field_number: int, value: Optional[int]) -> bytes:
    return b"" if value is None else wire.encode_int32(field_number, int(value))


def encode_header(h: MessageHeader) -> bytes:
    return (
        wire.encode_uint32(1, h.message_identifier)
        + wire.encode_uint32(2, h.sequence_counter)
        + wire.encode_uint32(3, h.reflected_sequence_counter)
    )


def _enc_timestamp(t: TimeStamp) -> bytes:
    return wire.encode_uint32(1, t.sec) + wire.encode_uint32(2, t.nanosec)


def _enc_connection_info(c: ConnectionInfo) -> bytes:
    out = wire.encode_int32(1, int(c.session_state)) + wire.encode_int32(2, int(c.quality))
    if c.send_period is not None:
        out += wire.encode_uint32(3, c.send_period)
    if c.receive_multiplier is not None:
        out += wire.encode_uint32(4, c.receive_multiplier)
    return out


def _enc_robot_info(r: RobotInfo) -> bytes:
    out = b""
    if r.number_of_joints is not None:
        out += wire.encode_int32(1, r.number_of_joints)
    out += _enc_enum(2, r.safety_state)
    for d in r.drive_state:  # repeated enum, not packed (proto2 default)
        out += wire.encode_int32(5, int(d))
    return out + _enc_enum(6, r.operation_mode) + _enc_enum(7, r.control_mode)


def _enc_pose(field_number: int, p: Optional[QuaternionTransformation]) -> bytes:
    if p is None:
        return b""
    out = wire.encode_bytes(1, p.name.encode("utf-8")) + wire.encode_repeated_double(2, p.element)
    if p.timestamp is not None:
        out += wire.encode_bytes(3, _enc_timestamp(p.timestamp))
    return wire.encode_bytes(field_number, out)


def _enc_redundancy(field_number: int, r: Optional[RedundancyInformation]) -> bytes:
    if r is None:
        return b""
    return wire.encode_bytes(field_number, wire.encode_int32(1, int(r.strategy)) + wire.encode_double(2, r.value))


def _enc_io(field_number: int, v: IOValue) -> bytes:
    out = wire.encode_bytes(1, v.name.encode("utf-8")) + wire.encode_int32(2, int(v.type))
    out += wire.encode_int32(3, int(v.direction))
    if v.digital_value is not None:
        out += wire.tag(4, VARINT) + wire.encode_varint(int(v.digital_value))
    if v.analog_value is not None:
        out += wire.encode_double(5, v.analog_value)
    return wire.encode_bytes(field_number, out)


def _enc_monitor_data(m: MonitorData) -> bytes:
    return (
        _enc_joint_values(1, m.measured_joint_position)
        + _enc_joint_values(2, m.measured_torque)
        + _enc_joint_values(3, m.commanded_joint_position)
        + _enc_joint_values(4, m.commanded_torque)
        + _enc_joint_values(5, m.external_torque)
        + b"".join(_enc_io(8, v) for v in m.io)
        + _enc_pose(9, m.measured_cartesian_pose)
        + _enc_redundancy(10, m.measured_redundancy)
        + (b"" if m.timestamp is None else wire.encode_bytes(15, _enc_timestamp(m.timestamp)))
    )


def _enc_ipo_data(p: IpoData) -> bytes:
    out = _enc_joint_values(1, p.joint_position) + _enc_pose(2, p.cartesian_pose)
    out += _enc_redundancy(3, p.redundancy)
    out += _enc_enum(10, p.client_command_mode) + _enc_enum(11, p.overlay_type)
    if p.tracking_performance is not None:
        out += wire.encode_double(12, p.tracking_performance)
    return out


def _enc_end_of_message(e: EndOfMessage) -> bytes:
    out = b""
    if e.message_length is not None:
        out += wire.encode_int32(1, e.message_length)
    if e.crc32 is not None:
        out += wire.encode_bytes(2, wire.encode_int32(1, e.crc32))
    return out


def encode_monitoring(msg: FRIMonitoringMessage) -> bytes:
    """Serialise a monitoring message, fields in ascending number order."""
    return (
        wire.encode_bytes(1, encode_header(msg.header))
        + _enc_message(2, None if msg.robot_info is None else _enc_robot_info(msg.robot_info))
        + _enc_message(3, None if msg.monitor_data is None else _enc_monitor_data(msg.monitor_data))
        + _enc_message(
            4, None if msg.connection_info is None else _enc_connection_info(msg.connection_info)
        )
        + _enc_message(5, None if msg.ipo_data is None else _enc_ipo_data(msg.ipo_data))
        + _enc_message(
            15, None if msg.end_of_message is None else _enc_end_of_message(msg.end_of_message)
        )
    )


def encode_command(msg: FRICommandMessage) -> bytes:
    """Serialise a command message, fields in ascending number order."""
    cd = msg.command_data
    payload = None
    if cd is not None:
        payload = (
            _enc_joint_values(1, cd.joint_position)
            + _enc_joint_values(3, cd.joint_torque)
            + _enc_pose(6, cd.cartesian_pose)
            + _enc_redundancy(7, cd.redundancy)
        )
    return (
        wire.encode_bytes(1, encode_header(msg.header))
        + _enc_message(2, payload)
        + _enc_message(
            15, None if msg.end_of_message is None else _enc_end_of_message(msg.end_of_message)
        )
    )


# ============================================================================ decoding


def _expect(wt: int, expected: int, what: str) -> None:
    if wt != expected:
        names = {0: "varint", 1: "64-bit", 2: "length-delimited", 5: "32-bit"}
        raise ProtocolError(
            f"{what}: wire type {names.get(wt, wt)}, expected {names.get(expected, expected)}"
        )


def _strict_enum(cls: type[IntEnum], value: int, what: str) -> IntEnum:
    v = wire.as_int32(value, what)
    try:
        return cls(v)
    except ValueError:
        allowed = ", ".join(f"{m.value} {m.name}" for m in cls)
        raise ProtocolError(f"{what}: unknown value {v}; allowed: {allowed}") from None


_ENUM_MEMBERS: dict[type, dict[int, IntEnum]] = {}


def _lenient_enum(cls: type[IntEnum], value: int, what: str) -> int:
    members = _ENUM_MEMBERS.get(cls)
    if members is None:
        members = _ENUM_MEMBERS.setdefault(cls, {m.value: m for m in cls})
    if value in members:
        return members[value]
    return wire.as_int32(value, what)


def _merged(parts: list) -> Optional[bytes]:
    if not parts:
        return None
    return bytes(parts[0]) if len(parts) == 1 else b"".join(bytes(p) for p in parts)


_JOINT_STRUCTS: dict[int, struct.Struct] = {}


def decode_joint_values(payload, what: str) -> JointValues:
    """A ``JointValues`` message: field 1 ``repeated double``, packed or not."""
    raw = bytes(payload)
    n, rest = divmod(len(raw), 9)
    if rest == 0 and raw[::9] == b"\x09" * n:  # fast path: n non-packed doubles, nothing else
        st = _JOINT_STRUCTS.get(n)
        if st is None:
            st = _JOINT_STRUCTS.setdefault(n, struct.Struct("<" + "Bd" * n))
        return st.unpack(raw)[1::2]
    values: list[float] = []
    for fn, wt, val in wire.iter_fields(payload):
        if fn != 1:
            continue
        if wt == I64:
            values.append(wire.decode_double(val))
        elif wt == LEN:
            values.extend(wire.decode_packed_doubles(val, f"{what}.value"))
        else:
            _expect(wt, I64, f"{what}.value")
    return tuple(values)


def decode_header(payload, what: str = "MessageHeader") -> MessageHeader:
    got: dict[int, int] = {}
    for fn, wt, val in wire.iter_fields(payload):
        if fn in (1, 2, 3):
            _expect(wt, VARINT, f"{what} field {fn}")
            got[fn] = wire.as_uint32(val, f"{what} field {fn}")
    for fn, name in ((1, "messageIdentifier"), (2, "sequenceCounter"), (3, "reflectedSequenceCounter")):
        if fn not in got:
            raise ProtocolError(f"{what}: required field {name} ({fn}) is missing")
    return MessageHeader(got[1], got[2], got[3])


def _dec_timestamp(payload) -> TimeStamp:
    got: dict[int, int] = {}
    for fn, wt, val in wire.iter_fields(payload):
        if fn in (1, 2):
            _expect(wt, VARINT, f"TimeStamp field {fn}")
            got[fn] = wire.as_uint32(val, f"TimeStamp field {fn}")
    for fn, name in ((1, "sec"), (2, "nanosec")):
        if fn not in got:
            raise ProtocolError(f"TimeStamp: required field {name} ({fn}) is missing")
    return TimeStamp(got[1], got[2])


def _dec_connection_info(payload) -> ConnectionInfo:
    state = quality = period = mult = None
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, VARINT, "ConnectionInfo.sessionState")
            state = _strict_enum(SessionState, val, "ConnectionInfo.sessionState")
        elif fn == 2:
            _expect(wt, VARINT, "ConnectionInfo.quality")
            quality = _strict_enum(ConnectionQuality, val, "ConnectionInfo.quality")
        elif fn == 3:
            _expect(wt, VARINT, "ConnectionInfo.sendPeriod")
            period = wire.as_uint32(val, "ConnectionInfo.sendPeriod")
        elif fn == 4:
            _expect(wt, VARINT, "ConnectionInfo.receiveMultiplier")
            mult = wire.as_uint32(val, "ConnectionInfo.receiveMultiplier")
    if state is None:
        raise ProtocolError("ConnectionInfo: required field sessionState (1) is missing")
    if quality is None:
        raise ProtocolError("ConnectionInfo: required field quality (2) is missing")
    return ConnectionInfo(state, quality, period, mult)


def _dec_robot_info(payload) -> RobotInfo:
    n = safety = op = ctrl = None
    drives: list[int] = []
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, VARINT, "RobotInfo.numberOfJoints")
            n = wire.as_int32(val, "RobotInfo.numberOfJoints")
        elif fn == 2:
            _expect(wt, VARINT, "RobotInfo.safetyState")
            safety = _lenient_enum(SafetyState, val, "RobotInfo.safetyState")
        elif fn == 5:
            if wt == LEN:  # packed repeated enum
                drives.extend(
                    _lenient_enum(DriveState, v, "RobotInfo.driveState")
                    for v in wire.decode_packed_varints(val)
                )
            else:
                _expect(wt, VARINT, "RobotInfo.driveState")
                drives.append(_lenient_enum(DriveState, val, "RobotInfo.driveState"))
        elif fn == 6:
            _expect(wt, VARINT, "RobotInfo.operationMode")
            op = _lenient_enum(OperationMode, val, "RobotInfo.operationMode")
        elif fn == 7:
            _expect(wt, VARINT, "RobotInfo.controlMode")
            ctrl = _lenient_enum(ControlMode, val, "RobotInfo.controlMode")
    return RobotInfo(n, safety, tuple(drives), op, ctrl)


_MONITOR_JOINT_FIELDS = {
    1: "measured_joint_position",
    2: "measured_torque",
    3: "commanded_joint_position",
    4: "commanded_torque",
    5: "external_torque",
}


def _collect(payload, wanted: set[int], what: str) -> dict[int, list]:
    """Group the length-delimited parts of ``wanted`` fields (for proto2 merging)."""
    parts: dict[int, list] = {}
    for fn, wt, val in wire.iter_fields(payload):
        if fn in wanted:
            _expect(wt, LEN, f"{what} field {fn}")
            parts.setdefault(fn, []).append(val)
    return parts


def _dec_pose(payload, what: str) -> QuaternionTransformation:
    """A ``QuaternionTransformation``: 1 name (required string), 2 element (repeated double),
    3 timestamp."""
    name = None
    elements: list[float] = []
    ts_parts: list = []
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, LEN, f"{what}.name")
            try:
                name = bytes(val).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise ProtocolError(f"{what}.name is not UTF-8: {exc}") from None
        elif fn == 2:
            if wt == I64:
                elements.append(wire.decode_double(val))
            elif wt == LEN:
                elements.extend(wire.decode_packed_doubles(val, f"{what}.element"))
            else:
                _expect(wt, I64, f"{what}.element")
        elif fn == 3:
            _expect(wt, LEN, f"{what}.timestamp")
            ts_parts.append(val)
    if name is None:
        raise ProtocolError(f"{what}: required field name (1) is missing")
    if len(elements) > 7:
        raise ProtocolError(f"{what}: {len(elements)} elements, at most 7 (t_x, t_y, t_z, q_w, q_x, q_y, q_z)")
    raw = _merged(ts_parts)
    return QuaternionTransformation(name, tuple(elements), None if raw is None else _dec_timestamp(raw))


def _dec_redundancy(payload, what: str) -> RedundancyInformation:
    """A ``RedundancyInformation``: 1 strategy (required enum), 2 value (required double)."""
    strategy = value = None
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, VARINT, f"{what}.strategy")
            strategy = _lenient_enum(RedundancyStrategy, val, f"{what}.strategy")
        elif fn == 2:
            _expect(wt, I64, f"{what}.value")
            value = wire.decode_double(val)
    if strategy is None:
        raise ProtocolError(f"{what}: required field strategy (1) is missing")
    if value is None:
        raise ProtocolError(f"{what}: required field value (2) is missing")
    return RedundancyInformation(strategy, value)


def _dec_io(payload, what: str) -> IOValue:
    """A ``FriIOValue``: 1 name (required string), 2 type, 3 direction (required enums),
    4 digitalValue (uint64), 5 analogValue (double)."""
    name = io_type = direction = digital = analog = None
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, LEN, f"{what}.name")
            try:
                name = bytes(val).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise ProtocolError(f"{what}.name is not UTF-8: {exc}") from None
        elif fn == 2:
            _expect(wt, VARINT, f"{what}.type")
            io_type = _lenient_enum(IOType, val, f"{what}.type")
        elif fn == 3:
            _expect(wt, VARINT, f"{what}.direction")
            direction = _lenient_enum(IODirection, val, f"{what}.direction")
        elif fn == 4:
            _expect(wt, VARINT, f"{what}.digitalValue")
            digital = int(val)
        elif fn == 5:
            _expect(wt, I64, f"{what}.analogValue")
            analog = wire.decode_double(val)
    for value, fn, field_name in ((name, 1, "name"), (io_type, 2, "type"), (direction, 3, "direction")):
        if value is None:
            raise ProtocolError(f"{what}: required field {field_name} ({fn}) is missing")
    return IOValue(name, io_type, direction, digital, analog)


def _dec_monitor_data(payload) -> MonitorData:
    parts = _collect(payload, {1, 2, 3, 4, 5, 8, 9, 10, 15}, "MessageMonitorData")
    kwargs = {}
    for fn, name in _MONITOR_JOINT_FIELDS.items():
        raw = _merged(parts.get(fn, []))
        if raw is not None:
            kwargs[name] = decode_joint_values(raw, f"MessageMonitorData.{name}")
    raw = _merged(parts.get(9, []))
    if raw is not None:
        kwargs["measured_cartesian_pose"] = _dec_pose(raw, "MessageMonitorData.measuredCartesianPose")
    raw = _merged(parts.get(10, []))
    if raw is not None:
        kwargs["measured_redundancy"] = _dec_redundancy(raw, "MessageMonitorData.measuredRedundancyInformation")
    raw = _merged(parts.get(15, []))
    if raw is not None:
        kwargs["timestamp"] = _dec_timestamp(raw)
    if 8 in parts:  # repeated: one FriIOValue per occurrence, never merged
        kwargs["io"] = tuple(_dec_io(v, "MessageMonitorData.readIORequest") for v in parts[8])
    return MonitorData(**kwargs)


def _dec_ipo_data(payload) -> IpoData:
    jp_parts: list = []
    pose_parts: list = []
    red_parts: list = []
    mode = overlay = perf = None
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, LEN, "MessageIpoData.jointPosition")
            jp_parts.append(val)
        elif fn == 2:
            _expect(wt, LEN, "MessageIpoData.cartesianPose")
            pose_parts.append(val)
        elif fn == 3:
            _expect(wt, LEN, "MessageIpoData.redundancyInformation")
            red_parts.append(val)
        elif fn == 10:
            _expect(wt, VARINT, "MessageIpoData.clientCommandMode")
            mode = _lenient_enum(ClientCommandMode, val, "MessageIpoData.clientCommandMode")
        elif fn == 11:
            _expect(wt, VARINT, "MessageIpoData.overlayType")
            overlay = _lenient_enum(OverlayType, val, "MessageIpoData.overlayType")
        elif fn == 12:
            _expect(wt, I64, "MessageIpoData.trackingPerformance")
            perf = wire.decode_double(val)
    raw = _merged(jp_parts)
    jp = None if raw is None else decode_joint_values(raw, "MessageIpoData.jointPosition")
    raw = _merged(pose_parts)
    pose = None if raw is None else _dec_pose(raw, "MessageIpoData.cartesianPose")
    raw = _merged(red_parts)
    red = None if raw is None else _dec_redundancy(raw, "MessageIpoData.redundancyInformation")
    return IpoData(jp, mode, overlay, perf, pose, red)


def _dec_end_of_message(payload) -> EndOfMessage:
    length = crc = None
    crc_parts: list = []
    for fn, wt, val in wire.iter_fields(payload):
        if fn == 1:
            _expect(wt, VARINT, "MessageEndOf.messageLength")
            length = wire.as_int32(val, "MessageEndOf.messageLength")
        elif fn == 2:
            _expect(wt, LEN, "MessageEndOf.messageChecksum")
            crc_parts.append(val)
    raw = _merged(crc_parts)
    if raw is not None:
        for fn, wt, val in wire.iter_fields(raw):
            if fn == 1:
                _expect(wt, VARINT, "Checksum.crc32")
                crc = wire.as_int32(val, "Checksum.crc32")
    return EndOfMessage(length, crc)


def _check_id(header: MessageHeader, expected: int, what: str) -> None:
    if header.message_identifier != expected:
        raise ProtocolError(
            f"{what}: message identifier 0x{header.message_identifier:X}, expected 0x{expected:X}"
        )


def decode_monitoring(data: bytes) -> FRIMonitoringMessage:
    """Parse a monitoring message, bare (FRI 1.x, 2.5) or in an FRI 2.7 frame (``framing``);
    ``ProtocolError`` for anything malformed, of another type, or a frame whose CRC-32 differs."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    data, _framed = unframe(data)
    parts = _collect(data, {1, 2, 3, 4, 5, 15}, "FRIMonitoringMessage")
    raw = _merged(parts.get(1, []))
    if raw is None:
        raise ProtocolError("FRIMonitoringMessage: required field header (1) is missing")
    header = decode_header(raw)
    _check_id(header, MONITORING_MESSAGE_ID, "FRIMonitoringMessage")

    def sub(fn, fun):
        r = _merged(parts.get(fn, []))
        return None if r is None else fun(r)

    return FRIMonitoringMessage(
        header=header,
        robot_info=sub(2, _dec_robot_info),
        monitor_data=sub(3, _dec_monitor_data),
        connection_info=sub(4, _dec_connection_info),
        ipo_data=sub(5, _dec_ipo_data),
        end_of_message=sub(15, _dec_end_of_message),
    )


def decode_command(data: bytes) -> FRICommandMessage:
    """Parse a command message, bare or in an FRI 2.7 frame (``framing``); ``ProtocolError`` for
    anything malformed, of another type, or a frame whose CRC-32 differs."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    data, _framed = unframe(data)
    parts = _collect(data, {1, 2, 15}, "FRICommandMessage")
    raw = _merged(parts.get(1, []))
    if raw is None:
        raise ProtocolError("FRICommandMessage: required field header (1) is missing")
    header = decode_header(raw)
    _check_id(header, COMMAND_MESSAGE_ID, "FRICommandMessage")
    command_data = None
    raw = _merged(parts.get(2, []))
    if raw is not None:
        cparts = _collect(raw, {1, 3, 6, 7}, "MessageCommandData")
        jp = _merged(cparts.get(1, []))
        jt = _merged(cparts.get(3, []))
        cp = _merged(cparts.get(6, []))
        rd = _merged(cparts.get(7, []))
        command_data = CommandData(
            joint_position=None if jp is None else decode_joint_values(jp, "MessageCommandData.jointPosition"),
            joint_torque=None if jt is None else decode_joint_values(jt, "MessageCommandData.jointTorque"),
            cartesian_pose=None if cp is None else _dec_pose(cp, "MessageCommandData.cartesianPose"),
            redundancy=None if rd is None else _dec_redundancy(rd, "MessageCommandData.redundancyInformation"),
        )
    raw = _merged(parts.get(15, []))
    return FRICommandMessage(
        header=header,
        command_data=command_data,
        end_of_message=None if raw is None else _dec_end_of_message(raw),
    )
