"""``TrackerSensor``: the laser tracker as a ``PositionSensor``, over any pyserial URL.

``socket://host:port`` (a TCP tracker or the fake), ``/dev/ttyUSB0`` or a pty path (RS-232),
``loop://`` (pyserial's in-process loopback) are one code path. The codec (``LineCodec`` by
default) is separate from the transport, so a vendor protocol can be plugged in as another codec.

One request is in flight at a time (a lock serialises callers, so ``asyncio.to_thread`` is
safe). Replies are matched to requests by id; a stale reply (from a request that timed out) is
discarded, unsolicited events (``BEAM_LOST`` / ``BEAM_LOCKED``) are logged and kept in
``events``.

Errors: no reply in time → DeviceTimeoutError; transport closed → ConnectionLostError (after
one transparent reconnect-and-retry when ``auto_reconnect`` is set); an unreadable line →
ProtocolError; a device ``ERR`` reply → the class in ``ERROR_CLASSES`` (beam lost →
TargetLostError, IFM distance lost → DistanceLostError, warming up → TrackerWarmingUpError ...).
"""

from __future__ import annotations

import collections
import math
import select
import socket
import threading
import time
from typing import Any, Callable

import numpy as np
import serial

from drivers.base import Clock, SensorBase, check_timeout
from drivers.errors import (
    ConnectionLostError,
    DeviceFaultError,
    DeviceTimeoutError,
    DistanceLostError,
    LimitError,
    ProtocolError,
    TargetLostError,
    TrackerWarmingUpError,
)
from drivers.protocols import MarkerMeasurement, MarkerSample
from drivers.tracker.air import STATION, Air, parse_environment, parse_reflector
from drivers.tracker.codec import (
    MAX_AVERAGE,
    MAX_RID,
    REPLY_FOR,
    Aim,
    AimReply,
    Environment,
    EnvironmentReply,
    ErrorCode,
    ErrorReply,
    Event,
    GetStatus,
    Home,
    Identify,
    IdentifyReply,
    LineCodec,
    MeasureAverage,
    MeasurePose,
    MeasurePoint,
    Mode,
    ModeReply,
    ReflectorReply,
    Search,
    SearchReply,
    SelectReflector,
    SetMode,
    StatusReply,
    TrackerCodec,
)


#: Exception class for each device error code; other codes raise DeviceFaultError.
ERROR_CLASSES: dict[int, type[Exception]] = {
    ErrorCode.SYNTAX: ProtocolError,
    ErrorCode.UNKNOWN_COMMAND: ProtocolError,
    ErrorCode.BAD_ARGUMENT: LimitError,
    ErrorCode.BEAM_LOST: TargetLostError,
    ErrorCode.DISTANCE_INVALID: DistanceLostError,
    ErrorCode.WARMING_UP: TrackerWarmingUpError,
    ErrorCode.NO_WEATHER_STATION: DeviceFaultError,
    ErrorCode.NOT_6DOF: DeviceFaultError,
}

#: Commands safe to send again after a reconnect (a search restarts from where the beam is).
_IDEMPOTENT = (Identify, GetStatus, SetMode, MeasurePoint, MeasureAverage, MeasurePose, Aim, Home, Environment, SelectReflector)


