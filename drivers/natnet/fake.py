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
for ``sensor`` belongs to one asset (the tool plate), fitted and labeled as ``fake_asset``
describes. Positions go out in metres (Motive's default).

Fault hooks: ``set_faults(drop=, duplicate=, reorder=)`` (per-frame probabilities, seeded;
``fake_faults``), ``stall()`` / ``resume()`` (stop / restart sending frames; ``stall()``
before ``start()`` starts it silent), ``restart()`` (frame counter and clock reset, like a
Motive restart). Threads stop on ``close()`` or context exit.
"""

from __future__ import annotations

import logging
import socket
import threading
import time

from drivers.errors import ProtocolError
from drivers.natnet import codec
from drivers.natnet.fake_asset import ASSET_KINDS, BONE_ID, BONE_NAME, FakeAsset
from drivers.natnet.fake_faults import FrameFaults
from drivers.sim.scene import MarkerScene

__all__ = ["ASSET_KINDS", "BITSTREAM_VERSIONS", "BONE_ID", "BONE_NAME", "FakeMotive"]

log = logging.getLogger("remaster.fake.natnet")

#: Stream versions a fake 4.x server may switch to with ``Bitstream,X.Y``.
BITSTREAM_VERSIONS = {(3, 0), (3, 1), (4, 0), (4, 1)}
_TIMELINE_COMMANDS = ("TimelinePlay", "TimelineStop", "SetPlaybackCurrentFrame")


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
        self._asset = FakeAsset(scene, sensor, asset, rigid_body_id, rigid_body_name)
        self._faults = FrameFaults(seed)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._clients: dict[tuple[str, int], float] = {}
        self._frame_no = 0
        self._t0 = time.monotonic()
        self._stalled = False
        self._emitting = threading.Lock()  # held from the stall check to the frame's last send
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
        self._asset.learn_layout()
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
        self._faults.set(drop=drop, duplicate=duplicate, reorder=reorder)

    def stall(self) -> None:
        """Stop sending frames (commands are still answered) until ``resume()``. On return no
        frame is on its way: one the stream thread had already begun has been sent."""
        with self._emitting, self._lock:
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
            self._faults.forget_held()
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
        """The MODELDEF describing the asset (``fake_asset.FakeAsset.model_def``)."""
        return self._asset.model_def()

    def _ticks(self) -> int:
        return int(time.monotonic_ns() * self.clock_frequency // 1_000_000_000)

    def make_frame(self) -> codec.FrameOfData:
        """The next frame from the scene as it is now (advances the frame counter)."""
        now = self._ticks()
        with self._lock:
            frame_no = self._frame_no
            self._frame_no += 1
        frame = self._asset.frame(frame_no, frame_no / self.rate_hz, now, self.clock_frequency)
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
            with self._emitting:
                with self._lock:
                    stalled = self._stalled
                    version = self.stream_version
                if stalled:
                    continue
                packet = codec.encode_packet(self.make_frame(), version)
                for p in self._faults.apply(packet):
                    self._emit(p)

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
