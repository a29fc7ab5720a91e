"""Universal Robots' kinematics parameters file: the YAML that UR's ROS description reads.

``ur_description`` (UniversalRobots/Universal_Robots_ROS2_Description, ``urdf/ur_macro.xacro``
and ``urdf/inc/ur_common.xacro``; the ROS 1 description alike) takes its joint origins from the
file given as ``kinematics_parameters_file`` — the file UR's ``ur_calibration`` tool
(Universal_Robots_ROS_Driver / Universal_Robots_ROS2_Driver) writes from the controller's own
calibration::

    kinematics:
      shoulder:  {x, y, z, roll, pitch, yaw}     # metres, radians
      upper_arm: {...}
      forearm:   {...}
      wrist_1:   {...}
      wrist_2:   {...}
      wrist_3:   {...}
      hash: calib_…                              # the controller's calibration hash

How ur_description builds the chain from it (the facts this module relies on):

* ``base_link`` → ``base_link_inertia``: fixed, rpy (0, 0, π); ``base_link`` → ``base``: fixed,
  rpy (0, 0, π) — so ``base`` (the controller's Base frame) and ``base_link_inertia`` coincide;
* six revolute joints, ``shoulder_pan_joint`` … ``wrist_3_joint``, each with ``axis 0 0 1`` and
  ``<origin xyz="x y z" rpy="roll pitch yaw">`` from the entries above in that order (parent:
  the previous link), so the chain is ``Π origin_i · Rz(q_i)`` with q the controller's angles;
  URDF rpy means R = Rz(yaw)·Ry(pitch)·Rx(roll);
* ``wrist_3_link`` → ``flange``: rpy (0, −π/2, −π/2); ``flange`` → ``tool0``: rpy (π/2, π, π/2),
  i.e. ``tool0`` = ``wrist_3_link`` · Rz(π).

``ur_calibration`` splits each DH link into Rz(θ)Tz(d) and Tx(a)Rx(α) and writes
``origin_1 = Rz(θ1)Tz(d1)``, ``origin_i = Tx(a_{i−1})Rx(α_{i−1}) · Rz(θ_i)Tz(d_i)``; the sixth
link's Tx(a6)Rx(α6) is not in the file (``wrist_3_link`` is DH frame 6 up to it). We write the
same chain from a (calibrated) robot model: origin_1 = base · Rz(θ1)Tz(d1), origin_i =
Tx(a_{i−1})Rx(α_{i−1})Ry(β_{i−1}) · Rz(θ_i)Tz(d_i) (θ with the zero-offset folded in; Rz(θ)Tz(d)
commutes with the joint's own turn Rz(q)). What the file cannot hold — the sixth link's a, α, β and the model's flange frame — is the
``residual``: the model's flange = ``wrist_3_link`` · residual (identity for UR's own DH).

The rpy angles are written in the URDF convention, because that is how ur_description applies
them. (ur_calibration takes them from Eigen's ``eulerAngles(0, 1, 2)``, R = Rx·Ry·Rz, which equals
the URDF reading only where a frame turns about one axis or two that commute; ours are read back
through the URDF convention and checked.)
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.robot.transforms import homogeneous, invert, matrix_to_euler_zyx, rot_x, rot_y, rot_z

#: The file's link entries, in chain order (ur_description's joint origins).
UR_LINKS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
UR_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


class UrKinematicsError(ValueError):
    """A model that UR's kinematics file cannot describe, or a file that is not one."""


def _urdf_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF ``rpy``: R = Rz(yaw)·Ry(pitch)·Rx(roll), (3, 3)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def _fixed(xyz_m, rpy) -> np.ndarray:
    """A URDF fixed transform (4, 4) in mm from xyz (m) and rpy (rad)."""
    return homogeneous(_urdf_rpy(*rpy), np.asarray(xyz_m, dtype=float) * 1000.0)


#: ur_description's fixed frames (mm): base_link → base_link_inertia and → base; wrist_3_link → tool0.
BASE_LINK_TO_INERTIA = _fixed((0, 0, 0), (0, 0, math.pi))
BASE_LINK_TO_BASE = _fixed((0, 0, 0), (0, 0, math.pi))
WRIST3_TO_TOOL0 = _fixed((0, 0, 0), (0, -math.pi / 2, -math.pi / 2)) @ _fixed((0, 0, 0), (math.pi / 2, math.pi, math.pi / 2))


@dataclass(frozen=True)
class UrKinematics:
    """The six joint origins (6, 4, 4) mm, the residual (4, 4) mm with model flange =
    ``wrist_3_link`` · residual, and the hash written with them."""

    origins: np.ndarray
    residual: np.ndarray
    hash: str

    def to_dict(self) -> dict:
        """The file's ``kinematics`` mapping (metres, radians, URDF rpy)."""
        out: dict = {}
        for name, t in zip(UR_LINKS, self.origins):
            yaw, pitch, roll = matrix_to_euler_zyx(t[:3, :3]).tolist()
            x, y, z = (t[:3, 3] / 1000.0).tolist()
            out[name] = {k: float(v) + 0.0 for k, v in zip(_KEYS, (x, y, z, roll, pitch, yaw))}
        out["hash"] = self.hash
        return {"kinematics": out}