class LinePort:
    """A pyserial port read as frames with a deadline, without per-byte reads where possible.

    Ports with a file descriptor (TCP sockets, serial devices, ptys) are read non-blocking
    after ``select``; others (``loop://``) with pyserial's own timeout.
    """

    def __init__(self, port: serial.SerialBase, framer: Callable[[bytearray], list[bytes]]) -> None:
        self.port = port
        self.framer = framer
        self.buffer = bytearray()
        self.frames: collections.deque[bytes] = collections.deque()
        try:
            self.fd: int | None = port.fileno()
        except (OSError, ValueError, AttributeError):
            self.fd = None

    def write(self, data: bytes) -> None:
        self.port.write(data)
        self.port.flush()

    def read_frame(self, deadline: float) -> bytes | None:
        """The next frame, or None when ``deadline`` (time.monotonic) passes."""
        while not self.frames:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            if self.fd is not None:
                ready, _, _ = select.select([self.fd], [], [], remaining)
                if not ready:
                    return None
                data = self.port.read(4096)  # timeout 0: whatever is there
                if not data:
                    # readable but empty: EOF on a socket / hang-up on a tty
                    raise serial.SerialException("device disconnected (readable but no data)")
            else:
                self.port.timeout = remaining
                data = self.port.read(1)
                if not data:
                    return None
                waiting = self.port.in_waiting
                if waiting:
                    data += self.port.read(waiting)
            self.buffer += data
            self.frames.extend(self.framer(self.buffer))
        return self.frames.popleft()

    def close(self) -> None:
        sock = getattr(self.port, "_socket", None)
        if sock is None:
            self.port.close()
            return
        # pyserial's socket:// close() leaks the socket when shutdown() fails (the peer hung up
        # first) and then sleeps 0.3 s; close the socket ourselves and mark the port closed.
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        sock.close()
        self.port._socket = None
        self.port.is_open = False


