"""``NatNetSensor``: marker positions from OptiTrack Motive over NatNet, as a PositionSensor."""

from __future__ import annotations

import math
import selectors
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import Clock, SensorBase
from drivers.errors import ConnectionLostError, DeviceTimeoutError, ProtocolError
from drivers.natnet import codec
from drivers.protocols import MarkerSample

#: Motive's default data port (frames, multicast) and multicast group.
NATNET_DEFAULT_DATA_PORT = 1511
NATNET_DEFAULT_MULTICAST = "239.255.42.99"

_NAN3 = np.full(3, np.nan)
_NAN3.flags.writeable = False


def _route_source(server: str, port: int) -> str:
    """This host's IPv4 address on the route to ``server`` (no packet is sent); "0.0.0.0"
    (any interface) when there is no route yet."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((server, port))
            return probe.getsockname()[0]
        except OSError:
            return "0.0.0.0"


def _is_group(address: str | None) -> bool:
    try:
        return address is not None and 224 <= socket.inet_aton(address)[0] <= 239 and address.count(".") == 3
    except OSError:
        return False


def _id_or_name(text: str, limit: int = 0x7FFFFFFF) -> int | str:
    """``"7"`` → 7 (a NatNet id), anything else stays a name."""
    return int(text) if text.isdigit() and int(text) <= limit else text


@dataclass(frozen=True, slots=True)
class MarkerSelector:
    """What one plan marker is on the NatNet stream.

    kind "rb": a rigid body (``body`` = id or name) reported by its pivot position;
    kind "lm": a labeled marker (``model`` id, ``marker`` id);
    kind "ms": an asset's marker by name (``body`` = the rigid body, skeleton or trained
    markerset the marker belongs to, ``name`` = marker name), resolved to a labeled marker
    once the model definitions arrive;
    kind "sk": a skeleton bone (``body`` = skeleton id or name, ``name`` = bone id or name)
    reported by its position; bones of a trained markerset (NatNet 4.1 asset) the same way.
    """

    kind: str
    body: str | int | None = None
    model: int | None = None
    marker: int | None = None
    name: str | int | None = None

    SYNTAX = (
        "'rb:<rigid body id or name>', 'lm:<model id>:<marker id>', "
        "'ms:<asset name>:<marker name>' or 'sk:<skeleton id or name>:<bone id or name>'"
    )

    @classmethod
    def parse(cls, text: str) -> "MarkerSelector":
        if not isinstance(text, str):
            raise TypeError(f"marker selector must be a string ({cls.SYNTAX}), got {text!r}")
        kind, _, rest = text.partition(":")
        if kind == "rb" and rest:
            return cls("rb", body=int(rest) if rest.lstrip("-").isdigit() else rest)
        a, _, b = rest.partition(":")
        if kind == "lm":
            if a.isdigit() and b.isdigit() and int(a) <= 0xFFFF and int(b) <= 0xFFFF:
                return cls("lm", model=int(a), marker=int(b))
        if kind == "ms":
            if a and b:
                return cls("ms", body=a, name=b)
        if kind == "sk":
            if a and b and not (a.isdigit() and int(a) > 0xFFFF) and not (b.isdigit() and int(b) > 0xFFFF):
                return cls("sk", body=_id_or_name(a), name=_id_or_name(b))
        raise ValueError(f"marker selector {text!r} is not one of {cls.SYNTAX}")

    @property
    def needs_names(self) -> bool:
        """True when the selector names something, so Motive's model definitions are needed."""
        return self.kind == "ms" or isinstance(self.body, str) or (self.kind == "sk" and isinstance(self.name, str))


