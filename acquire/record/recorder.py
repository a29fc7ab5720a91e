"""The run log: one MCAP file per run, crash-safe, resumable, indexed for every reader.

What is in the file (readable by ``mcap`` tooling, the TypeScript ``McapIndexedReader`` and Foxglove):

- Every stream is a channel with message encoding ``json`` and a schema with encoding
  ``jsonschema``. Run channels: ``/run/sample`` (``remaster.Sample``, one record per measured
  configuration), ``/run/event`` (``remaster.RunEvent``: moved, settled, suspended, resumed,
  skipped, …). :meth:`RunLog.record_markers` writes ``/<sensor>/markers``
  (``remaster.MarkerFrame``, mm, sensor frame, every frame).
- The Foxglove channels of :mod:`acquire.record.foxglove_view` (fixed names, one layout for every cell):
  ``/joint_state`` (:meth:`RunLog.record_joint_state`, degrees and radians), ``/tf``
  (``foxglove.FrameTransforms``, :meth:`RunLog.record_transforms`), ``/markers``
  (``foxglove.SceneUpdate``: every sensor's markers in its frame, at most ``scene_rate_hz`` per
  sensor, default 30 Hz; the model's nominal markers on the flange) and ``/log``
  (``foxglove.Log``: every event and sample as a line).
- Metadata records ``remaster.run`` (format, run id, segment number, creation time),
  ``remaster.run.metadata`` (the caller's metadata, each value JSON-encoded), ``remaster.plan``
  and ``remaster.robot_model`` (the exact texts), and the same two texts as attachments
  ``plan.yaml`` and ``robot.yaml``.

Layout and crash safety (:mod:`acquire.record.mcapfile`): messages collect in a small uncompressed chunk
that is written, with its message indexes, when it is ``flush_interval_s`` old (default 0.25 s;
a background thread closes it even when no further message arrives) or ``chunk_bytes`` big, and
before every ``sample`` and ``event``, which return only after ``flush`` + ``os.fsync``. A
``kill -9`` therefore loses at most the stream messages of the last ``flush_interval_s`` (plus
scheduling delay; ``tests/bench/bench_mcap_kill.py`` measures it); a power cut keeps what was
fsync'd. ``close`` writes the summary: schemas, channels, statistics, chunk / attachment /
metadata indexes. :func:`read_run` reads unit by unit (a chunk counts with all its message
indexes) and stops at the first incomplete one, so a truncated file yields exactly the complete
records — never a partial one. JSON encoding: :mod:`acquire.record.jsonpayload` (NaN/inf → null).

Live view: a ``live`` publisher (:class:`acquire.live.foxglove_server.LiveServer`) given to ``create`` /
``append_to`` receives every message written, on the same topics with the same schemas.

Resume: :meth:`RunLog.append_to` never rewrites recorded data. It finishes the killed file (cuts
the incomplete tail unit, if any, and appends DataEnd + a rebuilt summary + Footer, so the file is
indexed MCAP again), then continues in a new segment beside it: ``RUN.mcap`` →
``RUN.resume1.mcap`` → ``RUN.resume2.mcap`` …; each segment is a complete MCAP file with the run's
metadata and its segment number. :func:`read_run` given any segment reads them all in order and
returns the union.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import math
import os
import re
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from acquire.record import foxglove_view as fv
from acquire.record.foxglove_view import SCENE_UPDATE_SCHEMA, scene_update  # noqa: F401 - re-exported
from acquire.record.logstorage import LogFile, StorageError, summary_bytes
from acquire.record.mcapfile import ChunkedWriter, McapFileError, ScanResult, finish_truncated, scan
from acquire.record.jsonpayload import PayloadError, decode_json, encode_json

log = logging.getLogger(__name__)

FORMAT = "remaster-run/1"
SAMPLE_TOPIC = "/run/sample"
EVENT_TOPIC = "/run/event"
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
                    "quat_wxyz": {"type": "array", "items": _NUM, "minItems": 4, "maxItems": 4,
                                  "description": "6-DoF target only: mean orientation R_sensor←target, unit quaternion, "
                                                 "scalar first (w, x, y, z)"},
                    "std_deg": {**_NUM_OR_NULL, "description": "6-DoF target only: attitude spread per axis, degrees"},
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
                "trigger": {"type": "string", "enum": ["still", "confirm", "input"],
                            "description": "guided then held still for the window, the operator's confirmation "
                                           "(a key, the control call), or a controller input the operator pressed"},
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

JOINT_STATE_SCHEMA = fv.JOINT_STATE_SCHEMA

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


#: topic → (schema name, JSON schema) of the run's own records.
RUN_CHANNELS: dict[str, tuple[str, dict]] = {
    SAMPLE_TOPIC: ("remaster.Sample", SAMPLE_SCHEMA),
    EVENT_TOPIC: ("remaster.RunEvent", EVENT_SCHEMA),
}
#: (schema name, JSON schema) of every ``/<sensor>/markers`` channel.
MARKER_FRAME_CHANNEL: tuple[str, dict] = ("remaster.MarkerFrame", MARKER_FRAME_SCHEMA)


def schema_bytes(json_schema: dict) -> bytes:
    """The bytes a channel's JSON schema is stored and advertised as (one encoding, so a live
    channel advertised before its log exists is the same channel the log later writes to)."""
    return json.dumps(json_schema, sort_keys=True, separators=(",", ":")).encode("utf-8")


def advertise_run_channels(live: Any, sensors: tuple[str, ...] | list[str] = ()) -> None:
    """Advertise on ``live`` (``acquire.live.foxglove_server.LiveServer``) every channel a run writes — the run's
    records, the Foxglove view's ``/tf``, ``/markers``, ``/joint_state``, ``/log`` and each sensor's
    ``/<sensor>/markers`` — before its address is given to anyone.

    A channel created while a viewer is connecting can be advertised to it before the Foxglove SDK
    knows the viewer has it; the viewer's subscription is then refused ("attempted to subscribe to
    unknown channel") and that topic stays dark for the whole run. Channels that exist before the
    viewer connects are not exposed to that race."""
    channels = {**RUN_CHANNELS, **fv.CHANNELS, **{f"/{s}/markers": MARKER_FRAME_CHANNEL for s in sensors}}
    for topic, (schema_name, json_schema) in channels.items():
        live.advertise(topic, schema_name, schema_bytes(json_schema))


_stamp = fv.stamp


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
    """One JSON value as text, with the conventions of acquire.record.jsonpayload (numpy, NaN → null)."""
    return json.dumps(json.loads(encode_json({"v": value}))["v"], separators=(",", ":"))


@contextlib.contextmanager
def _closed_on_error(fh: LogFile):
    """Close ``fh`` if the block raises (a log that could not be started, e.g. on a full disk)."""
    try:
        yield
    except BaseException:
        fh.close()
        raise


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

    def __init__(self, path: Path, fh: LogFile, run_id: str, segment: int, *, flush_interval_s: float, fsync: bool,
                 scene_rate_hz: float = 30.0, chunk_bytes: int = 256 * 1024, live: Any = None):
        self.path = path
        self.run_id = run_id
        self.segment = segment
        self._fh = fh
        self._writer = ChunkedWriter(fh, chunk_bytes=chunk_bytes)
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
        self.live = live
        self.samples_written = 0
        self.events_written = 0
        self.recovered: RunContents | None = None
        self._halt = threading.Event()
        self._flusher: threading.Thread | None = None

    def _start_flusher(self) -> None:
        """Close the open chunk once it is ``flush_interval_s`` old even when no message follows."""
        if self._flush_interval_s <= 0:
            return  # every write closes its chunk
        self._flusher = threading.Thread(target=self._flush_loop, name=f"runlog-flush-{self.run_id}", daemon=True)
        self._flusher.start()

    def _flush_loop(self) -> None:
        period = max(self._flush_interval_s / 2.0, 0.005)
        while not self._halt.wait(period):
            with self._lock:
                if self._closed:
                    return
                if self._writer.pending_messages and time.monotonic() - self._last_flush >= self._flush_interval_s:
                    try:
                        self._flush_chunk()
                    except StorageError:
                        return  # the log is sealed; the next sample or event raises it
                    except (OSError, ValueError) as exc:
                        log.error("run %s: cannot write the log %s: %s", self.run_id, self.path, exc)
                        return

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
        flush_interval_s: float = 0.25,
        fsync: bool = True,
        scene_rate_hz: float = 30.0,
        chunk_bytes: int = 256 * 1024,
        live: Any = None,
    ) -> "RunLog":
        """Start a new run log at ``path`` (must not exist; parent folders are created).

        metadata: JSON-able values (stored JSON-encoded in ``remaster.run.metadata``).
        flush_interval_s: how long stream records may wait in the open chunk before it is
        written (s; what a ``kill -9`` can lose); 0 writes a chunk per message.
        fsync: False only for benchmarks — samples and events are then flushed but not fsync'd.
        scene_rate_hz: at most this many Foxglove scene updates per second and sensor (0: none);
        the mm marker frames are always all recorded.
        chunk_bytes: a chunk is written once it holds this many bytes, whatever its age.
        live: a publisher (``acquire.live.foxglove_server.LiveServer``) that receives every message as well.
        """
        return cls._open(Path(path), run_id=run_id, plan_text=plan_text, model_text=model_text, metadata=metadata,
                         segment=0, extra={}, flush_interval_s=flush_interval_s, fsync=fsync, scene_rate_hz=scene_rate_hz,
                         chunk_bytes=chunk_bytes, live=live)

    @classmethod
    def _open(cls, path: Path, *, run_id: str, plan_text: str, model_text: str, metadata: dict, segment: int,
              extra: dict[str, str], flush_interval_s: float, fsync: bool, scene_rate_hz: float = 30.0,
              chunk_bytes: int = 256 * 1024, live: Any = None) -> "RunLog":
        if not isinstance(run_id, str) or not run_id.strip():
            raise RunLogError(f"{path}: run_id must be a non-empty string, given {run_id!r}")
        if not isinstance(metadata, dict):
            raise RunLogError(f"{path}: metadata must be a dict, given {type(metadata).__name__}")
        if flush_interval_s < 0:
            raise RunLogError(f"{path}: flush_interval_s must be >= 0, given {flush_interval_s}")
        if scene_rate_hz < 0:
            raise RunLogError(f"{path}: scene_rate_hz must be >= 0, given {scene_rate_hz}")
        if not isinstance(chunk_bytes, int) or chunk_bytes < 1:
            raise RunLogError(f"{path}: chunk_bytes must be a positive integer, given {chunk_bytes!r}")
        try:
            meta_json = {str(k): _json_text(v) for k, v in metadata.items()}
        except PayloadError as exc:
            raise RunLogError(f"{path}: metadata is not JSON-able: {exc}") from exc
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fh = LogFile(path)
        except FileExistsError:
            raise RunLogError(f"{path}: exists already; a run log is never overwritten (resume it with append_to)") from None
        except OSError as exc:
            raise RunLogError(f"{path}: cannot create the run log: {exc.strerror or exc}") from exc
        self = cls(path, fh, run_id, segment, flush_interval_s=flush_interval_s, fsync=fsync, scene_rate_hz=scene_rate_hz,
                   chunk_bytes=chunk_bytes, live=live)
        now_ns = time.time_ns()
        with self._lock, _closed_on_error(fh):
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
            self.channel(SAMPLE_TOPIC, *RUN_CHANNELS[SAMPLE_TOPIC])
            self.channel(EVENT_TOPIC, *RUN_CHANNELS[EVENT_TOPIC])
            self.channel(fv.LOG_TOPIC, *fv.CHANNELS[fv.LOG_TOPIC])
            self._durable()
        _fsync_dir(path.parent)
        self._start_flusher()
        log.info("run %s: logging to %s (segment %d)", run_id, path, segment)
        return self

    @classmethod
    def append_to(cls, path: Path, *, flush_interval_s: float = 0.25, fsync: bool = True, scene_rate_hz: float = 30.0,
                  chunk_bytes: int = 256 * 1024, live: Any = None) -> "RunLog":
        """Resume the run logged at ``path`` (any of its segments) in a new segment file.

        Recovers every complete record of the existing segments (``self.recovered``), makes each
        killed segment indexed MCAP again (cuts only its incomplete tail unit, rebuilds the
        summary), and opens
        ``<stem>.resume<N>.mcap`` with the same run id, plan, model and metadata. Nothing recorded
        is rewritten or copied, so nothing is lost or duplicated; ``read_run`` returns the union.
        """
        contents = read_run(path)
        if not contents.run_id:
            raise RunLogError(f"{contents.files[0]}: holds no run metadata (killed while being created); nothing to resume — start a new run")
        for seg in contents.segments:
            LogFile.release_stale_reserve(seg.path)
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
            chunk_bytes=chunk_bytes,
            live=live,
        )
        self.recovered = contents
        try:
            self.event("log_resumed", segment=self.segment, previous_files=[p.name for p in contents.files],
                       recovered_samples=len(contents.samples), recovered_events=len(contents.events),
                       dropped_bytes=contents.dropped_bytes)
        except StorageError:
            self.close()
            raise
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
        data = schema_bytes(json_schema)
        with self._lock:
            self._check_open()
            known = self._channels.get(topic)
            if known is not None:
                if known[1:] != (schema_name, data):
                    raise RunLogError(f"{self.path}: topic {topic} is registered with schema {known[1]!r} already; a topic has one schema")
                return known[0]
            schema_id = self._schemas.get((schema_name, data))
            if schema_id is None:
                schema_id = self._writer.add_schema(schema_name, "jsonschema", data)
                self._schemas[(schema_name, data)] = schema_id
            channel_id = self._writer.add_channel(topic, "json", schema_id)
            self._channels[topic] = (channel_id, schema_name, data)
            self._sequence[channel_id] = 0
            if self.live is not None:
                try:
                    self.live.advertise(topic, schema_name, data)
                except Exception as exc:  # noqa: BLE001 - a viewer must never stop the recording
                    log.debug("live advertise of %s failed: %s", topic, exc)
            return channel_id

    def write(self, topic: str, message: dict, *, log_time_ns: int | None = None) -> None:
        """Append one JSON message to a registered channel (reaches the OS within flush_interval_s);
        dropped without a word once the log is sealed (the next sample or event raises StorageError)."""
        data = encode_json(message)
        t = time.time_ns() if log_time_ns is None else int(log_time_ns)
        with self._lock:
            if self._fh.error is not None:
                return
            try:
                self._append(topic, data, t)
                if time.monotonic() - self._last_flush >= self._flush_interval_s:
                    self._flush_chunk()
            except StorageError:
                return

    def sample(self, record: dict) -> None:
        """Record one measured configuration (see SAMPLE_SCHEMA); returns once it is on disk, or
        raises ``acquire.record.logstorage.StorageError`` (the sample is not in the log, which is sealed)."""
        if not isinstance(record, dict):
            raise RunLogError(f"{self.path}: a sample must be a dict, given {type(record).__name__}")
        missing = [k for k in SAMPLE_SCHEMA["required"] if k not in record]
        if missing:
            raise RunLogError(f"{self.path}: sample lacks {missing}; required: {SAMPLE_SCHEMA['required']}")
        if not isinstance(record["config_id"], str) or not record["config_id"]:
            raise RunLogError(f"{self.path}: sample config_id must be a non-empty string, given {record['config_id']!r}")
        data = encode_json(record)
        t_ns = time.time_ns()
        poses = [(topic, doc) for pair in fv.measured_poses(record, t_ns) for topic, doc in zip((fv.POSE_TOPIC, fv.TF_TOPIC), pair)]
        with self._lock:
            self._append(SAMPLE_TOPIC, data, t_ns)
            self._append(fv.LOG_TOPIC, encode_json(fv.sample_log(record, t_ns)), t_ns)
            for topic, doc in poses:  # 6-DoF targets' poses for Foxglove (channel(): the same id once registered)
                self.channel(topic, *fv.CHANNELS[topic])
                self._append(topic, encode_json(doc), t_ns)
            self._durable()
            self.samples_written += 1

    def event(self, kind: str, **fields: Any) -> None:
        """Record an event ``{"kind": kind, "t": unix s, **fields}``; returns once it is on disk
        (or raises ``StorageError``, as ``sample``)."""
        if not isinstance(kind, str) or not _EVENT_KIND_RE.match(kind):
            raise RunLogError(f"{self.path}: event kind must match [a-z][a-z0-9_-]*, given {kind!r}")
        if "kind" in fields or "t" in fields:
            raise RunLogError(f"{self.path}: event fields may not be named 'kind' or 't' (given {sorted(fields)})")
        t_ns = time.time_ns()
        doc = {"kind": kind, "t": t_ns / 1e9, **fields}
        data = encode_json(doc)
        with self._lock:
            self._append(EVENT_TOPIC, data, t_ns)
            self._append(fv.LOG_TOPIC, encode_json(fv.event_log(doc, t_ns)), t_ns)
            self._durable()
            self.events_written += 1

    def record_joint_state(self, device: str, q_rad: Any, *, names: list[str] | None = None,
                           device_time: float | None = None, log_time_ns: int | None = None) -> None:
        """Record measured joints on ``/joint_state`` (``remaster.JointState``); q_rad (n,) radians,
        stored in degrees rounded to 1e-6° and radians to 1e-8 (far below any encoder's resolution)."""
        q = np.asarray(q_rad, dtype=float).reshape(-1)
        topic = fv.JOINT_STATE_TOPIC
        if topic not in self._channels:
            self.channel(topic, *fv.CHANNELS[topic])
        t = time.time_ns() if log_time_ns is None else int(log_time_ns)
        names = names if names is not None else [f"A{i + 1}" for i in range(q.size)]
        try:
            doc = fv.joint_state(device, names, q, t, device_time)
        except ValueError as exc:
            raise RunLogError(f"{self.path}: {exc}") from None
        self.write(topic, doc, log_time_ns=t)

    def record_transforms(self, transforms: dict, *, log_time_ns: int | None = None) -> None:
        """Record a ``foxglove.FrameTransforms`` (see ``acquire.record.foxglove_view.RobotView``) on ``/tf``."""
        if fv.TF_TOPIC not in self._channels:
            self.channel(fv.TF_TOPIC, *fv.CHANNELS[fv.TF_TOPIC])
        self.write(fv.TF_TOPIC, transforms, log_time_ns=log_time_ns)

    def record_scene(self, update: dict, *, log_time_ns: int | None = None) -> None:
        """Record a ``foxglove.SceneUpdate`` on ``/markers`` (not rate-limited)."""
        if fv.SCENE_TOPIC not in self._channels:
            self.channel(fv.SCENE_TOPIC, *fv.CHANNELS[fv.SCENE_TOPIC])
        self.write(fv.SCENE_TOPIC, update, log_time_ns=log_time_ns)

    def record_markers(self, sensor: str, positions_mm: dict[str, Any], *, quality: dict[str, float] | None = None,
                       device_time: float | None = None, log_time_ns: int | None = None) -> None:
        """Record one sensor frame on ``/<sensor>/markers`` (mm) and, for Foxglove, on ``/markers``.

        positions_mm: marker name → xyz (3,) mm in the sensor frame, or None when not seen; stored
        rounded to 1e-4 mm. The scene channel is decimated to ``scene_rate_hz`` (log time).
        """
        topic = f"/{sensor}/markers"
        if topic not in self._channels:
            self.channel(topic, *MARKER_FRAME_CHANNEL)
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
            self.record_scene(scene_update(sensor, positions_mm, t), log_time_ns=t)

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
        if self.live is not None:
            try:
                self.live.publish(topic, known[1], known[2], data, t_ns)
            except Exception as exc:  # noqa: BLE001 - a viewer must never stop the recording
                log.debug("live publish of %s failed: %s", topic, exc)

    def _flush_chunk(self) -> None:
        """Write the open chunk and hand it to the OS (no fsync); keep room to finish the file."""
        self._writer.close_chunk()
        self._fh.ensure_reserve(summary_bytes(self._writer.index))
        self._last_flush = time.monotonic()

    def _durable(self) -> None:
        """Everything written so far to the disk; ``StorageError`` (log sealed) if it cannot be."""
        self._flush_chunk()
        if self._fsync:
            self._fh.fsync()

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
            self._halt.set()
            try:
                if self._fh.error is None:
                    self._fh.release_reserve()  # its space is for this summary
                    self._writer.finish()
                    self._fh.fsync()
            except StorageError as exc:  # sealed readable by LogFile; one line, no traceback
                log.error("run %s: %s", self.run_id, exc)
            finally:
                self._fh.close()
        if self._flusher is not None and self._flusher is not threading.current_thread():
            self._flusher.join(timeout=5.0)
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
    scan: ScanResult | None = None


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


def read_segment(path: Path) -> SegmentContents:
    """Read one segment; never raises for a truncated file (only for a non-MCAP or unreadable one)."""
    seg = SegmentContents(path=path)
    try:
        seg.size = path.stat().st_size
        fh = open(path, "rb")
    except OSError as exc:
        raise RunLogError(f"{path}: cannot read the run log: {exc.strerror or exc}") from exc

    def on_message(ch, log_time: int, seq: int, data: bytes) -> None:
        try:
            obj = decode_json(data)
        except PayloadError as exc:
            seg.corrupt_messages += 1
            log.warning("%s: undecodable %s message skipped: %s", path, ch.topic, exc)
            return
        (seg.samples if ch.topic == SAMPLE_TOPIC else seg.events).append(obj)

    def on_metadata(rec) -> None:
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

    with fh:
        try:
            res = scan(fh, seg.size, wanted=lambda ch: ch.topic in (SAMPLE_TOPIC, EVENT_TOPIC), on_message=on_message,
                       on_metadata=on_metadata, where=str(path))
        except McapFileError as exc:
            raise RunLogError(str(exc)) from None
    if not res.complete and res.stop_reason not in ("end of file", ""):
        log.debug("%s: read up to byte %d (%s)", path, res.good_end, res.stop_reason)
    seg.scan = res
    seg.has_header = res.has_header
    seg.good_end = res.good_end
    seg.data_end = res.good_end if res.data_end_start is not None else None
    seg.complete = res.complete
    channels = res.index.channels
    for cid, n in res.index.channel_message_counts.items():
        topic = channels[cid].topic
        seg.message_counts[topic] = seg.message_counts.get(topic, 0) + n
    return seg


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
    """Make a killed segment indexed MCAP again: cut its incomplete tail unit, append DataEnd,
    the summary rebuilt from its complete records, and the Footer.

    Only bytes after the last complete unit are removed; they never held a whole record.
    """
    res = seg.scan if seg.scan is not None else read_segment(seg.path).scan
    with open(seg.path, "r+b") as fh:
        dropped = finish_truncated(fh, res)
        fh.flush()
        os.fsync(fh.fileno())
    log.warning("%s: closed a truncated log (dropped %d incomplete bytes)", seg.path, dropped)


# --------------------------------------------------------------------------------------------
# To the fitter
# --------------------------------------------------------------------------------------------
def _orientation_columns(rows: dict[str, list]) -> dict:
    """``rot`` / ``att_std_rad`` for ``from_arrays`` when any row carries an orientation."""
    quat = np.array(rows["quat"], dtype=float)
    if not np.isfinite(quat).all(axis=1).any():
        return {}
    from calib.robot.transforms import quat_to_matrix

    rot = np.full((len(quat), 3, 3), np.nan)
    ok = np.isfinite(quat).all(axis=1)
    rot[ok] = quat_to_matrix(quat[ok])
    return {"rot": rot, "att_std_rad": np.array(rows["att"], dtype=float)}


def dataset_from_run(path: str | Path, model: Any):
    """The run's samples as a ``calib.measure.dataset.Dataset`` (one row per marker measurement).

    q from ``q_measured_deg`` (degrees → radians); xyz from ``mean_mm``; std_mm is the RMS of
    the per-axis ``std_mm`` (NaN when missing); count from ``count``; config and pose ids kept.
    Markers without a mean (not seen) give no row. Raises DatasetError naming the file and the
    configuration for joint counts or markers that do not match ``model``.
    """
    from calib.measure.dataset import DatasetError, check_units, from_arrays

    path = Path(path)
    try:
        contents = read_run(path)
    except RunLogError as exc:
        raise DatasetError(str(exc)) from exc
    n = model.n_joints
    rows: dict[str, list] = {k: [] for k in ("config", "pose", "q", "xyz", "marker", "sensor", "std", "count", "quat", "att")}
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
            quat = m.get("quat_wxyz")  # a 6-DoF target (scalar first, R_sensor←target)
            ok = isinstance(quat, list) and len(quat) == 4 and all(isinstance(v, (int, float)) for v in quat)
            rows["quat"].append(quat if ok else [math.nan] * 4)
            att = m.get("std_deg")
            rows["att"].append(math.radians(att) if ok and isinstance(att, (int, float)) else math.nan)
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
        **_orientation_columns(rows),
    )
    ds = replace(ds, source=str(path))
    check_units(ds, model)
    return ds
