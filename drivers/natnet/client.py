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

_NAN3 = np.full(3, np.nan)
_NAN3.flags.writeable = False


@dataclass(frozen=True, slots=True)
class MarkerSelector:
    """What one plan marker is on the NatNet stream.

    kind "rb": a rigid body (``body`` = id or name) reported by its pivot position;
    kind "lm": a labeled marker (``model`` id, ``marker`` id);
    kind "ms": a marker named in the model definitions (``body`` = marker set / rigid body
    name, ``name`` = marker name), resolved to a labeled marker once definitions arrive.
    """

    kind: str
    body: str | int | None = None
    model: int | None = None
    marker: int | None = None
    name: str | None = None

    SYNTAX = "'rb:<body id or name>', 'lm:<model id>:<marker id>' or 'ms:<marker set>:<marker name>'"

    @classmethod
    def parse(cls, text: str) -> "MarkerSelector":
        if not isinstance(text, str):
            raise TypeError(f"marker selector must be a string ({cls.SYNTAX}), got {text!r}")
        kind, _, rest = text.partition(":")
        if kind == "rb" and rest:
            return cls("rb", body=int(rest) if rest.lstrip("-").isdigit() else rest)
        if kind == "lm":
            a, _, b = rest.partition(":")
            if a.isdigit() and b.isdigit() and int(a) <= 0xFFFF and int(b) <= 0xFFFF:
                return cls("lm", model=int(a), marker=int(b))
        if kind == "ms":
            a, _, b = rest.partition(":")
            if a and b:
                return cls("ms", body=a, name=b)
        raise ValueError(f"marker selector {text!r} is not one of {cls.SYNTAX}")


