"""The datagrams the fake Sunrise sends: monitoring messages in each FRI version's layout, and
the malformed ones its fault hooks ask for.

Layouts (from the generated tables of KUKA's FRI client SDK): ``"1.15"`` carries
``commandedJointPosition`` (monitor data field 3); ``"2.5"`` drops it and adds the measured and
ipo Cartesian pose (mm, quaternion) and E1 redundancy; ``"2.7"`` is 2.5 without
``endOfMessageData``, framed with a length and a CRC-32 (``framing``). The Cartesian pose is the
flange of the nominal LBR iiwa 14 R820, as the controller's own model computes it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from drivers.kuka_fri.framing import frame, unframe
from drivers.kuka_fri.messages import (
    COMMAND_MESSAGE_ID,
    MONITORING_MESSAGE_ID,
    ClientCommandMode,
    ConnectionInfo,
    ConnectionQuality,
    ControlMode,
    DriveState,
    EndOfMessage,
    FRIMonitoringMessage,
    IODirection,
    IOType,
    IOValue,
    IpoData,
    MessageHeader,
    MonitorData,
    OperationMode,
    OverlayType,
    QuaternionTransformation,
    RedundancyInformation,
    RedundancyStrategy,
    RobotInfo,
    SafetyState,
    SessionState,
    TimeStamp,
)

N_JOINTS = 7
MALFORMED_KINDS = ("garbage", "truncated", "wrong_id", "bad_crc")

#: Nominal LBR iiwa 14 R820, standard DH (d mm, alpha rad; a = 0): the controller's own model.
_IIWA14_D = np.array([360.0, 0.0, 420.0, 0.0, 400.0, 0.0, 126.0])
_IIWA14_ALPHA = np.radians([-90.0, 90.0, 90.0, -90.0, -90.0, 90.0, 0.0])


def nominal_flange_pose(q_rad: np.ndarray) -> tuple[float, ...]:
    """Flange pose of the nominal iiwa 14 at joints ``q_rad`` (7,): ``(t_x, t_y, t_z, q_w,
    q_x, q_y, q_z)``, translation in mm, unit quaternion (FRI 2.x ``QuaternionTransformation``)."""
    T = np.eye(4)
    for th, d, al in zip(q_rad, _IIWA14_D, _IIWA14_ALPHA):
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, 0.0], [st, ct * ca, -ct * sa, 0.0],
                          [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]])
    R = T[:3, :3]
    w = math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2.0, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2.0, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2.0, R[1, 0] - R[0, 1])
    return (*T[:3, 3].tolist(), w, x, y, z)


@dataclass(frozen=True)
class ControllerView:
    """What one monitoring message reports. Joint arrays are (7,) rad: ``measured`` (noise
    included), ``setpoint`` (what the servo holds), ``ipo`` (the interpolator's position)."""

    seq: int
    client_seq: int
    measured: np.ndarray
    setpoint: np.ndarray
    ipo: np.ndarray
    state: SessionState
    quality: ConnectionQuality
    send_period_ms: int
    receive_multiplier: int
    safety: SafetyState
    drives: DriveState
    compliant: bool
    inputs: dict[str, bool]


def monitoring_datagram(version: str, view: ControllerView) -> bytes:
    """The monitoring datagram of FRI ``version`` (one of 1.15, 2.5, 2.7) for ``view``. Its time
    stamp is the controller's clock: time of day, not simulated time."""
    q = view.measured
    commanding = view.state in (SessionState.COMMANDING_WAIT, SessionState.COMMANDING_ACTIVE)
    v1 = version.startswith("1.")
    stamp = TimeStamp.from_seconds(time.time())
    pose = red = ipo_pose = ipo_red = None
    if not v1:
        pose = QuaternionTransformation("flange", nominal_flange_pose(q), stamp)
        red = RedundancyInformation(RedundancyStrategy.E1, float(q[2]))
        if commanding:
            ipo_pose = QuaternionTransformation("flange", nominal_flange_pose(view.ipo), stamp)
            ipo_red = RedundancyInformation(RedundancyStrategy.E1, float(view.ipo[2]))
    msg = FRIMonitoringMessage(
        header=MessageHeader(MONITORING_MESSAGE_ID, view.seq, view.client_seq),
        robot_info=RobotInfo(
            number_of_joints=N_JOINTS,
            safety_state=view.safety,
            drive_state=(view.drives,) * N_JOINTS,
            operation_mode=OperationMode.AUTOMATIC_MODE,
            control_mode=ControlMode.JOINT_IMPEDANCE_CONTROL_MODE if view.compliant else ControlMode.POSITION_CONTROL_MODE,
        ),
        monitor_data=MonitorData(
            measured_joint_position=tuple(q.tolist()),
            measured_torque=(0.0,) * N_JOINTS,
            commanded_joint_position=tuple(view.setpoint.tolist()) if v1 else None,
            timestamp=stamp,
            measured_cartesian_pose=pose,
            measured_redundancy=red,
            io=tuple(IOValue(name, IOType.BOOLEAN, IODirection.INPUT, int(v)) for name, v in view.inputs.items()),
        ),
        connection_info=ConnectionInfo(view.state, view.quality, view.send_period_ms, view.receive_multiplier),
        ipo_data=IpoData(
            joint_position=tuple(view.ipo.tolist()) if commanding else None,
            client_command_mode=ClientCommandMode.POSITION if commanding else ClientCommandMode.NO_COMMAND_MODE,
            overlay_type=OverlayType.JOINT if commanding else OverlayType.NO_OVERLAY,
            cartesian_pose=ipo_pose,
            redundancy=ipo_red,
        ),
    )
    body = msg.encode()
    if version == "2.7":
        return frame(body)  # no endOfMessageData; length and CRC-32 around the message
    # 1.x and 2.5 close with endOfMessageData; the SDK's decoder does not read it. We state
    # the length of what precedes it (unverified against a real controller).
    return FRIMonitoringMessage.encode(
        FRIMonitoringMessage(msg.header, msg.robot_info, msg.monitor_data, msg.connection_info,
                             msg.ipo_data, EndOfMessage(message_length=len(body)))
    )


def malformed_datagram(kind: str, good: bytes, version: str, seq: int, client_seq: int,
                       rng: np.random.Generator) -> bytes:
    """Bad bytes in place of the datagram ``good``: ``garbage`` (1–63 random bytes),
    ``truncated`` (its first half), ``wrong_id`` (a well-formed command message) or ``bad_crc``
    (an FRI 2.7 frame whose CRC-32 does not match its message)."""
    if kind == "bad_crc":
        bad = frame(unframe(good)[0])
        return bad[:-4] + bytes(b ^ 0xFF for b in bad[-4:])
    if kind == "garbage":
        return rng.integers(0, 256, size=int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    if kind == "truncated":
        return good[: max(1, len(good) // 2)]
    msg = FRIMonitoringMessage(header=MessageHeader(COMMAND_MESSAGE_ID, seq, client_seq))
    return frame(msg.encode()) if version == "2.7" else msg.encode()
