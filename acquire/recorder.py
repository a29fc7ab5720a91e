"""The run log: one MCAP file per run, crash-safe and resumable.

What is in the file (readable by ``mcap`` tooling and Foxglove):

- Every stream is a channel with message encoding ``json`` and a schema with encoding
  ``jsonschema``. Standard channels: ``/run/sample`` (``remaster.Sample``, one record per measured
  configuration), ``/run/event`` (``remaster.RunEvent``: moved, settled, suspended, resumed,
  skipped, …). Streams recorded with :meth:`RunLog.record_joint_state` go to
  ``/<device>/joint_state`` (``remaster.JointState``, degrees); :meth:`RunLog.record_markers`
  writes ``/<sensor>/markers`` (``remaster.MarkerFrame``, mm, sensor frame, every frame) and, for
  Foxglove's 3D panel, ``/<sensor>/markers/scene`` (``foxglove.SceneUpdate``: one sphere entity per
  marker, metres, frame id = the sensor name, at most ``scene_rate_hz``, default 30 Hz).
- Metadata records ``remaster.run`` (format, run id, segment number, creation time),
  ``remaster.run.metadata`` (the caller's metadata, each value JSON-encoded), ``remaster.plan``
  and ``remaster.robot_model`` (the exact texts), and the same two texts as attachments
  ``plan.yaml`` and ``robot.yaml``.

Crash safety: the file is written without chunks and without compression, record by record, so
no record waits in memory for a chunk to fill. ``sample`` and ``event`` return only after
``flush`` + ``os.fsync`` (with everything written before them); a stream write flushes to the OS
when the last flush is older than ``flush_interval_s`` (a ``kill -9`` keeps what reached the OS;
a power cut keeps what was fsync'd). :func:`read_run` reads records one by one and stops at the first one that is
incomplete or unreadable, so a truncated file yields exactly the records that were completely
written — never a partial one (``mcap``'s own readers would hand a cut record's bytes on, or
raise). The price of no chunks is a larger, unindexed file: tools read it linearly (``mcap`` and
Foxglove both do). JSON encoding: :mod:`acquire.jsonpayload` (NaN/inf → null).

Resume: :meth:`RunLog.append_to` never rewrites recorded data. It closes the killed file (cuts
the incomplete tail record, if any, and appends a DataEnd + Footer so the file is valid MCAP
again), then continues in a new segment beside it: ``RUN.mcap`` → ``RUN.resume1.mcap`` →
``RUN.resume2.mcap`` …; each segment is a complete MCAP file with the run's metadata and its
segment number. :func:`read_run` given any segment reads them all in order and returns the union.
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import logging
import math
import os
import re
import struct
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    Metadata,
    Message,
    Schema,
)
from mcap.stream_reader import MAGIC_SIZE, CRCValidationError, breakup_chunk
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from acquire.jsonpayload import PayloadError, decode_json, encode_json

log = logging.getLogger(__name__)

FORMAT = "remaster-run/1"
SAMPLE_TOPIC = "/run/sample"
EVENT_TOPIC = "/run/event"
MCAP_MAGIC = b"\x89MCAP0\r\n"
_SEGMENT_RE = re.compile(r"^(?P<stem>.+?)\.resume(?P<n>[1-9][0-9]*)\.mcap$")
_EVENT_KIND_RE = re.compile(r"^[a-z][a-z0-9_\-]*$")
_TOPIC_PART_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")


class RunLogError(ValueError):
    """A run log that cannot be created, read or resumed; the message names the file."""


# --------------------------------------------------------------------------------------------
# JSON schemas of the channels
# --------------------------------------------------------------------------------------------
_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
    "required": ["sec", "nsec"],
}

SAMPLE_SCHEMA: dict = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "remaster.Sample",
    "description": "One measured configuration: joint angles as the controller measured them and, per sensor and "
    "marker, the mean/std/count of the marker position in the sensor frame.",
    "type": "object",
    "properties": {
        "config_id": {"type": "string", "minLength": 1, "description": "stable configuration id, unique in the run"},
        "pose": {"type": "string", "description": "pose group id"},
        "branch": {"type": "string", "description": "IK branch label"},
        "q_target_deg": {"type": "array", "items": _NUM, "description": "commanded joint angles, degrees"},
        "q_measured_deg": {"type": "array", "items": _NUM, "description": "measured joint angles (mean), degrees"},
        "q_measured_std_deg": {"type": "array", "items": _NUM_OR_NULL, "description": "their std, degrees"},
        "markers": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "sensor": {"type": "string"},
                    "marker": {"type": "string", "description": "marker name of the robot model's tool"},
                    "mean_mm": {"type": ["array", "null"], "items": _NUM_OR_NULL, "minItems": 3, "maxItems": 3},
                    "std_mm": {"type": ["array", "null"], "items": _NUM_OR_NULL, "minItems": 3, "maxItems": 3},
                    "count": {"type": "integer", "minimum": 0},
                    "device_time": _NUM_OR_NULL,
                    "host_time": _NUM_OR_NULL,
                },
                "required": ["sensor", "marker", "mean_mm"],
            },
        },
        "socket": {
            "type": "object",
            "description": "socket calibration only: the joint sensor's record (markers is then empty)",
            "properties": {
                "sensor": {"type": "string"},
                "placement": {"type": "string"},
                "socket": {"type": "string"},
                "trigger": {"type": "string", "enum": ["still", "confirm"],
                            "description": "guided then held still for the window, or the operator's confirmation"},
                "count": {"type": "integer", "minimum": 1},
                "device_time": _NUM_OR_NULL,
            },
            "required": ["placement", "socket", "trigger"],
        },
        "t_start": {"type": "number", "description": "host time, unix seconds"},
        "t_end": {"type": "number", "description": "host time, unix seconds"},
        "attempts": {"type": "integer", "minimum": 0},
    },
    "required": ["config_id", "q_measured_deg", "markers"],
}

EVENT_SCHEMA: dict = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "remaster.RunEvent",
    "description": "A run event: kind (moved, settled, suspended, resumed, skipped, …), host time t (unix s), "
    "and fields that depend on the kind.",
    "type": "object",
    "properties": {"kind": {"type": "string"}, "t": _NUM},
    "required": ["kind", "t"],
    "additionalProperties": True,
}

JOINT_STATE_SCHEMA: dict = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "remaster.JointState",
    "description": "Measured joint positions of a commander, degrees (controller convention).",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "name": {"type": "array", "items": {"type": "string"}},
        "position_deg": {"type": "array", "items": _NUM_OR_NULL},
        "device_time": _NUM_OR_NULL,
    },
    "required": ["timestamp", "name", "position_deg"],
}

MARKER_FRAME_SCHEMA: dict = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "remaster.MarkerFrame",
    "description": "Marker positions seen by one sensor in one frame, mm in the sensor frame (null = not seen).",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "device_time": _NUM_OR_NULL,
        "markers": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "position_mm": {"type": ["array", "null"], "items": _NUM, "minItems": 3, "maxItems": 3},
                    "quality": _NUM_OR_NULL,
                },
                "required": ["name", "position_mm"],
            },
        },
    },
    "required": ["timestamp", "frame_id", "markers"],
}


def _obj(title: str, props: dict, required: list[str] | None = None) -> dict:
    return {"title": title, "type": "object", "properties": props, "required": required if required is not None else list(props)}


_VEC3 = _obj("foxglove.Vector3", {"x": _NUM, "y": _NUM, "z": _NUM})
_QUAT = _obj("foxglove.Quaternion", {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM})
_COLOR = _obj("foxglove.Color", {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM})
_POSE = _obj("foxglove.Pose", {"position": _VEC3, "orientation": _QUAT})
_DURATION = {"type": "object", "title": "duration", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}

#: The part of Foxglove's ``foxglove.SceneUpdate`` JSON schema that we emit (same field names and
#: structure as foxglove/schemas ``SceneUpdate.json``; other primitive lists are always empty).
SCENE_UPDATE_SCHEMA: dict = _obj(
    "foxglove.SceneUpdate",
    {
        "deletions": {"type": "array", "items": _obj("foxglove.SceneEntityDeletion", {"timestamp": _TIME, "type": {"type": "integer"}, "id": {"type": "string"}})},
        "entities": {
            "type": "array",
            "items": _obj(
                "foxglove.SceneEntity",
                {
                    "timestamp": _TIME,
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


def _stamp(t_ns: int) -> dict:
    return {"sec": int(t_ns // 1_000_000_000), "nsec": int(t_ns % 1_000_000_000)}


def scene_update(sensor: str, positions_mm: dict[str, Any], t_ns: int, *, diameter_mm: float = 15.0, lifetime_s: float = 0.5) -> dict:
    """A ``foxglove.SceneUpdate`` with one sphere entity per seen marker (metres, frame ``sensor``).

    positions_mm: marker name → xyz (3,) mm in the sensor frame, or None when not seen (no entity;
    its previous sphere expires after ``lifetime_s``).
    """
    d = diameter_mm / 1000.0
    entities = []
    for name, xyz in positions_mm.items():
        if xyz is None:
            continue
        x, y, z = (float(v) / 1000.0 for v in np.asarray(xyz, dtype=float).reshape(3))
        if not all(math.isfinite(v) for v in (x, y, z)):
            continue
        entities.append(
            {
                "timestamp": _stamp(t_ns),
                "frame_id": sensor,
                "id": f"{sensor}/{name}",
                "lifetime": {"sec": int(lifetime_s), "nsec": int(round((lifetime_s % 1) * 1e9))},
                "frame_locked": False,
                "metadata": [{"key": "marker", "value": str(name)}],
                "spheres": [
                    {
                        "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                        "size": {"x": d, "y": d, "z": d},
                        "color": {"r": 0.1, "g": 0.8, "b": 0.2, "a": 1.0},
                    }
                ],
                **{k: [] for k in ("arrows", "cubes", "cylinders", "lines", "triangles", "texts", "models")},
            }
        )
    return {"deletions": [], "entities": entities}


# --------------------------------------------------------------------------------------------
# Segments on disk
# --------------------------------------------------------------------------------------------
def base_path(path: str | Path) -> Path:
    """The first segment of the run that ``path`` belongs to (``RUN.resume2.mcap`` → ``RUN.mcap``)."""
    p = Path(path)
    m = _SEGMENT_RE.match(p.name)
    return p.with_name(m.group("stem") + ".mcap") if m else p


def segment_path(base: Path, n: int) -> Path:
    """Segment ``n`` of the run whose first file is ``base`` (0 → base itself)."""
    if n == 0:
        return base
    stem = base.name[: -len(".mcap")] if base.name.endswith(".mcap") else base.name
    return base.with_name(f"{stem}.resume{n}.mcap")


def segment_paths(path: str | Path) -> list[Path]:
    """The existing segments of the run, in order: the first file, then resume1, resume2, …

    Stops at the first missing number, so a stray ``resume5`` after a gap is not read.
    """
    base = base_path(path)
    out = [base]
    n = 1
    while segment_path(base, n).exists():
        out.append(segment_path(base, n))
        n += 1
    return out


def _json_text(value: Any) -> str:
    """One JSON value as text, with the conventions of acquire.jsonpayload (numpy, NaN → null)."""
    return json.dumps(json.loads(encode_json({"v": value}))["v"], separators=(",", ":"))


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(str(path), os.O_RDONLY)
    except OSError as exc:  # some filesystems do not allow opening directories
        log.debug("cannot open %s to fsync it: %s", path, exc)
        return
    try:
        os.fsync(fd)
    except OSError as exc:
        log.debug("fsync of directory %s failed: %s", path, exc)
    finally:
        os.close(fd)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------
class RunLog:
    """The MCAP log of one run (one segment file). Thread-safe. Use ``create`` or ``append_to``.

    ``recovered`` holds what earlier segments contain (``append_to``) or an empty record set.
    """

    def __init__(self, path: Path, fh: io.BufferedWriter, run_id: str, segment: int, *, flush_interval_s: float, fsync: bool,
                 scene_rate_hz: float = 30.0):
        self.path = path
        self.run_id = run_id
        self.segment = segment
        self._fh = fh
        self._writer = Writer(fh, use_chunking=False, compression=CompressionType.NONE)
        self._lock = threading.RLock()
        self._channels: dict[str, tuple[int, str, bytes]] = {}
        self._schemas: dict[tuple[str, bytes], int] = {}
        self._sequence: dict[int, int] = {}
        self._flush_interval_s = float(flush_interval_s)
        self._fsync = fsync
        self._last_flush = time.monotonic()
        self._closed = False
        self._scene_rate_hz = float(scene_rate_hz)
        self._next_scene_ns: dict[str, float] = {}
        self.samples_written = 0
        self.events_written = 0
        self.recovered: RunContents | None = None

    # -- opening ------------------------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: Path,
        *,
        run_id: str,
        plan_text: str,
        model_text: str,
        metadata: dict,
        flush_interval_s: float = 0.05,
        fsync: bool = True,
        scene_rate_hz: float = 30.0,
    ) -> "RunLog":
        """Start a new run log at ``path`` (must not exist; parent folders are created).

        metadata: JSON-able values (stored JSON-encoded in ``remaster.run.metadata``).
        flush_interval_s: how long stream records may wait in the process before reaching the OS.
        fsync: False only for benchmarks — samples and events are then flushed but not fsync'd.
        scene_rate_hz: at most this many Foxglove scene updates per second and sensor (0: none);
        the mm marker frames are always all recorded.
        """
        return cls._open(Path(path), run_id=run_id, plan_text=plan_text, model_text=model_text, metadata=metadata,
                         segment=0, extra={}, flush_interval_s=flush_interval_s, fsync=fsync, scene_rate_hz=scene_rate_hz)

    @classmethod
    def _open(cls, path: Path, *, run_id: str, plan_text: str, model_text: str, metadata: dict, segment: int,
              extra: dict[str, str], flush_interval_s: float, fsync: bool, scene_rate_hz: float = 30.0) -> "RunLog":
        if not isinstance(run_id, str) or not run_id.strip():
            raise RunLogError(f"{path}: run_id must be a non-empty string, given {run_id!r}")
        if not isinstance(metadata, dict):
            raise RunLogError(f"{path}: metadata must be a dict, given {type(metadata).__name__}")
        if flush_interval_s < 0:
            raise RunLogError(f"{path}: flush_interval_s must be >= 0, given {flush_interval_s}")
        if scene_rate_hz < 0:
            raise RunLogError(f"{path}: scene_rate_hz must be >= 0, given {scene_rate_hz}")
        try:
            meta_json = {str(k): _json_text(v) for k, v in metadata.items()}
        except PayloadError as exc:
            raise RunLogError(f"{path}: metadata is not JSON-able: {exc}") from exc
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fh = open(path, "xb")
        except FileExistsError:
            raise RunLogError(f"{path}: exists already; a run log is never overwritten (resume it with append_to)") from None
        except OSError as exc:
            raise RunLogError(f"{path}: cannot create the run log: {exc.strerror or exc}") from exc
        self = cls(path, fh, run_id, segment, flush_interval_s=flush_interval_s, fsync=fsync, scene_rate_hz=scene_rate_hz)
        now_ns = time.time_ns()
        with self._lock:
            self._writer.start(profile="", library="remaster")
            run_meta = {
                "format": FORMAT,
                "run_id": run_id,
                "segment": str(segment),
                "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
                **extra,
            }
            self._writer.add_metadata("remaster.run", run_meta)
            self._writer.add_metadata("remaster.run.metadata", meta_json)
            self._writer.add_metadata("remaster.plan", {"text": plan_text})
            self._writer.add_metadata("remaster.robot_model", {"text": model_text})
            self._writer.add_attachment(now_ns, now_ns, "plan.yaml", "application/yaml", plan_text.encode("utf-8"))
            self._writer.add_attachment(now_ns, now_ns, "robot.yaml", "application/yaml", model_text.encode("utf-8"))
            self.channel(SAMPLE_TOPIC, "remaster.Sample", SAMPLE_SCHEMA)
            self.channel(EVENT_TOPIC, "remaster.RunEvent", EVENT_SCHEMA)
            self._durable()
        _fsync_dir(path.parent)
        log.info("run %s: logging to %s (segment %d)", run_id, path, segment)
        return self

    @classmethod
    def append_to(cls, path: Path, *, flush_interval_s: float = 0.05, fsync: bool = True, scene_rate_hz: float = 30.0) -> "RunLog":
        """Resume the run logged at ``path`` (any of its segments) in a new segment file.

        Recovers every complete record of the existing segments (``self.recovered``), makes each
        killed segment valid MCAP again (cuts only its incomplete tail record), and opens
        ``<stem>.resume<N>.mcap`` with the same run id, plan, model and metadata. Nothing recorded
        is rewritten or copied, so nothing is lost or duplicated; ``read_run`` returns the union.
        """
        contents = read_run(path)
        if not contents.run_id:
            raise RunLogError(f"{contents.files[0]}: holds no run metadata (killed while being created); nothing to resume — start a new run")
        for seg in contents.segments:
            if not seg.complete:
                _close_truncated(seg)
        base = contents.files[0]
        new_path = segment_path(base, len(contents.files))
        self = cls._open(
            new_path,
            run_id=contents.run_id,
            plan_text=contents.plan_text,
            model_text=contents.model_text,
            metadata=contents.metadata,
            segment=len(contents.files),
            extra={"resumed_from": base.name, "recovered_samples": str(len(contents.samples))},
            flush_interval_s=flush_interval_s,
            fsync=fsync,
            scene_rate_hz=scene_rate_hz,
        )
        self.recovered = contents
        self.event(
            "log_resumed",
            segment=self.segment,
            previous_files=[p.name for p in contents.files],
            recovered_samples=len(contents.samples),
            recovered_events=len(contents.events),
            dropped_bytes=contents.dropped_bytes,
        )
        return self

    # -- writing ------------------------------------------------------------------------------
    def channel(self, topic: str, schema_name: str, json_schema: dict) -> int:
        """Register (or look up) the channel ``topic`` with a JSON schema; return its id.

        Registering a topic again with the same schema returns the same id; with a different
        schema it is an error.
        """
        if not isinstance(topic, str) or not topic.startswith("/") or not all(_TOPIC_PART_RE.match(p) for p in topic[1:].split("/")):
            raise RunLogError(f"{self.path}: topic must look like /device/stream (chunks of [A-Za-z0-9_.-]), given {topic!r}")
        if not isinstance(json_schema, dict):
            raise RunLogError(f"{self.path}: json_schema of {topic} must be a dict, given {type(json_schema).__name__}")
        data = json.dumps(json_schema, sort_keys=True, separators=(",", ":")).encode("utf-8")
        with self._lock:
            self._check_open()
            known = self._channels.get(topic)
            if known is not None:
                if known[1:] != (schema_name, data):
                    raise RunLogError(f"{self.path}: topic {topic} is registered with schema {known[1]!r} already; a topic has one schema")
                return known[0]
            schema_id = self._schemas.get((schema_name, data))
            if schema_id is None:
                schema_id = self._writer.register_schema(schema_name, SchemaEncoding.JSONSchema, data)
                self._schemas[(schema_name, data)] = schema_id
            channel_id = self._writer.register_channel(topic, MessageEncoding.JSON, schema_id)
            self._channels[topic] = (channel_id, schema_name, data)
            self._sequence[channel_id] = 0
            return channel_id

    def write(self, topic: str, message: dict, *, log_time_ns: int | None = None) -> None:
        """Append one JSON message to a registered channel (reaches the OS within flush_interval_s)."""
        data = encode_json(message)
        t = time.time_ns() if log_time_ns is None else int(log_time_ns)
        with self._lock:
            self._append(topic, data, t)
            if time.monotonic() - self._last_flush >= self._flush_interval_s:
                self._fh.flush()
                self._last_flush = time.monotonic()

    def sample(self, record: dict) -> None:
        """Record one measured configuration (see SAMPLE_SCHEMA); returns once it is on disk."""
        if not isinstance(record, dict):
            raise RunLogError(f"{self.path}: a sample must be a dict, given {type(record).__name__}")
        missing = [k for k in SAMPLE_SCHEMA["required"] if k not in record]
        if missing:
            raise RunLogError(f"{self.path}: sample lacks {missing}; required: {SAMPLE_SCHEMA['required']}")
        if not isinstance(record["config_id"], str) or not record["config_id"]:
            raise RunLogError(f"{self.path}: sample config_id must be a non-empty string, given {record['config_id']!r}")
        data = encode_json(record)
        with self._lock:
            self._append(SAMPLE_TOPIC, data, time.time_ns())
            self._durable()
            self.samples_written += 1

    def event(self, kind: str, **fields: Any) -> None:
        """Record an event ``{"kind": kind, "t": unix s, **fields}``; returns once it is on disk."""
        if not isinstance(kind, str) or not _EVENT_KIND_RE.match(kind):
            raise RunLogError(f"{self.path}: event kind must match [a-z][a-z0-9_-]*, given {kind!r}")
        if "kind" in fields or "t" in fields:
            raise RunLogError(f"{self.path}: event fields may not be named 'kind' or 't' (given {sorted(fields)})")
        t_ns = time.time_ns()
        data = encode_json({"kind": kind, "t": t_ns / 1e9, **fields})
        with self._lock:
            self._append(EVENT_TOPIC, data, t_ns)
            self._durable()
            self.events_written += 1

    def record_joint_state(self, device: str, q_rad: Any, *, names: list[str] | None = None,
                           device_time: float | None = None, log_time_ns: int | None = None) -> None:
        """Record measured joints on ``/<device>/joint_state``; q_rad (n,) radians, stored in degrees
        rounded to 1e-6° (far below any encoder's resolution; keeps the log small)."""
        q = np.asarray(q_rad, dtype=float).reshape(-1)
        topic = f"/{device}/joint_state"
        if topic not in self._channels:
            self.channel(topic, "remaster.JointState", JOINT_STATE_SCHEMA)
        t = time.time_ns() if log_time_ns is None else int(log_time_ns)
        names = names if names is not None else [f"A{i + 1}" for i in range(q.size)]
        self.write(topic, {"timestamp": _stamp(t), "name": names, "position_deg": np.round(np.degrees(q), 6), "device_time": device_time},
                   log_time_ns=t)

    def record_markers(self, sensor: str, positions_mm: dict[str, Any], *, quality: dict[str, float] | None = None,
                       device_time: float | None = None, log_time_ns: int | None = None) -> None:
        """Record one sensor frame on ``/<sensor>/markers`` (mm) and ``/<sensor>/markers/scene`` (Foxglove).

        positions_mm: marker name → xyz (3,) mm in the sensor frame, or None when not seen; stored
        rounded to 1e-4 mm. The scene channel is decimated to ``scene_rate_hz`` (log time).
        """
        topic = f"/{sensor}/markers"
        if topic not in self._channels:
            self.channel(topic, "remaster.MarkerFrame", MARKER_FRAME_SCHEMA)
            self.channel(topic + "/scene", "foxglove.SceneUpdate", SCENE_UPDATE_SCHEMA)
        t = time.time_ns() if log_time_ns is None else int(log_time_ns)
        quality = quality or {}
        frame = {
            "timestamp": _stamp(t),
            "frame_id": sensor,
            "device_time": device_time,
            "markers": [
                {"name": n, "position_mm": None if p is None else np.round(np.asarray(p, dtype=float).reshape(3), 4), "quality": quality.get(n)}
                for n, p in positions_mm.items()
            ],
        }
        self.write(topic, frame, log_time_ns=t)
        if self._scene_due(sensor, t):
            self.write(topic + "/scene", scene_update(sensor, positions_mm, t), log_time_ns=t)

    def _scene_due(self, sensor: str, t_ns: int) -> bool:
        """Whether the Foxglove scene of ``sensor`` is due at log time ``t_ns`` (rate limit)."""
        if self._scene_rate_hz <= 0:
            return False
        period = 1e9 / self._scene_rate_hz
        with self._lock:
            due = self._next_scene_ns.get(sensor)
            if due is not None and t_ns < due and due - t_ns <= period:
                return False
            # on a fixed schedule (so frame-time rounding does not lower the rate); re-anchored
            # after a gap or a jump back in time
            nxt = (due if due is not None and t_ns - due < period else t_ns) + period
            self._next_scene_ns[sensor] = nxt
            return True

    def _append(self, topic: str, data: bytes, t_ns: int) -> None:
        self._check_open()
        known = self._channels.get(topic)
        if known is None:
            raise RunLogError(f"{self.path}: topic {topic} has no channel; register it with channel() first (known: {sorted(self._channels)})")
        cid = known[0]
        seq = self._sequence[cid] = self._sequence[cid] + 1
        self._writer.add_message(cid, t_ns, data, t_ns, sequence=seq)

    def _durable(self) -> None:
        self._fh.flush()
        self._last_flush = time.monotonic()
        if self._fsync:
            os.fsync(self._fh.fileno())

    def _check_open(self) -> None:
        if self._closed:
            raise RunLogError(f"{self.path}: the run log is closed")

    def flush(self) -> None:
        """Push everything written so far to the disk (flush + fsync)."""
        with self._lock:
            self._check_open()
            self._durable()

    # -- closing ------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Write the MCAP summary and footer, fsync, close. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._writer.finish()
                self._fh.flush()
                os.fsync(self._fh.fileno())
            finally:
                self._fh.close()
        log.info("run %s: log %s closed (%d samples, %d events)", self.run_id, self.path, self.samples_written, self.events_written)

    def __enter__(self) -> "RunLog":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------
# Reading (tolerant of truncation)
# --------------------------------------------------------------------------------------------
@dataclass
class SegmentContents:
    """What one segment file holds. ``good_end``: byte offset after the last complete record."""

    path: Path
    run: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    plan_text: str = ""
    model_text: str = ""
    samples: list[dict] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    message_counts: dict[str, int] = field(default_factory=dict)
    complete: bool = False
    good_end: int = 0
    data_end: int | None = None
    size: int = 0
    corrupt_messages: int = 0
    has_header: bool = False


@dataclass
class RunContents:
    """Everything recovered from a run's segments (in order).

    complete: every segment ends with a valid footer (closed cleanly, or closed by append_to);
    it says the log is whole, not that every configuration was measured.
    """

    run_id: str
    plan_text: str
    model_text: str
    metadata: dict
    samples: list[dict]
    events: list[dict]
    complete: bool
    files: list[Path]
    segments: list[SegmentContents] = field(default_factory=list)
    dropped_bytes: int = 0
    message_counts: dict[str, int] = field(default_factory=dict)

    @property
    def measured_config_ids(self) -> list[str]:
        """Config ids with a sample, in recording order, without repeats."""
        return list(dict.fromkeys(s["config_id"] for s in self.samples))


_RECORD_READERS = {
    Opcode.HEADER: None,
    Opcode.FOOTER: Footer.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.METADATA: Metadata.read,
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.DATA_END: DataEnd.read,
}


def _iter_complete_records(
    fh: io.BufferedReader, size: int, start: int, wanted_channels: set[int]
) -> Iterator[tuple[int, int, bytes | None, int]]:
    """(opcode, end offset, body, channel id) of each complete record from ``start``.

    Stops at the first record cut by the end of the file (or at zero fill). Message records of
    channels not in ``wanted_channels`` are skipped by seeking (body None) — the run's streams
    are counted, not decoded. channel id is -1 for other records.
    """
    offset = start
    while True:
        head = fh.read(9)
        if len(head) < 9:
            return
        opcode, length = struct.unpack("<BQ", head)
        if opcode == 0 or length > size - offset - 9:
            return  # zero fill (power loss) or a record cut by the end of the file
        offset += 9 + length
        if opcode == Opcode.MESSAGE and length >= 2:
            peek = fh.read(2)
            (channel_id,) = struct.unpack("<H", peek)
            if channel_id not in wanted_channels:
                fh.seek(length - 2, io.SEEK_CUR)
                yield opcode, offset, None, channel_id
                continue
            body = peek + fh.read(length - 2)
        else:
            channel_id = -1
            body = fh.read(length)
        if len(body) < length:
            return
        yield opcode, offset, body, channel_id


def read_segment(path: Path) -> SegmentContents:
    """Read one segment; never raises for a truncated file (only for a non-MCAP or unreadable one)."""
    seg = SegmentContents(path=path)
    try:
        seg.size = path.stat().st_size
        fh = open(path, "rb")
    except OSError as exc:
        raise RunLogError(f"{path}: cannot read the run log: {exc.strerror or exc}") from exc
    with fh:
        magic = fh.read(MAGIC_SIZE)
        if magic != MCAP_MAGIC[: len(magic)]:
            raise RunLogError(f"{path}: not an MCAP file (starts with {magic!r}, expected {MCAP_MAGIC!r})")
        if len(magic) < MAGIC_SIZE:
            return seg
        seg.good_end = MAGIC_SIZE
        channels: dict[int, Channel] = {}
        wanted: set[int] = set()
        for opcode, end, body, channel_id in _iter_complete_records(fh, seg.size, MAGIC_SIZE, wanted):
            if body is None:  # a stream message: count it
                ch = channels.get(channel_id)
                if ch is None:
                    log.warning("%s: message of undeclared channel %d at byte %d; stopping there", path, channel_id, seg.good_end)
                    break
                seg.message_counts[ch.topic] = seg.message_counts.get(ch.topic, 0) + 1
                seg.good_end = end
                continue
            try:
                records = _parse_record(opcode, body)
            except (McapError, CRCValidationError, struct.error, UnicodeDecodeError, ValueError) as exc:
                log.warning("%s: unreadable record (opcode 0x%02x) at byte %d: %s; stopping there", path, opcode, seg.good_end, exc)
                break
            footer = False
            seg.has_header = seg.has_header or opcode == Opcode.HEADER
            for rec in records:
                if isinstance(rec, Footer):
                    footer = True
                else:
                    _take_record(seg, channels, rec)
                    if isinstance(rec, Channel) and rec.topic in (SAMPLE_TOPIC, EVENT_TOPIC):
                        wanted.add(rec.id)
            seg.good_end = end
            if records and isinstance(records[0], DataEnd) and seg.data_end is None:
                seg.data_end = end
            if footer:
                seg.complete = fh.read(MAGIC_SIZE) == MCAP_MAGIC
                break
    return seg


def _parse_record(opcode: int, body: bytes) -> list:
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, len(body))]
    if opcode == Opcode.CHUNK:
        return [r for r in breakup_chunk(Chunk.read(stream), validate_crc=True)]
    reader = _RECORD_READERS.get(opcode, None)
    if reader is None:
        return []  # header, indexes, statistics, summary offsets, unknown records: nothing to take
    return [reader(stream)]