class NatNetSensor(SensorBase):
    """Marker positions (mm, Motive's frame) from an OptiTrack Motive server over NatNet.

    URL (``from_url``)::

        natnet://<server ip>[:<command port>]?<option>=<value>&...

    options: ``command_port`` (default 1510), ``data_port`` (multicast only; default: the
    port SERVERINFO announces), ``multicast`` (group address, e.g. 239.255.42.99; absent =
    unicast), ``local`` (local interface address, default 127.0.0.1), ``bitstream`` (e.g.
    ``4.1``: ask a NatNet 4.x server for that stream version), ``silence_timeout`` (s),
    ``units`` (``m``, Motive's default, or ``mm``: the unit positions arrive in), ``name``.
    Example: ``natnet://127.0.0.1?command_port=1510&data_port=1511&multicast=239.255.42.99&local=127.0.0.1``.

    markers: plan marker name → selector: ``"rb:<body id or name>"`` (a rigid body's pivot
    reported as a marker, visible while Motive tracks it), ``"lm:<model id>:<marker id>"``
    (a labeled marker) or ``"ms:<marker set>:<marker name>"`` (a marker named in the model
    definitions; it becomes labeled marker (id of the rigid body with that name, index + 1)).

    Handshake on ``connect()``: CONNECT → SERVERINFO (retried, ``handshake_timeout_s``), then
    (``bitstream`` set and a 4.x server) REQUEST ``Bitstream,X.Y`` → RESPONSE 0, then
    REQUEST_MODELDEF → MODELDEF. Frames are decoded with the server's NatNet version unless a
    bitstream change was accepted. Unicast clients send KEEPALIVE every
    ``keepalive_interval_s``; frames come to the command socket (unicast) or the multicast
    group on the data port.

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
        local: str = "127.0.0.1",
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
        self.local = local
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
        if self._cmd is not None and self.multicast is None and self._connected:
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
                        f"{self.name}: no NatNet frame from {self.server}:{self.command_port} for "
                        f"{silent:.3f} s (silence limit {self.silence_timeout_s} s); "
                        "is Motive running and streaming?"
                    )
                if now >= deadline:
                    raise DeviceTimeoutError(f"{self.name}: no new NatNet frame within {timeout:.3g} s")
                self._cond.wait(min(deadline, self._last_rx + self.silence_timeout_s) - now)
        return self._samples(frame, host_time, resolved)

    # ------------------------------------------------------------------ samples
    def _samples(self, frame: codec.FrameOfData, host_time: float, resolved) -> list[MarkerSample]:
        out = []
        lm = frame.labeled_markers
        rbs = frame.rigid_bodies
        for plan_name, (kind, ident) in resolved.items():
            pos, visible, residual = _NAN3, False, None
            if kind == "rb":
                hit = np.flatnonzero(rbs["id"] == ident)
                if hit.size:
                    row = rbs[hit[0]]
                    pos = row["pos"].astype(np.float64) * self.scale_mm
                    visible = bool(row["params"] & codec.RIGID_BODY_TRACKED)
                    residual = float(row["mean_error"]) * self.scale_mm
            elif kind == "lm":
                hit = np.flatnonzero(lm["id"] == ident)
                if hit.size:
                    row = lm[hit[0]]
                    pos = row["pos"].astype(np.float64) * self.scale_mm
                    visible = not (row["params"] & codec.MARKER_OCCLUDED)
                    residual = float(row["residual"]) * self.scale_mm
            if visible and not np.all(np.isfinite(pos)):
                visible = False
            out.append(MarkerSample(plan_name, pos, frame.timestamp, host_time, visible, None, residual))
        for plan_name in self.selectors:
            if plan_name not in resolved:
                out.append(MarkerSample(plan_name, _NAN3, frame.timestamp, host_time, False))
        return out

    def _resolve(self, md: codec.ModelDef | None) -> dict[str, tuple[str, int]]:
        """Selectors → ("rb", body id) / ("lm", model << 16 | marker). Names need ``md``."""
        bodies = {d.name: d.id for d in md.rigid_bodies} if md else {}
        sets = {d.name: d.marker_names for d in md.marker_sets} if md else {}
        out: dict[str, tuple[str, int]] = {}
        for plan_name, sel in self.selectors.items():
            if sel.kind == "lm":
                out[plan_name] = ("lm", (sel.model << 16) | sel.marker)
            elif sel.kind == "rb" and isinstance(sel.body, int):
                out[plan_name] = ("rb", sel.body)
            elif md is None:
                continue
            elif sel.kind == "rb":
                if sel.body not in bodies:
                    raise ValueError(
                        f"{self.name}: marker {plan_name!r}: no rigid body named {sel.body!r}; "
                        f"Motive defines {sorted(bodies)}"
                    )
                out[plan_name] = ("rb", bodies[sel.body])
            else:  # ms
                names = sets.get(sel.body)
                if names is None or sel.name not in names:
                    raise ValueError(
                        f"{self.name}: marker {plan_name!r}: no marker {sel.name!r} in marker set "
                        f"{sel.body!r}; Motive defines "
                        + "; ".join(f"{k}: {', '.join(v)}" for k, v in sets.items())
                    )
                if sel.body not in bodies:
                    raise ValueError(
                        f"{self.name}: marker {plan_name!r}: marker set {sel.body!r} has no rigid "
                        "body of the same name, so its labeled-marker ids are unknown; select it "
                        "as 'lm:<model id>:<marker id>'"
                    )
                out[plan_name] = ("lm", (bodies[sel.body] << 16) | (names.index(sel.name) + 1))
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
        after ``handshake_timeout_s`` raise DeviceTimeoutError (or return None if not required)."""
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
                    f"{self.handshake_timeout_s} s; is Motive running with streaming enabled "
                    f"({'multicast ' + self.multicast if self.multicast else 'unicast'})?"
                )

    def _handshake(self) -> None:
        info = self._wait_for(
            codec.ServerInfo,
            codec.Connect("remaster", (0, 1, 0, 0), self.bitstream or (0, 0, 0, 0), "natnetlib"),
            "SERVERINFO",
        )
        try:
            version = codec.check_supported(info.natnet_version)
        except ValueError as exc:
            raise ProtocolError(f"{self.name}: {info.app_name} speaks {exc}") from exc
        self.log.info(
            "connected to %s %s (NatNet %s) at %s:%d",
            info.app_name, ".".join(map(str, info.app_version)), ".".join(map(str, version)),
            self.server, self.command_port,
        )
        if self.multicast and info.multicast is False:
            self.log.warning("server says it streams unicast, but multicast %s was asked for", self.multicast)
        if version[0] >= 4:
            version = self._negotiate_bitstream(version)
        elif self.bitstream is not None and self.bitstream[:2] != version[:2]:
            self.log.warning("NatNet %d.%d server cannot change its bitstream; decoding %d.%d",
                             *version[:2], *version[:2])
        with self._cond:
            self.server_info = info
            self.stream_version = version
            self._connected = True
            self._last_rx = self.clock()
        if self.multicast is not None:
            self._open_multicast(self.data_port or info.data_port or 1511)
        try:
            md = self._wait_for(codec.ModelDef, codec.RequestModelDef(), "MODELDEF")
        except ProtocolError as exc:
            by_name = [k for k, v in self.selectors.items()
                       if v.kind == "ms" or (v.kind == "rb" and isinstance(v.body, str))]
            if by_name:
                raise ProtocolError(
                    f"{self.name}: cannot read Motive's model definitions ({exc}), so markers "
                    f"{by_name} cannot be found by name; select them by id "
                    "('lm:<model id>:<marker id>' or 'rb:<body id>')"
                ) from exc
            self.log.warning("cannot read Motive's model definitions (%s); markers are selected by id", exc)
            md = None
        resolved = self._resolve(md)
        with self._cond:
            self.model_def = md
            self._resolved = resolved
            self._last_rx = self.clock()

    def _negotiate_bitstream(self, announced: codec.Version) -> codec.Version:
        """With a 4.x server: ask for ``bitstream`` if set, else ask which version it streams
        now (the setting is global: another client may have changed it)."""
        if self.bitstream is not None:
            want = f"{self.bitstream[0]}.{self.bitstream[1]}"
            reply = self._wait_for((codec.Response, codec.UnrecognizedRequest),
                                   codec.Request(f"Bitstream,{want}"), "reply to the bitstream request")
            if isinstance(reply, codec.Response) and reply.code == 0:
                self.log.info("server switched the stream to NatNet %s", want)
                return self.bitstream
            self.log.warning("server refused bitstream %s (%s); asking what it streams", want, reply)
        reply = self._wait_for((codec.Response, codec.UnrecognizedRequest),
                               codec.Request("Bitstream"), "reply to the bitstream query", required=False)
        text = reply.text if isinstance(reply, codec.Response) else None
        if text and text.startswith("Bitstream,"):
            try:
                return codec.check_supported(text.split(",", 1)[1])
            except ValueError as exc:
                raise ProtocolError(f"{self.name}: server streams {text!r}: {exc}") from exc
        return announced

    def _open_multicast(self, port: int) -> None:
        assert self.multicast is not None
        data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            data.bind((self.multicast, port))  # only datagrams to the group reach this socket
            data.setsockopt(
                socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                socket.inet_aton(self.multicast) + socket.inet_aton(self.local),
            )
        except OSError as exc:
            data.close()
            raise ConnectionLostError(
                f"{self.name}: cannot join multicast {self.multicast}:{port} on {self.local}: {exc}"
            ) from exc
        data.setblocking(False)
        with self._cond:
            self._data = data
        self.log.info("joined multicast %s:%d on %s", self.multicast, port, self.local)

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
                if self.multicast is None and now >= next_keepalive:
                    self._send(codec.KeepAlive())
                    next_keepalive = now + self.keepalive_interval_s
                if (self.multicast is None and now - self._last_rx > self.silence_timeout_s
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
        if isinstance(msg, codec.ServerInfo) and self._connected:
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
        our CONNECT after a silence. Take its version, restart ordering at its next frame."""
        try:
            version = codec.check_supported(info.natnet_version)
        except ValueError:
            self.log.error("server now speaks unsupported NatNet %s", info.natnet_version)
            return
        self.log.info("server re-announced itself (NatNet %d.%d)", *version[:2])
        with self._cond:
            self.server_info = info
            if self.bitstream is None or version[0] < 4:
                self.stream_version = version
            self._rejoined = True
        if self.bitstream is not None and version[0] >= 4 and self.bitstream[:2] != version[:2]:
            self._send(codec.Request(f"Bitstream,{self.bitstream[0]}.{self.bitstream[1]}"))
        self._send(codec.RequestModelDef())
