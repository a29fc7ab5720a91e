"""FRI message classes built with Google's protobuf runtime from the field tables of KUKA's FRI
client SDK (the generated ``FRIMessages.pb.h`` / ``.pb.c`` of each version; public copies in the
lbr-stack/fri repository's per-version branches). An independent encoder/decoder for our codec.

``messages(version)`` returns ``(FRIMonitoringMessage, FRICommandMessage)`` classes for
``"1.15"`` (monitor data field 3 ``commandedJointPosition``, end-of-message), ``"2.5"`` (no field
3; Cartesian pose and redundancy fields, client command mode 4; end-of-message) or ``"2.7"``
(as 2.5 without ``endOfMessageData``).
"""

from __future__ import annotations

from functools import lru_cache

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

F = descriptor_pb2.FieldDescriptorProto
OPT, REQ, REP = F.LABEL_OPTIONAL, F.LABEL_REQUIRED, F.LABEL_REPEATED
U32, I32, DBL, STR, ENUM, MSG, U64 = (F.TYPE_UINT32, F.TYPE_INT32, F.TYPE_DOUBLE, F.TYPE_STRING,
                                     F.TYPE_ENUM, F.TYPE_MESSAGE, F.TYPE_UINT64)

ENUMS = {
    "FRISessionState": ["IDLE", "MONITORING_WAIT", "MONITORING_READY", "COMMANDING_WAIT", "COMMANDING_ACTIVE"],
    "FRIConnectionQuality": ["POOR", "FAIR", "GOOD", "EXCELLENT"],
    "SafetyState": ["NORMAL_OPERATION", "SAFETY_STOP_LEVEL_0", "SAFETY_STOP_LEVEL_1", "SAFETY_STOP_LEVEL_2"],
    "OperationMode": ["TEST_MODE_1", "TEST_MODE_2", "AUTOMATIC_MODE"],
    "DriveState": ["OFF", "TRANSITIONING", "ACTIVE"],
    "ControlMode": ["POSITION_CONTROLMODE", "CARTESIAN_IMPEDANCE_CONTROLMODE", "JOINT_IMPEDANCE_CONTROLMODE",
                    "NO_CONTROLMODE"],
    "OverlayType": ["NO_OVERLAY", "JOINT", "CARTESIAN"],
    "FriIOType": ["BOOLEAN", "DIGITAL", "ANALOG"],
    "FriIODirection": ["INPUT", "OUTPUT"],
}