def body_rotation(quat_xyzw) -> np.ndarray | None:
    """A rigid body's (or bone's) orientation (3, 3) from its NatNet quaternion.

    Motive sends (qx, qy, qz, qw) — scalar **last** — as float32; the quaternion rotates the
    body's local frame (the one its markers were defined in at creation, origin at the pivot)
    into Motive's streamed world frame, the same frame its position is in (y up by default;
    the streaming "Up Axis" setting turns positions and orientations alike). So the matrix is
    ``R_sensor←body`` as ``calib.measure.dataset`` expects. None for a non-finite or zero
    quaternion."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or n < 0.5:
        return None
    from calib.robot.transforms import quat_to_matrix

    return quat_to_matrix(np.array([q[3], q[0], q[1], q[2]]) / n)


def _find_body(rows: np.ndarray, ident: int):
    hit = np.flatnonzero(rows["id"] == ident)
    return rows[hit[0]] if hit.size else None


def _find_marker(frame: codec.FrameOfData, ident: int):
    """A labeled marker by its composite id, else the same id among 4.1 asset markers."""
    row = _find_body(frame.labeled_markers, ident)
    if row is None:
        for asset in frame.assets:
            row = _find_body(asset.markers, ident)
            if row is not None:
                break
    return row


def _find_bone(frame: codec.FrameOfData, owner: int, bone: int):
    """Bone ``bone`` of skeleton (else 4.1 asset) ``owner``; frame bone ids are matched on
    their low 16 bits (frame data packs owner id << 16 | bone id)."""
    for group in (frame.skeletons, frame.assets):
        for item in group:
            if item.id == owner:
                hit = np.flatnonzero((item.rigid_bodies["id"] & 0xFFFF) == bone)
                if hit.size:
                    return item.rigid_bodies[hit[0]]
    return None


def _resolve_by_name(md: codec.ModelDef, sel: MarkerSelector, who: str) -> tuple[str, object]:
    """A named selector against Motive's model definitions (see NatNetSensor)."""
    bodies = {d.name: d.id for d in md.rigid_bodies}
    skeletons = {d.name: d for d in md.skeletons}
    assets = {d.name: d for d in md.assets}
    if sel.kind == "rb":
        if sel.body not in bodies:
            raise ValueError(f"{who}: no rigid body named {sel.body!r}; Motive defines {sorted(bodies)}")
        return ("rb", bodies[sel.body])
    if sel.kind == "sk":
        owners = {**{d.name: d for d in md.assets}, **skeletons}
        if isinstance(sel.body, str):
            owner = owners.get(sel.body)
        else:
            owner = next((d for d in (*md.skeletons, *md.assets) if d.id == sel.body), None)
        if owner is None:
            raise ValueError(
                f"{who}: no skeleton or asset {sel.body!r}; Motive defines skeletons "
                f"{sorted(skeletons)} and assets {sorted(assets)}"
            )
        bones = {b.name: b.id for b in owner.rigid_bodies}
        bone = sel.name if isinstance(sel.name, int) else bones.get(sel.name)
        if bone is None:
            raise ValueError(f"{who}: {owner.name!r} has no bone {sel.name!r}; its bones are {sorted(bones)}")
        return ("bone", (owner.id, bone))
    # "ms": a marker of an asset by name
    sets = {d.name: d.marker_names for d in md.marker_sets}
    if sel.body in assets:
        asset = assets[sel.body]
        for m in asset.markers:
            if m.name == sel.name:
                return ("lm", m.id if m.id > 0xFFFF else (asset.id << 16) | m.id)
        raise ValueError(
            f"{who}: asset {sel.body!r} has no marker {sel.name!r}; its markers are "
            f"{[m.name for m in asset.markers]}"
        )
    names = sets.get(sel.body)
    if names is None or sel.name not in names:
        raise ValueError(
            f"{who}: no marker {sel.name!r} in marker set {sel.body!r}; Motive defines "
            + ("; ".join(f"{k}: {', '.join(v)}" for k, v in sets.items()) or "no marker sets")
        )
    if sel.body in bodies:
        model = bodies[sel.body]
    elif sel.body in skeletons:
        model = skeletons[sel.body].id
    else:
        raise ValueError(
            f"{who}: marker set {sel.body!r} belongs to no rigid body, skeleton or asset of the "
            "same name, so its labeled-marker ids are unknown; select the marker as "
            "'lm:<model id>:<marker id>'"
        )
    return ("lm", (model << 16) | (names.index(sel.name) + 1))


