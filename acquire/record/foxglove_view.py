"""What Foxglove shows of a run: well-known Foxglove messages (JSON encoding) built from our data.

Channels (the same in the recorded MCAP and on the live WebSocket server; fixed names, so one
layout, ``fixtures/foxglove/remaster-layout.json``, fits every cell):

- ``/tf`` — ``foxglove.FrameTransforms``: ``base → link1 → … → linkN → flange`` from the measured
  joints through the robot model's kinematics (``calib.robot.kinematics.joint_frames``), and
  ``base → <sensor>`` for every sensor with a registration (the run's current estimate).
- ``/markers`` — ``foxglove.SceneUpdate``: each measured marker as a green sphere in its sensor's
  frame, and the model's nominal markers as grey spheres locked to ``flange`` — where the markers
  should be; the gap between the two is what the calibration removes.
- ``/joint_state`` — ``remaster.JointState``: names, positions in degrees *and* radians (plain
  number arrays: Foxglove's Plot panel plots ``/joint_state.position_deg[0]`` directly).
- ``/log`` — ``foxglove.Log``: run events and measured configurations, for the Log panel.
- ``/pose`` — ``foxglove.PoseInFrame``: each measured 6-DoF target's mean pose (position and
  orientation ``R_sensor←target``) in its sensor's frame, once per measured configuration; the
  same pose goes on ``/tf`` as the frame ``<sensor>/<marker>`` (parent ``<sensor>``), so the 3D
  panel draws its axes where the sensor saw the target.

Foxglove's units are metres and quaternions; ours are millimetres (converted here, nowhere
else). The JSON schemas below carry the names, fields and structure of Foxglove's published
JSON schemas (foxglove-sdk ``schemas/jsonschema``, FrameTransforms / SceneUpdate / Log), limited
to the fields we emit.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

import numpy as np

TF_TOPIC = "/tf"
SCENE_TOPIC = "/markers"
JOINT_STATE_TOPIC = "/joint_state"
LOG_TOPIC = "/log"
POSE_TOPIC = "/pose"
BASE_FRAME = "base"
FLANGE_FRAME = "flange"

# foxglove.LogLevel
DEBUG, INFO, WARNING, ERROR, FATAL = 1, 2, 3, 4, 5

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
TIME_SCHEMA = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
    "required": ["sec", "nsec"],
}


def _obj(title: str, props: dict, required: list[str] | None = None) -> dict:
    return {"title": title, "type": "object", "properties": props, "required": required if required is not None else list(props)}


_VEC3 = _obj("foxglove.Vector3", {"x": _NUM, "y": _NUM, "z": _NUM})
_QUAT = _obj("foxglove.Quaternion", {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM})
_COLOR = _obj("foxglove.Color", {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM})
_POSE = _obj("foxglove.Pose", {"position": _VEC3, "orientation": _QUAT})
_DURATION = {"type": "object", "title": "duration", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}

FRAME_TRANSFORMS_SCHEMA: dict = _obj(
    "foxglove.FrameTransforms",
    {
        "transforms": {
            "type": "array",
            "items": _obj(
                "foxglove.FrameTransform",
                {"timestamp": TIME_SCHEMA, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
                 "translation": _VEC3, "rotation": _QUAT},
            ),
        }
    },
)

SCENE_UPDATE_SCHEMA: dict = _obj(
    "foxglove.SceneUpdate",
    {
        "deletions": {"type": "array", "items": _obj("foxglove.SceneEntityDeletion", {"timestamp": TIME_SCHEMA, "type": {"type": "integer"}, "id": {"type": "string"}})},
        "entities": {
            "type": "array",
            "items": _obj(
                "foxglove.SceneEntity",
                {
                    "timestamp": TIME_SCHEMA,
                    "frame_id": {"type": "string"},
                    "id": {"type": "string"},
                    "lifetime": _DURATION,
                    "frame_locked": {"type": "boolean"},
                    "metadata": {"type": "array", "items": _obj("foxglove.KeyValuePair", {"key": {"type": "string"}, "value": {"type": "string"}})},
                    "spheres": {"type": "array", "items": _obj("foxglove.SpherePrimitive", {"pose": _POSE, "size": _VEC3, "color": _COLOR})},
                    **{name: {"type": "array"} for name in ("arrows", "cubes", "cylinders", "lines", "triangles", "texts", "models")},
                },
            ),
        },
    },
)

LOG_SCHEMA: dict = _obj(
    "foxglove.Log",
    {
        "timestamp": TIME_SCHEMA,
        "level": {"title": "foxglove.LogLevel", "oneOf": [{"title": t, "const": i} for i, t in
                                                            enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))]},
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
)

POSE_IN_FRAME_SCHEMA: dict = _obj(
    "foxglove.PoseInFrame", {"timestamp": TIME_SCHEMA, "frame_id": {"type": "string"}, "pose": _POSE})

JOINT_STATE_SCHEMA: dict = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "remaster.JointState",
    "description": "Measured joint positions of the run's commander, controller convention: degrees and radians "
    "(position_deg[i] and position_rad[i] belong to name[i]).",
    "type": "object",
    "properties": {
        "timestamp": TIME_SCHEMA,
        "device": {"type": "string", "description": "the commander's device name"},
        "name": {"type": "array", "items": {"type": "string"}},
        "position_deg": {"type": "array", "items": _NUM_OR_NULL},
        "position_rad": {"type": "array", "items": _NUM_OR_NULL},
        "device_time": _NUM_OR_NULL,
    },
    "required": ["timestamp", "device", "name", "position_deg", "position_rad"],
}

#: topic → (schema name, JSON schema) of the Foxglove channels.
CHANNELS: dict[str, tuple[str, dict]] = {
    TF_TOPIC: ("foxglove.FrameTransforms", FRAME_TRANSFORMS_SCHEMA),
    SCENE_TOPIC: ("foxglove.SceneUpdate", SCENE_UPDATE_SCHEMA),
    JOINT_STATE_TOPIC: ("remaster.JointState", JOINT_STATE_SCHEMA),
    LOG_TOPIC: ("foxglove.Log", LOG_SCHEMA),
    POSE_TOPIC: ("foxglove.PoseInFrame", POSE_IN_FRAME_SCHEMA),
}

_EMPTY_PRIMITIVES = ("arrows", "cubes", "cylinders", "lines", "triangles", "texts", "models")
MEASURED_RGBA = (0.1, 0.8, 0.2, 1.0)
NOMINAL_RGBA = (0.6, 0.6, 0.6, 0.6)


def stamp(t_ns: int) -> dict:
    """Foxglove time {sec, nsec} of a unix time in ns."""
    return {"sec": int(t_ns // 1_000_000_000), "nsec": int(t_ns % 1_000_000_000)}


def quaternions(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (x, y, z, w), w ≥ 0, of rotation matrices (..., 3, 3).

    Shepperd's method: each matrix uses the best-conditioned of the four formulas (largest of
    trace, r00, r11, r22), so rotations near 180° are as exact as small ones.
    """
    r = np.asarray(r, dtype=float)
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = r00 + r11 + r22
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s01, s02, s12 = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    pick = np.argmax(np.stack([tr, r00, r11, r22], -1), -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cand = np.stack([
            np.stack([d21, d02, d10, 1 + tr], -1),
            np.stack([1 + r00 - r11 - r22, s01, s02, d21], -1),
            np.stack([s01, 1 - r00 + r11 - r22, s12, d02], -1),
            np.stack([s02, s12, 1 - r00 - r11 + r22, d10], -1),
        ], -2)  # (..., 4 formulas, 4): each proportional to the quaternion
    q = np.take_along_axis(cand, pick[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w ≥ 0, of one (3, 3) rotation matrix (see :func:`quaternions`)."""
    x, y, z, w = quaternions(r).tolist()
    return x, y, z, w


def frame_transform(parent: str, child: str, parent2child_mm: np.ndarray, t_ns: int) -> dict:
    """One ``foxglove.FrameTransform``: the pose (4, 4), mm, of ``child`` in ``parent`` (metres out)."""
    t = np.asarray(parent2child_mm, dtype=float)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ValueError(f"transform {parent} → {child} must be a finite (4, 4) matrix, given shape {t.shape}")
    x, y, z, w = quaternion(t[:3, :3])
    return {
        "timestamp": stamp(t_ns),
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": {"x": float(t[0, 3]) / 1000.0, "y": float(t[1, 3]) / 1000.0, "z": float(t[2, 3]) / 1000.0},
        "rotation": {"x": x, "y": y, "z": z, "w": w},
    }


def _sphere_entity(frame: str, eid: str, xyz_m: Iterable[float], t_ns: int, *, diameter_m: float, rgba, lifetime_s: float,
                   frame_locked: bool, meta: dict[str, str]) -> dict:
    x, y, z = (float(v) for v in xyz_m)
    d = float(diameter_m)
    r, g, b, a = rgba
    return {
        "timestamp": stamp(t_ns),
        "frame_id": frame,
        "id": eid,
        "lifetime": {"sec": int(lifetime_s), "nsec": int(round((lifetime_s % 1) * 1e9))},
        "frame_locked": frame_locked,
        "metadata": [{"key": k, "value": str(v)} for k, v in meta.items()],
        "spheres": [{"pose": {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                     "size": {"x": d, "y": d, "z": d}, "color": {"r": r, "g": g, "b": b, "a": a}}],
        **{k: [] for k in _EMPTY_PRIMITIVES},
    }


def scene_update(sensor: str, positions_mm: dict[str, Any], t_ns: int, *, diameter_mm: float = 15.0, lifetime_s: float = 0.5) -> dict:
    """A ``foxglove.SceneUpdate`` with one sphere entity per seen marker (metres, frame ``sensor``).

    positions_mm: marker name → xyz (3,) mm in the sensor frame, or None when not seen (no entity;
    its previous sphere expires after ``lifetime_s``). Entity ids are ``<sensor>/<marker>``.
    """
    entities = []
    for name, xyz in positions_mm.items():
        if xyz is None:
            continue
        p = np.asarray(xyz, dtype=float).reshape(3) / 1000.0
        if not np.all(np.isfinite(p)):
            continue
        entities.append(_sphere_entity(sensor, f"{sensor}/{name}", p, t_ns, diameter_m=diameter_mm / 1000.0, rgba=MEASURED_RGBA,
                                       lifetime_s=lifetime_s, frame_locked=False, meta={"marker": str(name), "sensor": sensor}))
    return {"deletions": [], "entities": entities}


def nominal_markers_scene(marker_xyz_mm: dict[str, Any], t_ns: int, *, diameter_mm: float = 15.0) -> dict:
    """The model's markers (flange frame, mm) as grey spheres locked to the ``flange`` frame (no expiry)."""
    entities = [
        _sphere_entity(FLANGE_FRAME, f"nominal/{name}", np.asarray(xyz, dtype=float).reshape(3) / 1000.0, t_ns,
                       diameter_m=diameter_mm / 1000.0, rgba=NOMINAL_RGBA, lifetime_s=0.0, frame_locked=True,
                       meta={"marker": str(name), "source": "robot model"})
        for name, xyz in marker_xyz_mm.items()
    ]
    return {"deletions": [], "entities": entities}


def measured_poses(sample: dict, t_ns: int) -> list[tuple[dict, dict]]:
    """The 6-DoF targets of a measured configuration (a ``/run/sample`` record: markers with
    ``quat_wxyz``, scalar first, ``R_sensor←target``, and ``mean_mm``) as Foxglove messages: one
    (``foxglove.PoseInFrame`` in the sensor's frame, ``foxglove.FrameTransforms`` with the frame
    ``<sensor>/<marker>``) pair per target, metres; none for point targets."""
    out = []
    for m in sample.get("markers") or []:
        quat, mean = m.get("quat_wxyz"), m.get("mean_mm")
        if not (isinstance(quat, (list, tuple)) and len(quat) == 4 and isinstance(mean, (list, tuple)) and len(mean) == 3):
            continue
        w, x, y, z = (float(v) for v in quat)
        p = np.asarray([float("nan") if v is None else v for v in mean], dtype=float) / 1000.0
        if not (np.all(np.isfinite(p)) and all(math.isfinite(v) for v in (w, x, y, z))):
            continue
        sensor, marker = str(m.get("sensor", "sensor")), str(m.get("marker", "marker"))
        position = {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}
        orientation = {"x": x, "y": y, "z": z, "w": w}
        pose = {"timestamp": stamp(t_ns), "frame_id": sensor, "pose": {"position": position, "orientation": orientation}}
        tf = {"transforms": [{"timestamp": stamp(t_ns), "parent_frame_id": sensor, "child_frame_id": f"{sensor}/{marker}",
                              "translation": position, "rotation": orientation}]}
        out.append((pose, tf))
    return out


def log_message(level: int, message: str, t_ns: int, *, name: str = "remaster") -> dict:
    """A ``foxglove.Log`` record (level: DEBUG … FATAL of this module)."""
    return {"timestamp": stamp(t_ns), "level": int(level), "message": str(message), "name": name, "file": "", "line": 0}


_WARN_KINDS = ("suspended", "beam_lost", "lost", "skipped", "retry", "controller_restarted", "log_resumed")
_ERROR_KINDS = ("failed", "aborted", "run_failed")


def event_log(event: dict, t_ns: int) -> dict:
    """A run event ``{"kind", "t", …}`` as a ``foxglove.Log`` line: WARNING for suspensions and
    skips, ERROR for failures, INFO otherwise; the message lists the event's fields."""
    kind = str(event.get("kind", "event"))
    level = ERROR if any(k in kind for k in _ERROR_KINDS) else WARNING if any(k in kind for k in _WARN_KINDS) else INFO
    fields = " ".join(f"{k}={_short(v)}" for k, v in event.items() if k not in ("kind", "t"))
    return log_message(level, f"{kind} {fields}".strip(), t_ns, name="run")


def sample_log(sample: dict, t_ns: int) -> dict:
    """A measured configuration as one INFO line: config id and each marker's position (mm)."""
    parts = []
    for m in sample.get("markers") or []:
        mean = m.get("mean_mm")
        where = "not seen" if mean is None else "[" + ", ".join("nan" if v is None else f"{float(v):.2f}" for v in mean) + "] mm"
        parts.append(f"{m.get('sensor', '?')}/{m.get('marker', '?')} {where}")
    return log_message(INFO, f"measured {sample.get('config_id')}: " + ("; ".join(parts) or "no markers"), t_ns, name="run")


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)) and len(v) > 6:
        return f"[{len(v)} items]"
    return str(v)


def joint_state(device: str, names: list[str], q_rad: np.ndarray, t_ns: int, device_time: float | None = None) -> dict:
    """A ``remaster.JointState``: q (n,) radians → degrees rounded to 1e-6° and radians to 1e-8."""
    q = np.asarray(q_rad, dtype=float).reshape(-1)
    if len(names) != q.size:
        raise ValueError(f"joint state of {device}: {len(names)} names for {q.size} positions")
    return {"timestamp": stamp(t_ns), "device": device, "name": list(names), "position_deg": np.round(np.degrees(q), 6),
            "position_rad": np.round(q, 8), "device_time": device_time}


class RobotView:
    """Frame transforms of one robot model: ``base → link1 … linkN → flange`` and ``base → sensor``.

    chain: ``calib.robot.kinematics.Chain`` (nominal model). Registrations are (4, 4) ``base2sensor``
    matrices, mm (p_sensor = base2sensor · p_base), as the run estimates them; set them with
    :meth:`set_registration`. Registrations may be set while another thread calls :meth:`transforms`.
    """

    def __init__(self, chain) -> None:
        self.chain = chain
        self.link_frames = [f"link{i + 1}" for i in range(chain.n)]
        self._registration: dict[str, np.ndarray] = {}

    def set_registration(self, sensor: str, base2sensor_mm: np.ndarray | None) -> None:
        """Set (or, with None, drop) the ``base → sensor`` transform of ``sensor``."""
        reg = dict(self._registration)  # copy on write: ``transforms`` may run on another thread
        if base2sensor_mm is None:
            reg.pop(sensor, None)
        else:
            t = np.asarray(base2sensor_mm, dtype=float)
            if t.shape != (4, 4) or not np.all(np.isfinite(t)):
                raise ValueError(f"registration of {sensor} must be a finite (4, 4) matrix, given shape {t.shape}")
            reg[sensor] = t.copy()
        self._registration = reg

    def transforms(self, q_rad: np.ndarray, t_ns: int) -> dict:
        """``foxglove.FrameTransforms`` for joint angles q (n,) rad (controller convention).

        Numbers are rounded to 1e-7 m (0.1 µm) and 1e-10 per quaternion component (< 1e-6 mm
        at 2 m): far below any sensor's resolution, and half the bytes of full float reprs.
        """
        from calib.robot.kinematics import joint_frames

        q = np.asarray(q_rad, dtype=float).reshape(-1)
        if q.size != self.chain.n or not np.all(np.isfinite(q)):
            raise ValueError(f"need {self.chain.n} finite joint angles, given {q.size}: {q.tolist()}")
        frames = joint_frames(self.chain, q)  # (n+1, 4, 4) in the base frame: DH frame 0 (the model's base), links 1..n
        # Each link relative to its parent: link1 in base, link i in link i-1 (rigid inverse: Rᵀ, −Rᵀp);
        # then the flange in link n, and each sensor in base (the inverse of base2sensor).
        parent = np.concatenate([np.eye(4)[None], frames[1:-1]])
        rt = np.swapaxes(parent[:, :3, :3], -1, -2)
        rot = [rt @ frames[1:, :3, :3], self.chain.flange[None, :3, :3]]
        pos = [np.einsum("nij,nj->ni", rt, frames[1:, :3, 3] - parent[:, :3, 3]), self.chain.flange[None, :3, 3]]
        names = [BASE_FRAME, *self.link_frames]
        pairs = [(names[i], names[i + 1]) for i in range(self.chain.n)] + [(names[-1], FLANGE_FRAME)]
        for sensor, b2s in sorted(self._registration.items()):  # a snapshot: set_registration replaces the dict
            r_t = b2s[:3, :3].T
            rot.append(r_t[None])
            pos.append((-r_t @ b2s[:3, 3])[None])
            pairs.append((BASE_FRAME, sensor))
        quats = np.round(quaternions(np.concatenate(rot)), 10).tolist()
        trans = np.round(np.concatenate(pos) / 1000.0, 7).tolist()
        st = stamp(t_ns)
        return {"transforms": [
            {"timestamp": st, "parent_frame_id": parent_id, "child_frame_id": child_id,
             "translation": {"x": p[0], "y": p[1], "z": p[2]}, "rotation": {"x": qq[0], "y": qq[1], "z": qq[2], "w": qq[3]}}
            for (parent_id, child_id), p, qq in zip(pairs, trans, quats)
        ]}
