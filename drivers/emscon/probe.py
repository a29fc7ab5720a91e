"""emScon 6-DoF probes (a T-Mac, a T-Probe): which probe types measure orientation, and a
``ProbeStationaryResultT`` turned into a pose.

``dQuaternion0..3`` is scalar first; the header's SDK sample builds the probe's x, y, z axes in
tracker coordinates as the columns of its rotation matrix, so the quaternion is
``R_tracker←probe``. Rotation-angle std devs are in the angle unit set with ``SetUnits``.
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from drivers.emscon import codec as es
from drivers.errors import LimitError, ProtocolError

#: ``ES_ProbeType`` values that measure orientation.
SIX_DOF_PROBES = (es.ProbeType.TProbe, es.ProbeType.TScan, es.ProbeType.MachineControlProbe,
                  es.ProbeType.MachineControlProbeMultiSide)


def check_probe(info: Mapping, who: str) -> None:
    """Raise LimitError unless ``GetMeasurementProbeInfo``'s ``probeType`` is a 6-DoF probe."""
    kind = info["probeType"]
    if kind not in [int(k) for k in SIX_DOF_PROBES]:
        name = es.ProbeType(kind).name if kind in es.ProbeType._value2member_map_ else str(kind)
        raise LimitError(f"{who}: the tracker's active probe is {name}, not a 6-DoF probe "
                         f"({', '.join(k.name for k in SIX_DOF_PROBES)}); pose measurement needs one")


def probe_pose(v: Mapping, who: str, degrees_per_unit: float = 1.0):
    """(position (3,), its std (3,) in the length unit set, rotation (3, 3) ``R_tracker←probe``,
    attitude spread in degrees: the RMS over the axes of ``dStdDevRotationAngleX..Z``) of a
    ``ProbeStationaryResultT``'s values; ProtocolError for a quaternion that is not a unit one."""
    from calib.robot.transforms import quat_to_matrix

    xyz = np.array([v["dPosition1"], v["dPosition2"], v["dPosition3"]], dtype=float)
    std = np.array([v["dStdDevPosition1"], v["dStdDevPosition2"], v["dStdDevPosition3"]], dtype=float)
    q = np.array([v["dQuaternion0"], v["dQuaternion1"], v["dQuaternion2"], v["dQuaternion3"]], dtype=float)
    srot = np.array([v["dStdDevRotationAngleX"], v["dStdDevRotationAngleY"], v["dStdDevRotationAngleZ"]]) * degrees_per_unit
    norm = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else math.nan
    if not (abs(norm - 1.0) <= 1e-3 and np.all(np.isfinite(srot))):
        raise ProtocolError(f"{who}: the server sent a 6-DoF result with quaternion {q.tolist()} "
                            f"(norm {norm:.6f}, must be 1) and rotation std devs {srot.tolist()}")
    return xyz, std, quat_to_matrix(q / norm), float(np.sqrt(np.mean(srot ** 2)))