def _check_ur_like(model: RobotModel) -> None:
    if model.n_joints != 6:
        raise UrKinematicsError(f"{model.name}: UR's kinematics file describes six joints, the model has {model.n_joints}")
    flipped = [j.axis for j in model.joints if j.sign != 1]
    if flipped:
        raise UrKinematicsError(f"{model.name}: ur_description turns every joint about +z (axis 0 0 1); axes {', '.join(flipped)} "
                                "have sign -1 — export a URDF instead")


def ur_kinematics(model: RobotModel) -> UrKinematics:
    """The UR kinematics file's frames for ``model`` (its theta, d, a, α, β, base and flange; a
    calibrated model from ``calib.robot.calibrated``). ``UrKinematicsError`` unless six joints that
    all turn in the DH sense."""
    _check_ur_like(model)
    chain = Chain(model)
    p = chain.nominal
    n = 6
    d, a, al, be = p[n:2 * n], p[2 * n:3 * n], p[3 * n:4 * n], p[4 * n:5 * n]

    def turn(i: int) -> np.ndarray:  # Rz(θ_i + δ_i) Tz(d_i): commutes with the joint's own turn
        return homogeneous(rot_z(chain.theta0[i]), np.array([0.0, 0.0, d[i]]))

    def twist(i: int) -> np.ndarray:  # Tx(a_i) Rx(α_i) Ry(β_i)
        return homogeneous(rot_x(al[i]) @ rot_y(be[i]), np.array([a[i], 0.0, 0.0]))

    origins = [chain.base @ turn(0)] + [twist(i - 1) @ turn(i) for i in range(1, n)]
    residual = twist(n - 1) @ chain.flange
    origins = np.array(origins)
    digest = hashlib.sha256(np.round(origins, 9).tobytes()).hexdigest()[:16]
    return UrKinematics(origins, residual, f"remaster_{digest}")


def write_ur_kinematics(model: RobotModel, path: str | Path, header: str = "") -> UrKinematics:
    """Write ``model`` as UR's kinematics parameters YAML (``header`` as leading comments)."""
    import yaml  # noqa: PLC0415

    kin = ur_kinematics(model)
    lines = [f"# {line}".rstrip() for line in header.strip().splitlines()] if header.strip() else []
    body = yaml.safe_dump(kin.to_dict(), sort_keys=False, default_flow_style=False)
    Path(path).write_text("\n".join(lines + [body]), encoding="utf-8")
    return kin


@dataclass(frozen=True)
class UrChain:
    """A kinematics file read back and built as ur_description builds it: ``origins`` (6, 4, 4) mm."""

    origins: np.ndarray
    hash: str

    def wrist3(self, q: np.ndarray) -> np.ndarray:
        """``wrist_3_link`` in ur_description's ``base`` frame, (..., 4, 4) mm for q (..., 6) rad."""
        q = np.asarray(q, dtype=float)
        t = np.broadcast_to(BASE_LINK_TO_INERTIA, q.shape[:-1] + (4, 4))
        for i in range(6):
            t = t @ self.origins[i] @ homogeneous(rot_z(q[..., i]), np.zeros(3))
        return invert(BASE_LINK_TO_BASE) @ t

    def tool0(self, q: np.ndarray) -> np.ndarray:
        """``tool0`` in ``base``, (..., 4, 4) mm."""
        return self.wrist3(q) @ WRIST3_TO_TOOL0


def read_ur_kinematics(path: str | Path) -> UrChain:
    """Read a UR kinematics parameters file (ours or ur_calibration's); ``UrKinematicsError``
    naming the file and the entry when it is not one."""
    import yaml  # noqa: PLC0415

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise UrKinematicsError(f"{path}: cannot read as YAML: {exc}") from None
    kin = doc.get("kinematics") if isinstance(doc, dict) else None
    if not isinstance(kin, dict):
        raise UrKinematicsError(f"{path}: no 'kinematics' mapping (expected kinematics: {{shoulder: …, …, hash: …}})")
    origins = []
    for name in UR_LINKS:
        entry = kin.get(name)
        if not isinstance(entry, dict) or any(not isinstance(entry.get(k), (int, float)) for k in _KEYS):
            raise UrKinematicsError(f"{path}: kinematics.{name} must have numbers {', '.join(_KEYS)} (metres, radians)")
        origins.append(_fixed([entry[k] for k in "xyz"], [entry[k] for k in ("roll", "pitch", "yaw")]))
    return UrChain(np.array(origins), str(kin.get("hash", "")))