class NatNetSensor(SensorBase):
    """Marker positions (mm, Motive's frame) from an OptiTrack Motive server over NatNet.

    URL (``from_url``)::

        natnet://<server ip>[:<command port>]?<option>=<value>&...

    options: ``command_port`` (default 1510), ``multicast`` and ``data_port`` (only for a
    server that does not announce how it streams; see Transport), ``local`` (this computer's
    IPv4 address on Motive's network; default: the address the route to the server leaves
    from), ``bitstream`` (e.g. ``4.1``: ask a NatNet 4.x server for that stream version),
    ``silence_timeout`` (s), ``units`` (``m``, Motive's default, or ``mm``: the unit positions
    arrive in), ``name``. Example: ``natnet://192.168.1.20?local=192.168.1.31``.

    markers: plan marker name → selector:

    - ``"rb:<body id or name>"``: a rigid body's pivot reported as a marker, visible while
      Motive tracks it;
    - ``"lm:<model id>:<marker id>"``: a labeled marker;
    - ``"ms:<asset>:<marker name>"``: a marker of an asset named in the model definitions. For
      a rigid body or skeleton of that name it is the labeled marker (asset id, index of the
      name in the asset's marker set + 1), Motive's asset-id/member-id labelling (real Motive
      2.1 capture: rigid body 2 "RaceQuad", markers 2:1 … 2:5); for a NatNet 4.1 trained
      markerset it is the asset marker with that name (its description's id; an id below
      65536 is taken as the member id under the asset id — *unverified* against Motive 3.1);
    - ``"sk:<skeleton id or name>:<bone id or name>"``: a skeleton bone's position (a bone of a
      NatNet 4.1 trained markerset the same way), visible while its tracking-valid bit is set.
      Bones are matched on the low 16 bits of their frame id (frame data packs
      skeleton id << 16 | bone id; definitions give the bone id alone).

    Transport: Motive streams frames either multicast (its default: group 239.255.42.99, data
    port 1511) or unicast to each client that sent CONNECT; a NatNet ≥ 3.0 SERVERINFO says which
    (``ServerInfo.multicast``, ``multicast_address``, ``data_port``). The client follows that
    announcement: it joins the announced group on the announced port on interface ``local``, or
    receives unicast frames on its command socket and sends KEEPALIVE every
    ``keepalive_interval_s``. ``multicast``/``data_port`` options are for servers that announce
    nothing; given with a server that announces, they must agree with it (else connect()
    fails saying what to change). ``stream_group`` / ``stream_port`` say what was used.

    Handshake on ``connect()``: CONNECT → SERVERINFO (retried, ``handshake_timeout_s``), then
    (4.x server) REQUEST ``Bitstream,X.Y`` (``bitstream`` set) or ``Bitstream`` (which version
    streams now), then REQUEST ``FrameRate`` (float32 frames per second → ``frame_rate_hz``,
    None if the server does not answer) and REQUEST_MODELDEF → MODELDEF. A server announcing a
    NatNet version above 4.1 (the newest layout this driver reads) is refused unless
    ``bitstream`` (≤ 4.1) is set and the server accepts the switch.

    Ordering: the client keeps only the newest frame. A frame whose number is not above the
    newest one is a duplicate or arrived late and is dropped. A server restart is recognised
    when the counter jumps back by more than ``reorder_window`` frames, when ``restart_run``
    consecutive older frames arrive in increasing order, or when a new SERVERINFO arrives;
    then ordering restarts, model definitions are requested again and ``restarts`` counts it.

    Silence: ``read()`` raises DeviceTimeoutError as soon as no frame has arrived for
    ``silence_timeout_s`` (default 0.5 s), even when the caller's timeout is longer; so a
    server that stops sending is reported at most ``silence_timeout_s`` after its last frame.
    While silent, a unicast client re-sends CONNECT every ``silence_timeout_s`` to rejoin a
    restarted server.

    Samples: ``device_time`` is the frame's timestamp (s, Motive's clock), ``host_time`` is
    ``clock()`` (``time.monotonic``) when the datagram arrived. A marker that is occluded
    (params bit 0x01), missing from the frame, or a rigid body Motive does not track comes
    back with ``visible=False`` (occluded: Motive's predicted position; missing: NaN).
    """

    def __init__(
        self,
        name: str = "natnet",
        *,
        markers: Mapping[str, str],
        server: str = "127.0.0.1",
        command_port: int = 1510,
        data_port: int | None = None,
        multicast: str | None = None,
        local: str | None = None,
        bitstream=None,
        silence_timeout_s: float = 0.5,
        handshake_timeout_s: float = 2.0,
        keepalive_interval_s: float = 1.0,
        units: str = "m",
        reorder_window: int = 60,
        restart_run: int = 3,
        clock: Clock = time.monotonic,
    ) -> None:
        super().__init__(name, clock=clock)
        if not isinstance(markers, Mapping) or not markers:
            raise ValueError(
                f"markers must be a non-empty mapping plan name → selector "
                f"({MarkerSelector.SYNTAX}), got {markers!r}"
            )
        self.selectors = {str(k): MarkerSelector.parse(v) for k, v in markers.items()}
        for label, value in (("command_port", command_port), ("data_port", data_port)):
            if value is not None and not (isinstance(value, int) and 0 < value < 65536):
                raise ValueError(f"{label} must be a port 1..65535, got {value!r}")
        for label, value in (
            ("silence_timeout_s", silence_timeout_s), ("handshake_timeout_s", handshake_timeout_s),
            ("keepalive_interval_s", keepalive_interval_s),
        ):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a positive number of seconds, got {value!r}")
        if units not in ("m", "mm"):
            raise ValueError(f"units must be 'm' or 'mm' (the unit Motive streams), got {units!r}")
        if multicast is not None:
            try:
                first = int(multicast.split(".")[0])
                socket.inet_aton(multicast)
            except (ValueError, OSError) as exc:
                raise ValueError(f"multicast must be an IPv4 group address, got {multicast!r}") from exc
            if not 224 <= first <= 239:
                raise ValueError(
                    f"multicast must be a group address 224.0.0.0–239.255.255.255, got {multicast!r}"
                )
        if reorder_window < 1 or restart_run < 2:
            raise ValueError(
                f"reorder_window must be ≥ 1 and restart_run ≥ 2, got {reorder_window}, {restart_run}"
            )
        self.server = server
        self.command_port = command_port
        self.data_port = data_port
        self.multicast = multicast
        self.local = local or _route_source(server, command_port)
        self.bitstream = codec.check_supported(bitstream) if bitstream is not None else None
        self.silence_timeout_s = float(silence_timeout_s)
        self.handshake_timeout_s = float(handshake_timeout_s)
        self.keepalive_interval_s = float(keepalive_interval_s)
        self.scale_mm = 1000.0 if units == "m" else 1.0
        self.reorder_window = int(reorder_window)
        self.restart_run = int(restart_run)

        #: What the server said: SERVERINFO, the version frames are decoded with, MODELDEF.
        self.server_info: codec.ServerInfo | None = None
        self.stream_version: codec.Version | None = None
        self.model_def: codec.ModelDef | None = None
        #: How frames arrive after connect(): the multicast group (None = unicast) and port.
        self.stream_group: str | None = None
        self.stream_port: int | None = None
        #: Motive's answer to REQUEST "FrameRate" (frames per second), None if it gave none.
        self.frame_rate_hz: float | None = None
        #: Counters: accepted frames, dropped stale/duplicate frames, undecodable packets,
        #: recognised server restarts.
        self.frames_accepted = 0
        self.frames_stale = 0
        self.bad_packets = 0
        self.restarts = 0

        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._connected = False
        self._responses: list[codec.Message] = []
        self._frame: codec.FrameOfData | None = None
        self._frame_host_time = 0.0
        self._seq = 0  # accepted frames so far; read() returns each at most once
        self._read_seq = 0
        self._newest = None  # newest accepted frame number
        self._old_run: list[int] = []
        self._rejoined = False
        self._last_rx = 0.0  # host time of the last frame datagram (any)
        self._failure: BaseException | None = None
        self._stream_problem: str | None = None  # why frames are dropped, for the silence error
        self._pending_bitstream = False  # a re-announced 4.x server was asked to switch back
        self._handshake_done = False  # SERVERINFO after this is a re-announcement
        self._resolved: dict[str, tuple[str, int]] = {}

    # ------------------------------------------------------------------ construction
    _URL_OPTIONS = (
        "command_port", "data_port", "multicast", "local", "bitstream", "silence_timeout", "units", "name",
    )

    @classmethod
    def from_url(cls, url: str, *, markers: Mapping[str, str], **kwargs) -> "NatNetSensor":
        """Build from ``natnet://host[:port]?options`` (see the class docstring)."""
        parts = urlsplit(url)
        if parts.scheme != "natnet" or not parts.hostname:
            raise ValueError(f"NatNet URL must look like 'natnet://<server ip>[:port]?…', got {url!r}")
        opts: dict = {"server": parts.hostname}
        try:
            port = parts.port
        except ValueError as exc:
            raise ValueError(f"bad port in NatNet URL {url!r}") from exc
        if port is not None:
            opts["command_port"] = port
        for key, value in parse_qsl(parts.query, keep_blank_values=True):
            if key not in cls._URL_OPTIONS:
                raise ValueError(f"unknown NatNet URL option {key!r}; allowed: {', '.join(cls._URL_OPTIONS)}")
            try:
                if key in ("command_port", "data_port"):
                    opts[key] = int(value)
                elif key == "silence_timeout":
                    opts["silence_timeout_s"] = float(value)
                elif key == "multicast":
                    opts[key] = value or None
                else:
                    opts[key] = value
            except ValueError as exc:
                raise ValueError(f"NatNet URL option {key}={value!r} is not a number") from exc
        name = opts.pop("name", "natnet")
        opts.update(kwargs)
        return cls(name, markers=markers, **opts)

    # ------------------------------------------------------------------ PositionSensor
    def marker_names(self) -> list[str]:
        return list(self.selectors)

    def connect(self) -> None:
        if self._thread is not None:
            return
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            cmd.bind((self.local, 0))
        except OSError as exc:
            cmd.close()
            raise ConnectionLostError(
                f"{self.name}: cannot bind a UDP socket on {self.local}: {exc}"
            ) from exc
        cmd.setblocking(False)
        self._cmd = cmd
        with self._cond:  # nothing learnt from an earlier connection carries over
            self.stream_version = self.stream_group = self.stream_port = None
            self._stream_problem, self._pending_bitstream, self._handshake_done = None, False, False
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-natnet", daemon=True)
        self._thread.start()
        try:
            self._handshake()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._cmd is not None and self.stream_group is None and self._connected:
            self._send(codec.Disconnect())
        for s in (self._cmd, self._data):
            if s is not None:
                s.close()
        self._cmd = self._data = None
        self._connected = False

    def _read_internal(self, timeout: float) -> list[MarkerSample]:
        if self._thread is None:
            raise ConnectionLostError(f"{self.name}: not connected; call connect() first")
        deadline = self.clock() + timeout
        with self._cond:
            while True:
                if self._failure is not None:
                    raise ConnectionLostError(
                        f"{self.name}: receiver stopped: {self._failure}"
                    ) from self._failure
                if self._seq > self._read_seq and self._frame is not None:
                    self._read_seq = self._seq
                    frame, host_time = self._frame, self._frame_host_time
                    resolved = dict(self._resolved)
                    break
                now = self.clock()
                silent = now - self._last_rx
                if silent >= self.silence_timeout_s:
                    raise DeviceTimeoutError(
                        f"{self.name}: no NatNet frame for {silent:.3f} s (silence limit "
                        f"{self.silence_timeout_s} s); "
                        + (self._stream_problem or self._where_frames_come())
                    )
                if now >= deadline:
                    raise DeviceTimeoutError(f"{self.name}: no new NatNet frame within {timeout:.3g} s")
                self._cond.wait(min(deadline, self._last_rx + self.silence_timeout_s) - now)
        return self._samples(frame, host_time, resolved)

    def _where_frames_come(self) -> str:
        """What the client listens to and what to check when nothing comes (for errors)."""
        if self.stream_group is not None:
            return (
                f"listening to multicast {self.stream_group}:{self.stream_port} on interface "
                f"{self.local} as Motive at {self.server} announced. Check that Motive is streaming "
                "(Streaming pane: Enable on), that this computer's address on Motive's network is "
                f"{self.local} (else set the sensor URL option local=<that address>) and that the "
                f"firewall lets UDP port {self.stream_port} in; or set Motive's Streaming "
                "Transmission Type to Unicast"
            )
        return (
            f"listening for unicast frames from {self.server}:{self.command_port} on "
            f"{self.local}. Check that Motive is running and streaming (Streaming pane: Enable on) "
            f"and that the firewall lets UDP from {self.server} in"
        )

    # ------------------------------------------------------------------ samples
    def _samples(self, frame: codec.FrameOfData, host_time: float, resolved) -> list[MarkerSample]:
        out = []
        for plan_name, (kind, ident) in resolved.items():
            pos, visible, residual, rotation = _NAN3, False, None, None
            if kind == "lm":
                row = _find_marker(frame, ident)
                if row is not None:
                    pos = row["pos"].astype(np.float64) * self.scale_mm
                    visible = not (row["params"] & codec.MARKER_OCCLUDED)
                    residual = float(row["residual"]) * self.scale_mm
            else:
                row = (_find_body(frame.rigid_bodies, ident) if kind == "rb"
                       else _find_bone(frame, *ident))
                if row is not None:
                    pos = row["pos"].astype(np.float64) * self.scale_mm
                    visible = bool(row["params"] & codec.RIGID_BODY_TRACKED)
                    residual = float(row["mean_error"]) * self.scale_mm
                    rotation = body_rotation(row["quat"]) if visible else None
            if visible and not np.all(np.isfinite(pos)):
                visible = False
            out.append(MarkerSample(plan_name, pos, frame.timestamp, host_time, visible, None, residual,
                                    rotation if visible else None))
        for plan_name in self.selectors:
            if plan_name not in resolved:
                out.append(MarkerSample(plan_name, _NAN3, frame.timestamp, host_time, False))
        return out

    def _resolve(self, md: codec.ModelDef | None) -> dict[str, tuple[str, object]]:
        """Selectors → ("rb", body id), ("lm", model << 16 | marker) or ("bone", (skeleton or
        asset id, bone id)). Selectors by name need ``md`` (skipped while it is None); a name
        Motive does not define raises ValueError listing what it does define."""
        out: dict[str, tuple[str, object]] = {}
        for plan_name, sel in self.selectors.items():
            if sel.kind == "lm":
                out[plan_name] = ("lm", (sel.model << 16) | sel.marker)
            elif not sel.needs_names:
                out[plan_name] = ("rb", sel.body) if sel.kind == "rb" else ("bone", (sel.body, sel.name))
            elif md is not None:
                out[plan_name] = _resolve_by_name(md, sel, f"{self.name}: marker {plan_name!r}")
        return out

    # ------------------------------------------------------------------ handshake
    def _send(self, msg) -> None:
        sock = self._cmd
        if sock is None:
            return
        try:
            sock.sendto(codec.encode_packet(msg, self.stream_version or codec.MIN_VERSION),
                        (self.server, self.command_port))
        except OSError as exc:
            self.log.warning(
                "send %s to %s:%d failed: %s", type(msg).__name__, self.server, self.command_port, exc
            )

    def _wait_for(self, cls, resend, what: str, *, required: bool = True):
        """Send ``resend`` (every 1/4 of the handshake timeout) until a ``cls`` reply arrives;
        after ``handshake_timeout_s`` raise DeviceTimeoutError (or return None if not required).
        Replies of that class still queued from an earlier request are dropped first."""
        with self._cond:
            self._responses = [m for m in self._responses if not isinstance(m, cls)]
        deadline = self.clock() + self.handshake_timeout_s
        retry = self.handshake_timeout_s / 4
        while True:
            self._send(resend)
            until = min(deadline, self.clock() + retry)
            with self._cond:
                while True:
                    if self._failure is not None:
                        raise ConnectionLostError(f"{self.name}: receiver stopped: {self._failure}")
                    for i, m in enumerate(self._responses):
                        if isinstance(m, cls):
                            return self._responses.pop(i)
                        if isinstance(m, ProtocolError) and cls is codec.ModelDef:
                            raise self._responses.pop(i)
                    left = until - self.clock()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            if self.clock() >= deadline:
                if not required:
                    return None
                raise DeviceTimeoutError(
                    f"{self.name}: no {what} from {self.server}:{self.command_port} within "
                    f"{self.handshake_timeout_s} s; is Motive running on {self.server} with streaming "
                    f"enabled and its command port set to {self.command_port}?"
                )

    def _too_new(self, version: codec.Version, app: str) -> ProtocolError:
        mx = codec.MAX_VERSION
        return ProtocolError(
            f"{self.name}: {app} at {self.server} streams NatNet {version[0]}.{version[1]}, newer "
            f"than the newest layout this driver reads ({mx[0]}.{mx[1]}). Add bitstream={mx[0]}.{mx[1]} "
            f"to the sensor URL (natnet://{self.server}:{self.command_port}?bitstream={mx[0]}.{mx[1]}) "
            f"so the driver asks Motive to stream NatNet {mx[0]}.{mx[1]} (a NatNet 4.x server "
            "switches its stream for all its clients), or use a driver that reads "
            f"NatNet {version[0]}.{version[1]}"
        )

    def _handshake(self) -> None:
        info = self._wait_for(
            codec.ServerInfo,
            codec.Connect("remaster", (0, 1, 0, 0), self.bitstream or (0, 0, 0, 0), "natnetlib"),
            "SERVERINFO",
        )
        announced = codec.version_tuple(info.natnet_version)
        if announced[:2] < codec.MIN_VERSION[:2]:
            raise ProtocolError(
                f"{self.name}: {info.app_name} at {self.server} speaks NatNet "
                f"{announced[0]}.{announced[1]}; this driver reads NatNet 3.0 to 4.1 (Motive 2.0 "
                "and later): update Motive"
            )
        if announced[:2] > codec.MAX_VERSION[:2] and (announced[0] < 4 or self.bitstream is None):
            raise self._too_new(announced, info.app_name)
        version = announced
        self.log.info(
            "connected to %s %s (NatNet %s) at %s:%d",
            info.app_name, ".".join(map(str, info.app_version)), ".".join(map(str, version)),
            self.server, self.command_port,
        )
        group, port = self._transport(info)
        if version[0] >= 4:
            version = self._negotiate_bitstream(version, info.app_name)
        elif self.bitstream is not None and self.bitstream[:2] != version[:2]:
            self.log.warning("NatNet %d.%d server cannot change its bitstream; decoding %d.%d",
                             *version[:2], *version[:2])
        with self._cond:
            self.server_info = info
            self.stream_version = version
            self.stream_group, self.stream_port = group, port
            self._connected = True
            self._last_rx = self.clock()
        if group is not None:
            self._open_multicast(group, port)
        self.frame_rate_hz = self._ask_frame_rate()
        try:
            md = self._wait_for(codec.ModelDef, codec.RequestModelDef(), "MODELDEF")
        except ProtocolError as exc:
            by_name = [k for k, v in self.selectors.items() if v.needs_names]
            if by_name:
                raise ProtocolError(
                    f"{self.name}: cannot read Motive's model definitions ({exc}), so markers "
                    f"{by_name} cannot be found by name; select them by id "
                    "('lm:<model id>:<marker id>', 'rb:<body id>' or 'sk:<skeleton id>:<bone id>')"
                ) from exc
            self.log.warning("cannot read Motive's model definitions (%s); markers are selected by id", exc)
            md = None
        resolved = self._resolve(md)
        with self._cond:
            self.model_def = md
            self._resolved = resolved
            self._last_rx = self.clock()
            self._handshake_done = True

    def _transport(self, info: codec.ServerInfo) -> tuple[str | None, int | None]:
        """(multicast group or None for unicast, data port) from the server's announcement,
        checked against the ``multicast`` / ``data_port`` options."""
        where = f"{info.app_name} at {self.server}"
        if info.multicast is None:  # short SERVERINFO: the server announces nothing
            if self.multicast is None:
                return None, None
            return self.multicast, self.data_port or NATNET_DEFAULT_DATA_PORT
        if not info.multicast:
            if self.multicast is not None:
                raise ProtocolError(
                    f"{self.name}: {where} streams unicast (its Streaming Transmission Type is "
                    f"Unicast) but the sensor URL asks for multicast={self.multicast}. Remove the "
                    "multicast option (the driver follows what Motive announces), or set Motive's "
                    "Streaming Transmission Type to Multicast"
                )
            return None, None
        group, port = info.multicast_address, info.data_port
        if not _is_group(group) or not port:
            raise ProtocolError(
                f"{self.name}: {where} announces multicast streaming to {group}:{port}, which is "
                "not a multicast group and port; check Motive's Streaming pane (Multicast "
                "Interface, Data Port) or set its Transmission Type to Unicast"
            )
        for option, mine, theirs in (("multicast", self.multicast, group), ("data_port", self.data_port, port)):
            if mine is not None and mine != theirs:
                raise ProtocolError(
                    f"{self.name}: {where} announces multicast {group}:{port} but the sensor URL "
                    f"sets {option}={mine}. Remove the {option} option (the driver follows what "
                    f"Motive announces) or set it to {theirs}"
                )
        self.log.info("%s streams multicast %s:%d; joining on %s", where, group, port, self.local)
        return group, port

    def _ask_frame_rate(self) -> float | None:
        """REQUEST "FrameRate": Motive answers a float32 in frames per second
        (NatNet SDK NatNetRequests.h); None when it does not answer or makes no sense."""
        reply = self._wait_for((codec.Response, codec.UnrecognizedRequest), codec.Request("FrameRate"),
                               "reply to the frame-rate request", required=False)
        if not isinstance(reply, codec.Response) or reply.code is None:
            self.log.info("server gave no frame rate (%s)", reply)
            return None
        rate = reply.float32
        if not (math.isfinite(rate) and 0.0 < rate <= 10_000.0):
            self.log.warning("server's frame rate %r Hz makes no sense; ignored", rate)
            return None
        self.log.info("Motive tracks at %.3f Hz", rate)
        return rate

    def _negotiate_bitstream(self, announced: codec.Version, app: str) -> codec.Version:
        """With a 4.x server: ask for ``bitstream`` if set, else ask which version it streams
        now (the setting is global: another client may have changed it). Returns a version
        this codec reads or raises ProtocolError."""
        if self.bitstream is not None:
            want = f"{self.bitstream[0]}.{self.bitstream[1]}"
            reply = self._wait_for((codec.Response, codec.UnrecognizedRequest),
                                   codec.Request(f"Bitstream,{want}"), "reply to the bitstream request")
            if isinstance(reply, codec.Response) and reply.code == 0:
                self.log.info("server switched the stream to NatNet %s", want)
                return self.bitstream
            if announced[:2] > codec.MAX_VERSION[:2]:
                raise ProtocolError(
                    f"{self.name}: {app} at {self.server} streams NatNet {announced[0]}.{announced[1]} "
                    f"and refused 'Bitstream,{want}' ({reply}); this driver reads NatNet 3.0 to "
                    f"{codec.MAX_VERSION[0]}.{codec.MAX_VERSION[1]}, so it cannot read this server"
                )
            self.log.warning("server refused bitstream %s (%s); asking what it streams", want, reply)
        reply = self._wait_for((codec.Response, codec.UnrecognizedRequest),
                               codec.Request("Bitstream"), "reply to the bitstream query", required=False)
        text = reply.text if isinstance(reply, codec.Response) else None
        if text and text.startswith("Bitstream,"):
            try:
                now = codec.version_tuple(text.split(",", 1)[1])
            except ValueError as exc:
                raise ProtocolError(f"{self.name}: server streams {text!r}: {exc}") from exc
            if now[:2] > codec.MAX_VERSION[:2]:
                raise self._too_new(now, app)
            try:
                return codec.check_supported(now)
            except ValueError as exc:
                raise ProtocolError(f"{self.name}: server streams {text!r}: {exc}") from exc
        return announced

    def _open_multicast(self, group: str, port: int) -> None:
        data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            data.bind((group, port))  # only datagrams to the group reach this socket
            data.setsockopt(
                socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                socket.inet_aton(group) + socket.inet_aton(self.local),
            )
        except OSError as exc:
            data.close()
            raise ConnectionLostError(
                f"{self.name}: Motive at {self.server} streams multicast to {group}:{port}, but this "
                f"computer cannot receive it on interface {self.local}: {exc}. Either set the sensor "
                "URL option local=<this computer's IPv4 address on Motive's network>, free UDP port "
                f"{port} (another program holds it without sharing), or set Motive's Streaming "
                "Transmission Type to Unicast"
            ) from exc
        data.setblocking(False)
        with self._cond:
            self._data = data
        self.log.info("joined multicast %s:%d on %s", group, port, self.local)

    # ------------------------------------------------------------------ receiver thread
    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        registered: set[int] = set()
        next_keepalive = self.clock() + self.keepalive_interval_s
        next_reconnect = 0.0
        try:
            while not self._stop.is_set():
                for s in (self._cmd, self._data):
                    if s is not None and s.fileno() not in registered:
                        sel.register(s, selectors.EVENT_READ)
                        registered.add(s.fileno())
                for key, _ in sel.select(timeout=0.02):
                    self._drain(key.fileobj)
                now = self.clock()
                if not self._connected:
                    continue
                if self.stream_group is None and now >= next_keepalive:
                    self._send(codec.KeepAlive())
                    next_keepalive = now + self.keepalive_interval_s
                if (self.stream_group is None and now - self._last_rx > self.silence_timeout_s
                        and now >= next_reconnect):
                    self.log.warning("no frame for %.2f s; sending CONNECT again", now - self._last_rx)
                    self._send(codec.Connect("remaster", (0, 1, 0, 0), self.bitstream or (0, 0, 0, 0)))
                    next_reconnect = now + self.silence_timeout_s
        except OSError as exc:
            if not self._stop.is_set():
                self.log.error("NatNet receiver failed: %s", exc)
                with self._cond:
                    self._failure = exc
                    self._cond.notify_all()
        finally:
            sel.close()

    def _drain(self, sock: socket.socket) -> None:
        for _ in range(256):  # bounded: never starve the keep-alive
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return
            self._on_datagram(data, self.clock())

    def _on_datagram(self, data: bytes, host_time: float) -> None:
        try:
            msg_id = codec.peek_message_id(data)
            if msg_id == codec.NAT_FRAMEOFDATA:
                version = self.stream_version
                if version is None:
                    return  # before SERVERINFO we cannot know the layout
                self._on_frame(codec.decode_packet(data, version), host_time)
                return
            msg = codec.decode_packet(data, self.stream_version or codec.MIN_VERSION)
        except ProtocolError as exc:
            self.bad_packets += 1
            if data[:2] == b"\x05\x00" and self.model_def is None:  # MODELDEF during handshake
                with self._cond:
                    self._responses.append(exc)
                    self._cond.notify_all()
            if self.bad_packets <= 5 or self.bad_packets % 1000 == 0:
                self.log.warning(
                    "undecodable NatNet packet #%d (%d bytes): %s", self.bad_packets, len(data), exc
                )
            return
        if isinstance(msg, codec.ServerInfo) and self._handshake_done:
            self._on_server_info(msg)
            return
        if isinstance(msg, codec.ModelDef) and self._connected and self.model_def is not None:
            try:
                resolved = self._resolve(msg)
            except ValueError as exc:
                self.log.error("model definitions changed and no longer match the markers: %s", exc)
                return
            with self._cond:
                self.model_def, self._resolved = msg, resolved
            return
        if isinstance(msg, codec.MessageString):
            self.log.info("Motive says: %s", msg.text)
            return
        if self._pending_bitstream and isinstance(msg, (codec.Response, codec.UnrecognizedRequest)):
            with self._cond:
                self._pending_bitstream = False
                if isinstance(msg, codec.Response) and msg.code == 0:
                    self.stream_version = self.bitstream
                    self.log.info("server switched the stream back to NatNet %d.%d", *self.bitstream[:2])
                else:
                    self._stream_problem = (
                        f"Motive restarted and refused to stream NatNet {self.bitstream[0]}."
                        f"{self.bitstream[1]} again ({msg}); connect the sensor again")
                    self.log.error("%s", self._stream_problem)
            return
        with self._cond:
            self._responses.append(msg)
            del self._responses[:-16]
            self._cond.notify_all()

    def _on_frame(self, frame: codec.FrameOfData, host_time: float) -> None:
        n = frame.frame_number
        with self._cond:
            self._last_rx = host_time
            newest = self._newest
            reason = None
            if self._rejoined:  # first frame after a SERVERINFO: accept whatever its number
                self._rejoined = False
                if newest is not None and n <= newest:
                    reason = f"frame counter restarted at {n} (was {newest}) after a new SERVERINFO"
            elif newest is not None and n <= newest:
                run = self._old_run
                if run and n <= run[-1]:
                    run.clear()
                run.append(n)
                if newest - n <= self.reorder_window and len(run) < self.restart_run:
                    self.frames_stale += 1
                    return
                reason = f"frame counter went back from {newest} to {n}"
            self._old_run.clear()
            self._newest = n
            self._frame = frame
            self._frame_host_time = host_time
            self._seq += 1
            self.frames_accepted += 1
            self._cond.notify_all()
        if reason is not None:
            self.restarts += 1
            self.log.warning("NatNet server restarted (%s); re-reading model definitions", reason)
            self._send(codec.RequestModelDef())

    def _on_server_info(self, info: codec.ServerInfo) -> None:
        """A SERVERINFO after the handshake: the server (re)announced itself, e.g. answering
        our CONNECT after a silence. Take its version, restart ordering at its next frame.
        A changed transport (e.g. Motive switched to multicast) is logged with what to do: the
        sockets are chosen at connect(), so the sensor must be connected again."""
        version = codec.version_tuple(info.natnet_version)
        if version[:2] < codec.MIN_VERSION[:2] or (
                version[:2] > codec.MAX_VERSION[:2] and (self.bitstream is None or version[0] < 4)):
            problem = (f"Motive now announces NatNet {version[0]}.{version[1]}, which this driver "
                       f"cannot read, so its frames are dropped; set bitstream={codec.MAX_VERSION[0]}."
                       f"{codec.MAX_VERSION[1]} in the sensor URL and connect again")
            if problem != self._stream_problem:
                self.log.error("%s", problem)
            with self._cond:
                self.server_info = info
                self.stream_version = None  # never read a newer layout as an older one
                self._stream_problem = problem
            return
        if info.multicast is not None:
            now = (info.multicast_address, info.data_port) if info.multicast else (None, None)
            if now != (self.stream_group, self.stream_port):
                self.log.error(
                    "Motive now streams %s but this sensor listens to %s; connect the sensor again "
                    "to follow it", f"multicast {now[0]}:{now[1]}" if now[0] else "unicast",
                    f"multicast {self.stream_group}:{self.stream_port}" if self.stream_group else "unicast",
                )
        self.log.info("server re-announced itself (NatNet %d.%d)", *version[:2])
        with self._cond:
            self.server_info = info
            switch = self.bitstream is not None and version[0] >= 4 and self.bitstream[:2] != version[:2]
            # until the server confirms the switch, frames are dropped rather than misread
            if switch:
                self.stream_version = None
            else:
                self.stream_version = self.bitstream if self.bitstream and version[0] >= 4 else version
            self._pending_bitstream = switch
            self._stream_problem = None
            self._rejoined = True
        if switch:
            self._send(codec.Request(f"Bitstream,{self.bitstream[0]}.{self.bitstream[1]}"))
        self._send(codec.RequestModelDef())