def _fields(version: str) -> dict[str, list[tuple]]:
    """Message name -> [(field name, number, label, type, type name)] for one SDK version."""
    v2 = version.startswith("2.")
    monitor = [
        ("measuredJointPosition", 1, OPT, MSG, "JointValues"),
        ("measuredTorque", 2, OPT, MSG, "JointValues"),
        ("commandedTorque", 4, OPT, MSG, "JointValues"),
        ("externalTorque", 5, OPT, MSG, "JointValues"),
        ("readIORequest", 8, REP, MSG, "FriIOValue"),
        ("timestamp", 15, OPT, MSG, "TimeStamp"),
    ]
    ipo = [
        ("jointPosition", 1, OPT, MSG, "JointValues"),
        ("clientCommandMode", 10, OPT, ENUM, "ClientCommandMode"),
        ("overlayType", 11, OPT, ENUM, "OverlayType"),
        ("trackingPerformance", 12, OPT, DBL, None),
    ]
    command = [
        ("jointPosition", 1, OPT, MSG, "JointValues"),
        ("jointTorque", 3, OPT, MSG, "JointValues"),
    ]
    if v2:
        monitor += [("measuredCartesianPose", 9, OPT, MSG, "QuaternionTransformation"),
                    ("measuredRedundancyInformation", 10, OPT, MSG, "RedundancyInformation")]
        ipo += [("cartesianPose", 2, OPT, MSG, "QuaternionTransformation"),
                ("redundancyInformation", 3, OPT, MSG, "RedundancyInformation")]
        command += [("cartesianPose", 6, OPT, MSG, "QuaternionTransformation"),
                    ("redundancyInformation", 7, OPT, MSG, "RedundancyInformation")]
    else:
        monitor += [("commandedJointPosition", 3, OPT, MSG, "JointValues")]
    monitoring = [
        ("header", 1, REQ, MSG, "MessageHeader"),
        ("robotInfo", 2, OPT, MSG, "RobotInfo"),
        ("monitorData", 3, OPT, MSG, "MessageMonitorData"),
        ("connectionInfo", 4, OPT, MSG, "ConnectionInfo"),
        ("ipoData", 5, OPT, MSG, "MessageIpoData"),
    ]
    cmd_msg = [("header", 1, REQ, MSG, "MessageHeader"), ("commandData", 2, OPT, MSG, "MessageCommandData")]
    if version != "2.7":
        monitoring.append(("endOfMessageData", 15, OPT, MSG, "MessageEndOf"))
        cmd_msg.append(("endOfMessageData", 15, OPT, MSG, "MessageEndOf"))
    return {
        "JointValues": [("value", 1, REP, DBL, None)],
        "TimeStamp": [("sec", 1, REQ, U32, None), ("nanosec", 2, REQ, U32, None)],
        "Checksum": [("crc32", 1, OPT, I32, None)],
        "FriIOValue": [("name", 1, REQ, STR, None), ("type", 2, REQ, ENUM, "FriIOType"),
                       ("direction", 3, REQ, ENUM, "FriIODirection"), ("digitalValue", 4, OPT, U64, None),
                       ("analogValue", 5, OPT, DBL, None)],
        "QuaternionTransformation": [("name", 1, REQ, STR, None), ("element", 2, REP, DBL, None),
                                     ("timestamp", 3, OPT, MSG, "TimeStamp")],
        "RedundancyInformation": [("strategy", 1, REQ, ENUM, "RedundancyStrategy"), ("value", 2, REQ, DBL, None)],
        "MessageHeader": [("messageIdentifier", 1, REQ, U32, None), ("sequenceCounter", 2, REQ, U32, None),
                          ("reflectedSequenceCounter", 3, REQ, U32, None)],
        "ConnectionInfo": [("sessionState", 1, REQ, ENUM, "FRISessionState"),
                           ("quality", 2, REQ, ENUM, "FRIConnectionQuality"),
                           ("sendPeriod", 3, OPT, U32, None), ("receiveMultiplier", 4, OPT, U32, None)],
        "RobotInfo": [("numberOfJoints", 1, OPT, I32, None), ("safetyState", 2, OPT, ENUM, "SafetyState"),
                      ("driveState", 5, REP, ENUM, "DriveState"), ("operationMode", 6, OPT, ENUM, "OperationMode"),
                      ("controlMode", 7, OPT, ENUM, "ControlMode")],
        "MessageMonitorData": monitor,
        "MessageIpoData": ipo,
        "MessageCommandData": command,
        "MessageEndOf": [("messageLength", 1, OPT, I32, None), ("messageChecksum", 2, OPT, MSG, "Checksum")],
        "FRIMonitoringMessage": monitoring,
        "FRICommandMessage": cmd_msg,
    }


@lru_cache(maxsize=None)
def messages(version: str):
    """``(FRIMonitoringMessage, FRICommandMessage)`` protobuf classes of one SDK version."""
    if version not in ("1.15", "2.5", "2.7"):
        raise ValueError(f"version must be 1.15, 2.5 or 2.7, got {version!r}")
    pkg = "fri" + version.replace(".", "_")
    fd = descriptor_pb2.FileDescriptorProto(name=f"{pkg}.proto", package=pkg, syntax="proto2")
    enums = dict(ENUMS)
    v2 = version.startswith("2.")
    enums["ClientCommandMode"] = ["NO_COMMAND_MODE", "JOINT_POSITION", "WRENCH", "TORQUE"] + (
        ["CARTESIAN_POSE"] if v2 else [])
    for name, values in enums.items():
        e = fd.enum_type.add(name=name)
        for i, v in enumerate(values):
            e.value.add(name=f"{name}_{v}", number=i)
    e = fd.enum_type.add(name="RedundancyStrategy")
    e.value.add(name="RedundancyStrategy_E1", number=0)
    e.value.add(name="RedundancyStrategy_NONE", number=4)
    for mname, fields in _fields(version).items():
        m = fd.message_type.add(name=mname)
        for fname, number, label, ftype, tname in fields:
            f = m.field.add(name=fname, number=number, label=label, type=ftype)
            if tname is not None:
                f.type_name = f".{pkg}.{tname}"
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    get = message_factory.GetMessageClass
    return (get(pool.FindMessageTypeByName(f"{pkg}.FRIMonitoringMessage")),
            get(pool.FindMessageTypeByName(f"{pkg}.FRICommandMessage")))