def _take_record(seg: SegmentContents, channels: dict[int, Channel], rec: Any) -> None:
    if isinstance(rec, Channel):
        channels[rec.id] = rec
    elif isinstance(rec, Message):
        ch = channels.get(rec.channel_id)
        if ch is None:
            seg.corrupt_messages += 1
            return
        seg.message_counts[ch.topic] = seg.message_counts.get(ch.topic, 0) + 1
        if ch.topic in (SAMPLE_TOPIC, EVENT_TOPIC):
            try:
                obj = decode_json(rec.data)
            except PayloadError as exc:
                seg.corrupt_messages += 1
                log.warning("%s: undecodable %s message skipped: %s", seg.path, ch.topic, exc)
                return
            (seg.samples if ch.topic == SAMPLE_TOPIC else seg.events).append(obj)
    elif isinstance(rec, Metadata):
        if rec.name == "remaster.run":
            seg.run = dict(rec.metadata)
        elif rec.name == "remaster.run.metadata":
            for k, v in rec.metadata.items():
                try:
                    seg.metadata[k] = json.loads(v)
                except ValueError:
                    seg.metadata[k] = v
        elif rec.name == "remaster.plan":
            seg.plan_text = rec.metadata.get("text", "")
        elif rec.name == "remaster.robot_model":
            seg.model_text = rec.metadata.get("text", "")


