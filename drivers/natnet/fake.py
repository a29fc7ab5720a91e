"""``FakeMotive``: a Motive server on loopback that speaks NatNet over real UDP sockets.

It answers CONNECT with SERVERINFO (NatNet ≥ 3.0 form: clock frequency, data port, multicast
flag and group, so a client learns how frames will arrive), REQUEST_MODELDEF with MODELDEF,
ECHOREQUEST, KEEPALIVE, REQUEST (``Bitstream``, ``Bitstream,X.Y``, ``FrameRate`` → float32
frames per second, ``AnalogSamplesPerMocapFrame`` → int32, ``UnitsToMillimeters`` → float32,
timeline commands; request names and reply types as in the NatNet SDK's
``NatNetRequests.h``) and streams FRAMEOFDATA at a fixed rate, unicast (from the command socket
to every client that sent CONNECT) or multicast as Motive does by default (from the data
socket to ``group:data_port``, default group 239.255.42.99, with ``IP_MULTICAST_IF`` =
127.0.0.1, ``IP_MULTICAST_LOOP`` on and TTL 0, so nothing leaves the host).

Frame content comes from a ``drivers.sim.scene.MarkerScene``: every marker the scene reports
for ``sensor`` belongs to one rigid body (the tool plate). The body's pose is fitted (Kabsch)
from its visible markers to the layout seen at start; with fewer than three visible markers
the body is untracked. Visible markers are labeled markers ``(body id, index + 1)``;
an invisible one is sent occluded at its model-predicted position while the body is tracked
and omitted otherwise. Positions go out in metres (Motive's default).

Fault hooks: ``set_faults(drop=, duplicate=, reorder=)`` (per-frame probabilities, seeded),
``stall()`` / ``resume()`` (stop / restart sending frames; ``stall()`` before ``start()``
starts it silent), ``restart()`` (frame counter and
clock reset, like a Motive restart). Threads stop on ``close()`` or context exit.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time

import numpy as np

from drivers.errors import ProtocolError
from drivers.natnet import codec
from drivers.sim.scene import MarkerScene

log = logging.getLogger("remaster.fake.natnet")

#: Stream versions a fake 4.x server may switch to with ``Bitstream,X.Y``.
BITSTREAM_VERSIONS = {(3, 0), (3, 1), (4, 0), (4, 1)}
#: What the scene's markers are in Motive: a rigid body (default), a one-bone skeleton, or a
#: NatNet 4.1 trained markerset with one bone. All share ``rigid_body_id`` / ``rigid_body_name``.
ASSET_KINDS = ("rigid_body", "skeleton", "trained_markerset")
#: The fake skeleton's / trained markerset's single bone: id and name.
BONE_ID, BONE_NAME = 1, "plate"
_TIMELINE_COMMANDS = ("TimelinePlay", "TimelineStop", "SetPlaybackCurrentFrame")


def _quat_xyzw(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a 3×3 rotation matrix."""
    m = r
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _kabsch(local: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t with ``seen ≈ local @ R.T + t``; local, seen shape (n, 3), n ≥ 3."""
    cl, cs = local.mean(axis=0), seen.mean(axis=0)
    h = (local - cl).T @ (seen - cs)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cs - r @ cl


class FakeMotive:
    """Fake OptiTrack Motive on 127.0.0.1.

    scene: gives the markers (``observe(sensor)``, positions in mm, sensor frame).
    rate_hz: frame rate, 120–360 Hz like a real system (other values are refused).
    natnet_version: the server's NatNet version, (3, 0), (3, 1), (4, 0) or (4, 1).
    multicast: stream to ``multicast_group:data_port`` instead of to unicast clients (Motive's
    default Transmission Type); SERVERINFO announces either.
    command_port, data_port: 0 picks a free port; the chosen ones are ``command_port`` /
    ``data_port`` after ``start()``.
    asset: what the scene's markers are (``ASSET_KINDS``): a rigid body ``rigid_body_id`` /
    ``rigid_body_name``; a skeleton of that id and name with one bone (``BONE_ID``,
    ``BONE_NAME``) whose labeled markers are (skeleton id, index + 1); or (NatNet 4.1 only) a
    trained markerset asset with that bone whose markers travel in the frame's asset section.
    analog_samples_per_frame: the int32 answer to ``AnalogSamplesPerMocapFrame``.
    """

    def __init__(
        self,
        scene: MarkerScene,
        *,
        sensor: str = "mocap",
        rate_hz: float = 120.0,
        natnet_version=(3, 0),
        multicast: bool = False,
        multicast_group: str = "239.255.42.99",
        command_port: int = 0,
        data_port: int = 0,
        rigid_body_id: int = 1,
        rigid_body_name: str = "tool",
        app_name: str = "Motive",
        app_version=(3, 1, 0, 0),
        clock_frequency: int = 10_000_000,
        client_timeout_s: float = 10.0,
        analog_samples_per_frame: int = 0,
        asset: str = "rigid_body",
        seed: int = 0,
    ) -> None:
        if not 120.0 <= rate_hz <= 360.0:
            raise ValueError(f"rate_hz must be within 120–360 Hz like Motive, got {rate_hz}")
        version = codec.version_tuple(natnet_version)
        if version[:2] not in BITSTREAM_VERSIONS:
            raise ValueError(
                f"natnet_version {version[:2]} not offered; choose one of {sorted(BITSTREAM_VERSIONS)}"
            )
        if not 1 <= rigid_body_id <= 0xFFFF:
            raise ValueError(f"rigid_body_id must be 1..65535, got {rigid_body_id}")
        if asset not in ASSET_KINDS:
            raise ValueError(f"asset must be one of {', '.join(ASSET_KINDS)}, got {asset!r}")
        if asset == "trained_markerset" and version[:2] < (4, 1):
            raise ValueError(f"a trained_markerset asset needs NatNet 4.1, got natnet_version {version[:2]}")
        if not (isinstance(analog_samples_per_frame, int) and analog_samples_per_frame >= 0):
            raise ValueError(f"analog_samples_per_frame must be an int ≥ 0, got {analog_samples_per_frame!r}")
        self.scene = scene
        self.sensor = sensor
        self.rate_hz = float(rate_hz)
        self.server_version: codec.Version = version
        self.stream_version: codec.Version = version
        self.multicast = multicast
        self.multicast_group = multicast_group
        self.rigid_body_id = rigid_body_id
        self.rigid_body_name = rigid_body_name
        self.app_name = app_name
        self.app_version = codec.version_tuple(app_version)
        self.clock_frequency = int(clock_frequency)
        self.client_timeout_s = client_timeout_s
        self.analog_samples_per_frame = analog_samples_per_frame
        self.asset = asset
        self._want_ports = (command_port, data_port)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._clients: dict[tuple[str, int], float] = {}
        self._marker_names: list[str] = []
        self._layout_m: np.ndarray | None = None  # (n, 3) reference layout about its centroid
        self._frame_no = 0
        self._t0 = time.monotonic()
        self._held: bytes | None = None  # a frame held back for reordering
        self._drop = self._dup = self._reorder = 0.0
        self._stalled = False
        self._last_frame: codec.FrameOfData | None = None
        #: Counters for tests: frames sent (after faults), commands answered, bad packets,
        #: keep-alives received, and the text of every REQUEST.
        self.frames_sent = 0
        self.commands_answered = 0
        self.bad_packets = 0
        self.keepalives = 0
        self.requests: list[str] = []

    # ------------------------------------------------------------------ lifecycle
    @property
    def command_port(self) -> int:
        if self._cmd is None:
            raise RuntimeError("FakeMotive is not started")
        return self._cmd.getsockname()[1]

    @property
    def data_port(self) -> int:
        if self._data is None:
            raise RuntimeError("FakeMotive is not started")
        return self._data.getsockname()[1]

    @property
    def clients(self) -> list[tuple[str, int]]:
        with self._lock:
            return list(self._clients)

    def start(self) -> "FakeMotive":
        if self._cmd is not None:
            raise RuntimeError("FakeMotive already started")
        obs = self.scene.observe(self.sensor)
        if not obs:
            raise ValueError(f"scene reports no markers for sensor {self.sensor!r}")
        self._marker_names = [o.name for o in obs]
        pos_m = np.array([o.position_mm for o in obs], dtype=float) / 1000.0
        self._layout_m = pos_m - pos_m.mean(axis=0)
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            cmd.bind(("127.0.0.1", self._want_ports[0]))
            cmd.settimeout(0.05)
            data.bind(("127.0.0.1", self._want_ports[1]))
            data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
            data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        except OSError:
            cmd.close()
            data.close()
            raise
        self._cmd, self._data = cmd, data
        self._t0 = time.monotonic()
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._serve_commands, name="fake-motive-cmd", daemon=True),
            threading.Thread(target=self._stream, name="fake-motive-stream", daemon=True),
        ]
        for t in self._threads:
            t.start()
        log.info(
            "fake Motive NatNet %d.%d on 127.0.0.1 command %d data %d (%s, %.0f Hz)",
            *self.server_version[:2], self.command_port, self.data_port,
            f"multicast {self.multicast_group}" if self.multicast else "unicast", self.rate_hz,
        )
        return self

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        for s in (self._cmd, self._data):
            if s is not None:
                s.close()
        self._cmd = self._data = None

    def __enter__(self) -> "FakeMotive":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ fault hooks
    def set_faults(self, *, drop: float = 0.0, duplicate: float = 0.0, reorder: float = 0.0) -> None:
        """Per-frame probabilities of dropping, sending twice, or swapping with the next."""
        for name, p in (("drop", drop), ("duplicate", duplicate), ("reorder", reorder)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} probability must be within [0, 1], got {p}")
        with self._lock:
            self._drop, self._dup, self._reorder = drop, duplicate, reorder

    def stall(self) -> None:
        """Stop sending frames (commands are still answered) until ``resume()``."""
        with self._lock:
            self._stalled = True

    def resume(self) -> None:
        with self._lock:
            self._stalled = False

    def restart(self, *, forget_clients: bool = False) -> None:
        """Act like a restarted Motive: frame counter and clock from zero, stream version back
        to the server's; ``forget_clients`` also drops every unicast client."""
        with self._lock:
            self._frame_no = 0
            self._t0 = time.monotonic()
            self._held = None
            self.stream_version = self.server_version
            if forget_clients:
                self._clients.clear()

    # ------------------------------------------------------------------ content
    def server_info(self) -> codec.ServerInfo:
        return codec.ServerInfo(
            self.app_name, self.app_version, self.server_version, self.clock_frequency,
            self.data_port, self.multicast, self.multicast_group,
        )

    def model_def(self) -> codec.ModelDef:
        assert self._layout_m is not None
        markers = tuple(
            codec.RigidBodyMarkerDescription(tuple(float(v) for v in p), 0, name)
            for p, name in zip(self._layout_m, self._marker_names)
        )
        marker_set = codec.MarkerSetDescription(self.rigid_body_name, tuple(self._marker_names))
        if self.asset == "rigid_body":
            body = codec.RigidBodyDescription(self.rigid_body_name, self.rigid_body_id, -1, (0.0, 0.0, 0.0), markers)
            return codec.ModelDef((body, marker_set))
        bone = codec.RigidBodyDescription(BONE_NAME, BONE_ID, -1, (0.0, 0.0, 0.0), markers)
        if self.asset == "skeleton":
            skeleton = codec.SkeletonDescription(self.rigid_body_name, self.rigid_body_id, (bone,))
            return codec.ModelDef((marker_set, skeleton))
        asset_markers = tuple(
            codec.AssetMarkerDescription(name, (self.rigid_body_id << 16) | (i + 1),
                                         tuple(float(v) for v in p), 0.014, 0)
            for i, (p, name) in enumerate(zip(self._layout_m, self._marker_names))
        )
        return codec.ModelDef((marker_set, codec.AssetDescription(
            self.rigid_body_name, 0, self.rigid_body_id, (bone,), asset_markers)))

    def _ticks(self) -> int:
        return int(time.monotonic_ns() * self.clock_frequency // 1_000_000_000)

    def make_frame(self) -> codec.FrameOfData:
        """The next frame from the scene as it is now (advances the frame counter)."""
        assert self._layout_m is not None
        obs = self.scene.observe(self.sensor)
        by_name = {o.name: o for o in obs}
        n = len(self._marker_names)
        seen = np.full((n, 3), np.nan)
        vis = np.zeros(n, dtype=bool)
        for i, name in enumerate(self._marker_names):
            o = by_name.get(name)
            if o is not None:
                seen[i] = np.asarray(o.position_mm, dtype=float) / 1000.0
                vis[i] = bool(o.visible)
        tracked = int(vis.sum()) >= 3
        rb = np.zeros(1, dtype=codec.RIGID_BODY_DTYPE)
        rb["id"] = self.rigid_body_id
        predicted = None
        if tracked:
            r, t = _kabsch(self._layout_m[vis], seen[vis])
            predicted = self._layout_m @ r.T + t
            err = np.linalg.norm(predicted[vis] - seen[vis], axis=1)
            rb["pos"] = t
            rb["quat"] = _quat_xyzw(r)
            rb["mean_error"] = float(err.mean())
            rb["params"] = codec.RIGID_BODY_TRACKED
        else:
            rb["quat"] = (0.0, 0.0, 0.0, 1.0)
        rows = []
        for i in range(n):
            mid = (self.rigid_body_id << 16) | (i + 1)
            if vis[i]:
                res = float(np.linalg.norm(predicted[i] - seen[i])) if predicted is not None else 0.0
                rows.append((mid, seen[i], 0.014, codec.MARKER_PC_SOLVED | codec.MARKER_HAS_MODEL, res))
            elif predicted is not None:
                flags = codec.MARKER_OCCLUDED | codec.MARKER_MODEL_SOLVED | codec.MARKER_HAS_MODEL
                rows.append((mid, predicted[i], 0.014, flags, 0.0))
        labeled = np.zeros(len(rows), codec.LABELED_MARKER_DTYPE)
        for k, row in enumerate(rows):
            labeled[k] = row
        set_pos = np.where(vis[:, None], seen, predicted if predicted is not None else 0.0)
        now = self._ticks()
        with self._lock:
            frame_no = self._frame_no
            self._frame_no += 1
        skeletons, assets = (), ()
        if self.asset != "rigid_body":  # the plate is the asset's one bone
            rb["id"] = (self.rigid_body_id << 16) | BONE_ID
            if self.asset == "skeleton":
                skeletons = (codec.SkeletonData(self.rigid_body_id, rb),)
            else:  # trained markerset: its markers go with the asset, not the labeled list
                assets = (codec.AssetData(self.rigid_body_id, rb, labeled),)
                labeled = labeled[:0]
            rb = rb[:0]
        frame = codec.FrameOfData(
            frame_number=frame_no,
            marker_sets=(codec.MarkerSetData(self.rigid_body_name, set_pos.astype("<f4")),),
            unlabeled=seen[vis].astype("<f4").reshape(-1, 3),
            rigid_bodies=rb,
            skeletons=skeletons,
            assets=assets,
            labeled_markers=labeled,
            timestamp=frame_no / self.rate_hz,
            stamp_camera_mid_exposure=now - self.clock_frequency // 200,
            stamp_data_received=now - self.clock_frequency // 1000,
            stamp_transmit=now,
        )
        self._last_frame = frame
        return frame

    # ------------------------------------------------------------------ threads
    def _send(self, packet: bytes, addr) -> None:
        sock = self._cmd
        if sock is None:
            return
        try:
            sock.sendto(packet, addr)
        except OSError as exc:  # a vanished client must not stop the server
            log.debug("fake Motive: send to %s failed: %s", addr, exc)

    def _serve_commands(self) -> None:
        sock = self._cmd
        assert sock is not None
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError as exc:
                if self._stop.is_set():
                    return
                log.warning("fake Motive: command socket error: %s", exc)
                continue
            try:
                msg = codec.decode_packet(data, self.stream_version)
            except ProtocolError as exc:
                self.bad_packets += 1
                log.debug("fake Motive: bad packet from %s: %s", addr, exc)
                continue
            reply = self._answer(msg, addr)
            if reply is not None:
                self._send(codec.encode_packet(reply, self.stream_version), addr)
                self.commands_answered += 1

    def _answer(self, msg, addr):
        now = time.monotonic()
        if isinstance(msg, codec.Discovery):
            return self.server_info()
        if isinstance(msg, codec.Connect):
            with self._lock:
                self._clients[addr] = now
            return self.server_info()
        if isinstance(msg, codec.KeepAlive):
            self.keepalives += 1
            with self._lock:
                if addr in self._clients:
                    self._clients[addr] = now
            return None
        if isinstance(msg, codec.Disconnect):
            with self._lock:
                self._clients.pop(addr, None)
            return None
        if isinstance(msg, codec.RequestModelDef):
            return self.model_def()
        if isinstance(msg, codec.RequestFrameOfData):
            return self._last_frame or self.make_frame()
        if isinstance(msg, codec.EchoRequest):
            return codec.EchoResponse(msg.client_stamp, self._ticks())
        if isinstance(msg, codec.Request):
            self.requests.append(msg.command)
            return self._answer_request(msg.command)
        return None

    def _answer_request(self, command: str):
        parts = [p.strip() for p in command.split(",")]
        if parts[0] == "Bitstream":
            if self.server_version[0] < 4:
                return codec.UnrecognizedRequest()
            if len(parts) == 1:
                return codec.Response(text=f"Bitstream,{self.stream_version[0]}.{self.stream_version[1]}")
            try:
                want = codec.version_tuple(parts[1])
            except ValueError:
                return codec.Response(code=1)
            if want[:2] not in BITSTREAM_VERSIONS or (self.asset == "trained_markerset" and want[:2] < (4, 1)):
                return codec.Response(code=1)
            with self._lock:
                self.stream_version = want
            log.info("fake Motive: bitstream now NatNet %d.%d", *want[:2])
            return codec.Response(code=0)
        if parts[0] == "FrameRate":
            return codec.Response.of_float32(self.rate_hz)
        if parts[0] == "AnalogSamplesPerMocapFrame":
            return codec.Response(code=self.analog_samples_per_frame)
        if parts[0] == "UnitsToMillimeters":
            return codec.Response.of_float32(1000.0)  # streams metres
        if parts[0] in _TIMELINE_COMMANDS:
            return codec.Response(code=0)
        return codec.UnrecognizedRequest()

    def _stream(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            delay = next_t - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            next_t += period
            if next_t < time.monotonic() - period:  # fell behind (busy host): resync
                next_t = time.monotonic() + period
            with self._lock:
                stalled = self._stalled
                version = self.stream_version
            if stalled:
                continue
            packet = codec.encode_packet(self.make_frame(), version)
            for p in self._apply_faults(packet):
                self._emit(p)

    def _apply_faults(self, packet: bytes) -> list[bytes]:
        with self._lock:
            drop, dup, reorder = self._drop, self._dup, self._reorder
            u = self._rng.random(3)
            if drop and u[0] < drop:
                return []
            out = [packet, packet] if dup and u[1] < dup else [packet]
            if self._held is not None:
                out.append(self._held)  # the held-back older frame goes after this newer one
                self._held = None
            elif reorder and u[2] < reorder:
                self._held = packet
                out = out[1:]
            return out

    def _emit(self, packet: bytes) -> None:
        self.frames_sent += 1
        if self.multicast:
            data = self._data
            if data is not None:
                try:
                    data.sendto(packet, (self.multicast_group, self.data_port))
                except OSError as exc:
                    log.debug("fake Motive: multicast send failed: %s", exc)
            return
        now = time.monotonic()
        with self._lock:
            for addr, seen in list(self._clients.items()):
                if now - seen > self.client_timeout_s:
                    log.info("fake Motive: unicast client %s timed out (no keep-alive)", addr)
                    del self._clients[addr]
            clients = list(self._clients)
        for addr in clients:
            self._send(packet, addr)