class TrackerSensor(SensorBase):
    """A laser tracker that measures one reflector (``marker``), tracker frame, mm.

    url: any pyserial URL. reply_timeout: seconds allowed for an ordinary reply (commands that
    take device time get that time on top). ``serial_options`` go to ``serial_for_url``
    (``baudrate`` ...). The connection opens in ``connect()`` (or ``with``).

    environment: the air for the refraction correction, sent on connect (``ENV``): an ``Air``,
    ``"station"`` (the tracker's weather station) or the plan's mapping; None leaves the
    tracker's setting. reflector: the reflector type (``"RRR15"``) or ``{type, offset_mm}``,
    selected on connect (``REFL``); None leaves it. pose: the target is a 6-DoF target (a T-Mac,
    a probe): ``measure`` asks for its pose (``POSE``) and returns its orientation
    ``R_tracker←target`` and attitude spread with the position.
    """

    def __init__(
        self,
        url: str,
        *,
        marker: str = "smr",
        name: str = "tracker",
        reply_timeout: float = 2.0,
        auto_reconnect: bool = True,
        codec: TrackerCodec | None = None,
        clock: Clock = time.monotonic,
        environment: Air | str | dict | None = None,
        reflector: str | dict | None = None,
        pose: bool = False,
        **serial_options: Any,
    ) -> None:
        super().__init__(name, clock=clock)
        if not isinstance(url, str) or not url:
            raise ValueError(f"url must be a pyserial URL such as socket://127.0.0.1:7000 or /dev/ttyUSB0, got {url!r}")
        if not isinstance(marker, str) or not marker:
            raise ValueError(f"marker must be a non-empty name, got {marker!r}")
        self.url = url
        self.marker = marker
        self.reply_timeout = check_timeout(reply_timeout)
        self.auto_reconnect = auto_reconnect
        self.codec = codec or LineCodec(require_checksum=True)
        self.serial_options = serial_options
        self.environment = parse_environment(environment)
        self.reflector = parse_reflector(reflector)
        if not isinstance(pose, bool):
            raise ValueError(f"pose must be true (a 6-DoF target) or false, got {pose!r}")
        self.pose = pose
        #: what the tracker reported on the last ENV / REFL exchange
        self.air_in_use: EnvironmentReply | None = None
        self.reflector_in_use: ReflectorReply | None = None
        self.events: collections.deque[tuple[Event, float]] = collections.deque(maxlen=256)
        self._port: LinePort | None = None
        self._lock = threading.RLock()
        self._rid = 0
        self._average_supported = True

    @classmethod
    def from_url(cls, url: str, marker: str = "smr", **kwargs: Any) -> "TrackerSensor":
        """A connected sensor for ``url``."""
        sensor = cls(url, marker=marker, **kwargs)
        sensor.connect()
        return sensor

    # ----------------------------------------------------------------- connection
    def connect(self) -> None:
        with self._lock:
            if self._port is not None:
                return
            try:
                port = serial.serial_for_url(
                    self.url, timeout=0, write_timeout=self.reply_timeout, **self.serial_options
                )
            except ValueError as exc:
                raise ValueError(f"{self.name}: bad URL or option for {self.url!r}: {exc}") from exc
            except (serial.SerialException, OSError) as exc:
                raise ConnectionLostError(f"{self.name}: cannot open {self.url!r}: {exc}") from exc
            self._port = LinePort(port, self.codec.split_frames)
            self.log.info("connected to %s", self.url)
            try:
                self._configure()
            except BaseException:
                self.close()
                raise

    def _configure(self) -> None:
        """Send the air and reflector this sensor was built with."""
        if self.environment is not None:
            self.set_environment(self.environment)
        if self.reflector is not None:
            self.select_reflector(*self.reflector)

    def close(self) -> None:
        with self._lock:
            if self._port is None:
                return
            try:
                self._port.close()
            except (serial.SerialException, OSError) as exc:
                self.log.debug("close: %s", exc)
            self._port = None
            self.log.info("closed %s", self.url)

    def reconnect(self) -> None:
        """Close and open the transport again (raises ConnectionLostError if it cannot)."""
        with self._lock:
            self.log.warning("reconnecting to %s", self.url)
            self.close()
            self.connect()

    @property
    def connected(self) -> bool:
        return self._port is not None

    # ----------------------------------------------------------------- exchange
    def _next_rid(self) -> int:
        self._rid = self._rid % MAX_RID + 1
        return self._rid

    def request(self, command, timeout: float | None = None):
        """Send ``command`` and return its typed reply (see the module docstring for errors).

        timeout: seconds to wait for the reply (default ``reply_timeout``). An error raised
        for a device ``ERR`` reply carries the numeric ``code`` attribute.
        """
        return self._request(command, timeout)[0]

    def _request(self, command, timeout: float | None = None):
        """``request`` that also returns the host time (``clock``) the reply arrived."""
        timeout = self.reply_timeout if timeout is None else check_timeout(timeout)
        with self._lock:
            if self._port is None:
                raise ConnectionLostError(f"{self.name}: not connected to {self.url}; call connect() or reconnect()")
            try:
                return self._exchange(command, timeout)
            except ConnectionLostError:
                if not (self.auto_reconnect and isinstance(command, _IDEMPOTENT)):
                    raise
            self.reconnect()
            return self._exchange(command, timeout)

    def _exchange(self, command, timeout: float):
        rid = self._next_rid()
        line = self.codec.encode_request(rid, command)
        port = self._port
        self._io(port.write, line)
        deadline = time.monotonic() + timeout
        while True:
            frame = self._io(port.read_frame, deadline)
            if frame is None:
                raise DeviceTimeoutError(
                    f"{self.name}: no reply to {line.decode().strip()!r} within {timeout:.3g} s from {self.url}"
                )
            host_time = self.clock()
            got_rid, reply = self.codec.decode_reply(frame)
            if isinstance(reply, Event):
                self.events.append((reply, host_time))
                self.log.info("event %s at device time %.6f", reply.name, reply.device_time)
                continue
            if got_rid not in (rid, 0):
                self.log.debug("discarding stale reply %r (waiting for id %d)", frame, rid)
                continue
            return self._check(command, line, reply, host_time)

    def _io(self, fn, *args):
        """Call a transport function, turning pyserial / OS errors into driver errors."""
        try:
            return fn(*args)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeoutError(
                f"{self.name}: could not write to {self.url} within {self.reply_timeout:.3g} s"
            ) from exc
        except ProtocolError:
            raise
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise ConnectionLostError(f"{self.name}: connection to {self.url} lost: {exc}") from exc

    def _check(self, command, line: bytes, reply, host_time: float):
        sent = line.decode().strip()
        if isinstance(reply, ErrorReply):
            cls = ERROR_CLASSES.get(reply.code, DeviceFaultError)
            exc = cls(f"{self.name}: device refused {sent!r}: error {reply.code}: {reply.text}")
            exc.code = reply.code
            raise exc
        want = REPLY_FOR[type(command)]
        if not isinstance(reply, want):
            raise ProtocolError(f"{self.name}: sent {sent!r}, got a {reply.verb} reply (expected {want.verb})")
        return reply, host_time

    # ----------------------------------------------------------------- tracker commands
    def identify(self) -> IdentifyReply:
        return self.request(Identify())

    def status(self) -> StatusReply:
        """Beam lock, mode, warm-up and distance validity (``StatusReply``)."""
        return self.request(GetStatus())

    def set_mode(self, mode: Mode | str) -> ModeReply:
        """Switch to ``"ADM"`` or ``"IFM"`` (IFM then needs ``home()`` before measuring)."""
        text = mode.value if isinstance(mode, Mode) else str(mode).upper()
        if text not in Mode.__members__:
            raise ValueError(f"mode must be one of {', '.join(Mode.__members__)}, got {mode!r}")
        return self.request(SetMode(Mode(text)))

    def set_environment(self, air: Air | str | dict) -> EnvironmentReply:
        """Air for the refraction correction: an ``Air`` (°C, hPa, %), or ``"station"`` for
        the tracker's weather station (refused with DeviceFaultError if it has none). Returns
        the air the tracker now uses."""
        air = parse_environment(air)
        if air is None:
            raise ValueError("set_environment needs an Air or 'station'")
        cmd = Environment("STATION") if air == STATION else \
            Environment("HOST", air.temperature_c, air.pressure_hpa, air.humidity_pct)
        self.air_in_use = self.request(cmd)
        a = self.air_in_use
        self.log.info("air for refraction (%s): %.2f °C, %.2f hPa, %.1f %%", a.source, a.temperature_c,
                      a.pressure_hpa, a.humidity_pct)
        return a

    def select_reflector(self, reflector_type: str, offset_mm: float | None = None) -> ReflectorReply:
        """Select the reflector by type name (e.g. ``RRR15``), with its surface offset in mm
        (None: the tracker's own value for that type). Unknown types raise LimitError."""
        self.reflector_in_use = self.request(SelectReflector(reflector_type, offset_mm))
        self.log.info("reflector %s, offset %.4f mm", self.reflector_in_use.reflector_type,
                      self.reflector_in_use.offset_mm)
        return self.reflector_in_use

    def home(self, timeout: float = 10.0) -> None:
        """Re-establish the interferometer distance (needs a locked beam)."""
        self.request(Home(), timeout=self.reply_timeout + check_timeout(timeout))

    def aim(self, xyz_mm, timeout: float = 10.0) -> None:
        """Point the beam at ``xyz_mm`` (shape (3,), tracker frame, mm).

        Returns once the beam is locked on a reflector there; raises TargetLostError if no
        reflector was caught within the device's capture radius.
        """
        p = np.asarray(xyz_mm, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"aim point must be 3 finite numbers (mm), got {xyz_mm!r}")
        reply: AimReply = self.request(Aim(*map(float, p)), timeout=self.reply_timeout + check_timeout(timeout))
        if not reply.locked:
            raise TargetLostError(
                f"{self.name}: aimed at ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm but no reflector within the "
                "capture radius; try search()"
            )

    def search(self, radius_mm: float, timeout: float, max_turns: int = 0) -> SearchReply:
        """Spiral search out to ``radius_mm`` around the current beam direction.

        timeout: device seconds the search may take (the reply may take ``reply_timeout`` more).
        Returns the ``SearchReply`` when found; raises TargetLostError when not.
        """
        if not (isinstance(radius_mm, (int, float)) and math.isfinite(radius_mm) and 0 < radius_mm <= 10_000):
            raise ValueError(f"radius_mm must be in (0, 10000] mm, got {radius_mm!r}")
        timeout = check_timeout(timeout)
        reply: SearchReply = self.request(Search(float(radius_mm), timeout, int(max_turns)),
                                          timeout=self.reply_timeout + timeout)
        if not reply.found:
            raise TargetLostError(
                f"{self.name}: spiral search of radius {radius_mm:g} mm found no reflector "
                f"in {reply.elapsed_s:.2f} s ({reply.turns:.1f} turns)"
            )
        return reply

    def reacquire(self, xyz_mm, search_radius_mm: float = 50.0, timeout: float = 30.0) -> None:
        """Aim at the predicted reflector position, spiral-search if that fails, and restore
        the IFM distance if needed. Raises TargetLostError if the reflector is not found."""
        try:
            self.aim(xyz_mm, timeout)
        except TargetLostError:
            self.search(search_radius_mm, timeout)
        if not self.status().distance_valid:
            self.home(timeout)

    # ----------------------------------------------------------------- PositionSensor
    def marker_names(self) -> list[str]:
        return [self.marker]

    def _read_internal(self, timeout: float) -> list[MarkerSample]:
        """One MEAS: a visible sample, or ``visible=False`` (NaN position and device time)
        when the beam is lost or the IFM distance is invalid."""
        try:
            reply, host_time = self._request(MeasurePoint(), timeout=timeout)
        except TargetLostError as exc:
            self.log.info("%s", exc)
            return [MarkerSample(self.marker, np.full(3, np.nan), math.nan, self.clock(), visible=False)]
        return [
            MarkerSample(self.marker, reply.xyz_mm, reply.device_time, host_time,
                         visible=True, std_mm=reply.std_mm)
        ]

    def measure(self, marker: str, n: int, timeout: float) -> MarkerMeasurement:
        """Average ``n`` points with the device's AVG command (falls back to ``n`` single
        points when the device does not know AVG). Raises TargetLostError when the beam is or
        becomes lost (DistanceLostError when the IFM distance is invalid)."""
        if marker != self.marker:
            raise ValueError(f"{self.name} measures marker {self.marker!r}, not {marker!r}")
        if not (isinstance(n, int) and 1 <= n <= MAX_AVERAGE):
            raise ValueError(f"n must be an integer in 1..{MAX_AVERAGE}, got {n!r}")
        timeout = check_timeout(timeout)
        if self.pose:
            return self._measure_pose(n, timeout)
        if self._average_supported:
            try:
                reply, host_time = self._request(MeasureAverage(n), timeout=timeout)
            except ProtocolError as exc:
                if getattr(exc, "code", None) != ErrorCode.UNKNOWN_COMMAND:
                    raise
                self.log.warning("device does not know AVG; averaging %d single points instead", n)
                self._average_supported = False
            else:
                return MarkerMeasurement(self.marker, reply.xyz_mm, reply.std_xyz_mm, reply.n,
                                         reply.device_time, host_time)
        return super().measure(marker, n, timeout)

    def _measure_pose(self, n: int, timeout: float) -> MarkerMeasurement:
        """``POSE n``: the 6-DoF target's mean position and orientation (``R_tracker←target``)
        with their spreads (``std_deg``: RMS over the three axes of the rotation-vector spread)."""
        from calib.robot.transforms import quat_to_matrix

        reply, host_time = self._request(MeasurePose(n), timeout=timeout)
        q = reply.quat_wxyz
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise ProtocolError(f"{self.name}: POSE quaternion {q.tolist()} has norm {norm:.6f}, not 1")
        return MarkerMeasurement(self.marker, reply.xyz_mm, reply.std_xyz_mm, reply.n, reply.device_time, host_time,
                                 rotation=quat_to_matrix(q / norm),
                                 std_deg=float(np.sqrt(np.mean(reply.std_rot_deg ** 2))))