def read_run(path: str | Path) -> RunContents:
    """Everything complete in the run's segments (``path`` may name any of them).

    Never raises for truncation at any byte (a killed writer): it returns the complete records
    before the cut. Raises RunLogError for a missing file, a file that is not MCAP, or a resume
    segment whose run id differs from the first file's.
    """
    files = segment_paths(path)
    if not files[0].exists():
        raise RunLogError(f"{files[0]}: no such run log")
    segments = [read_segment(p) for p in files]
    first = segments[0]
    run_id = first.run.get("run_id", "")
    for seg in segments[1:]:
        other = seg.run.get("run_id")
        if other is not None and run_id and other != run_id:
            raise RunLogError(f"{seg.path}: belongs to run {other!r}, not to {run_id!r} of {first.path}")
    counts: dict[str, int] = {}
    for seg in segments:
        for k, v in seg.message_counts.items():
            counts[k] = counts.get(k, 0) + v
    samples = [s for seg in segments for s in seg.samples]
    seen: set[str] = set()
    for s in samples:
        cid = s.get("config_id")
        if cid in seen:
            log.warning("%s: configuration %r has more than one sample", files[0], cid)
        seen.add(cid)
    return RunContents(
        run_id=run_id,
        plan_text=first.plan_text,
        model_text=first.model_text,
        metadata=first.metadata,
        samples=samples,
        events=[e for seg in segments for e in seg.events],
        complete=all(seg.complete for seg in segments),
        files=files,
        segments=segments,
        dropped_bytes=sum(seg.size - seg.good_end for seg in segments if not seg.complete),
        message_counts=counts,
    )


def _close_truncated(seg: SegmentContents) -> None:
    """Make a killed segment valid MCAP: cut its incomplete tail record, append DataEnd + Footer.

    Only bytes after the last complete record are removed; they never held a whole record.
    """
    builder = RecordBuilder()
    if not seg.has_header:
        # Killed before its header was complete: it holds nothing; make it an empty, valid MCAP.
        cut = 0
        Header(profile="", library="remaster").write(builder)
    else:
        cut = seg.data_end if seg.data_end is not None else seg.good_end
    if seg.data_end is None:
        DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    tail = (MCAP_MAGIC if cut == 0 else b"") + builder.end() + MCAP_MAGIC
    with open(seg.path, "r+b") as fh:
        fh.truncate(cut)
        fh.seek(cut)
        fh.write(tail)
        fh.flush()
        os.fsync(fh.fileno())
    log.warning("%s: closed a truncated log (dropped %d incomplete bytes)", seg.path, seg.size - seg.good_end)


# --------------------------------------------------------------------------------------------
# To the fitter
# --------------------------------------------------------------------------------------------
def dataset_from_run(path: str | Path, model: Any):
    """The run's samples as a ``calib.dataset.Dataset`` (one row per marker measurement).

    q from ``q_measured_deg`` (degrees → radians); xyz from ``mean_mm``; std_mm is the RMS of
    the per-axis ``std_mm`` (NaN when missing); count from ``count``; config and pose ids kept.
    Markers without a mean (not seen) give no row. Raises DatasetError naming the file and the
    configuration for joint counts or markers that do not match ``model``.
    """
    from calib.dataset import DatasetError, check_units, from_arrays

    path = Path(path)
    try:
        contents = read_run(path)
    except RunLogError as exc:
        raise DatasetError(str(exc)) from exc
    n = model.n_joints
    rows: dict[str, list] = {k: [] for k in ("config", "pose", "q", "xyz", "marker", "sensor", "std", "count")}
    for s in contents.samples:
        cid = s.get("config_id", "?")
        q = s.get("q_measured_deg")
        if not isinstance(q, list) or len(q) != n or any(not isinstance(v, (int, float)) for v in q):
            raise DatasetError(f"{path}: configuration {cid!r}: q_measured_deg must hold {n} numbers for '{model.name}', given {q!r}")
        for m in s.get("markers") or []:
            mean = m.get("mean_mm")
            if mean is None or len(mean) != 3 or any(v is None for v in mean):
                continue
            marker = m.get("marker") or model.marker_names[0]
            if marker not in model.marker_names:
                raise DatasetError(f"{path}: configuration {cid!r}: marker {marker!r} is not on the tool; markers: {model.marker_names}")
            std = m.get("std_mm")
            std_rms = math.nan
            if isinstance(std, list) and len(std) == 3 and all(isinstance(v, (int, float)) for v in std):
                std_rms = math.sqrt(sum(v * v for v in std) / 3.0)
            rows["config"].append(cid)
            rows["pose"].append(s.get("pose") or "")
            rows["q"].append(q)
            rows["xyz"].append(mean)
            rows["marker"].append(marker)
            rows["sensor"].append(m.get("sensor") or "sensor")
            rows["std"].append(std_rms)
            rows["count"].append(int(m.get("count") or 0))
    if not rows["q"]:
        raise DatasetError(f"{path}: no marker measurements in the run log ({len(contents.samples)} samples)")
    ds = from_arrays(
        np.radians(np.array(rows["q"], dtype=float)),
        np.array(rows["xyz"], dtype=float),
        marker=np.array(rows["marker"]),
        sensor=np.array(rows["sensor"]),
        pose=np.array(rows["pose"]),
        config=np.array(rows["config"]),
        std_mm=np.array(rows["std"], dtype=float),
        count=np.array(rows["count"], dtype=int),
    )
    ds = replace(ds, source=str(path))
    check_units(ds, model)
    return ds
