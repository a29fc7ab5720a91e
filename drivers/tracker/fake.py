"""A fake laser tracker that speaks the line protocol of ``PROTOCOL.md`` over real transports.

``FakeTracker`` is the device logic: it reads the reflector's true position and line of sight
from a ``drivers.sim.scene.MarkerScene`` (``observe("tracker")``, tracker frame, mm), keeps the
beam-lock / distance state machine, adds measurement noise and spends simulated time on a
``SimClock``. ``TcpTrackerServer`` serves it on 127.0.0.1 (``socket://`` URL) and
``PtyTrackerServer`` on a pseudo-terminal (a ``/dev/pts/N`` path pyserial opens like a serial
port). Both servers have fault hooks: ``drop()``, ``stall(seconds)``, ``garble(n)``.

Behaviour (all configurable in the constructor):

- Lock: a locked beam follows the reflector. When the scene reports the reflector invisible the
  lock is lost (event ``BEAM_LOST``) and stays lost even when the line of sight returns, until
  ``AIM`` points the beam ray within ``capture_radius_mm`` of the reflector or ``SEARCH`` finds it.
- Distance: in ADM the distance is measured again after every lock (``adm_lock_s``). In IFM a
  beam break loses the distance for good; measurements are refused (DISTANCE_INVALID) until ``HOME``.
  Switching to IFM also requires ``HOME``.
- Noise: per-axis σ = ``noise_um`` + ``noise_um_per_m`` × distance (µm), seeded RNG. Set both
  to 0 when the scene already applies sensor noise.
- Warm-up: MEAS, AVG and HOME are refused (WARMING_UP) for ``warmup_s`` device seconds.
- Air: distances are scaled by n(true air)/n(air in use) (``drivers.tracker.air``), so a tracker
  told the wrong temperature measures a few ppm long or short, as a real one does. ``ENV`` sets
  the air in use by hand or switches to the simulated weather station (which reads ``air``).
- Reflectors: ``REFL`` selects one of ``reflectors`` by type name (the host may give its offset).
- 6-DoF target (``six_dof=True``, a T-Mac-like target): ``POSE n`` averages ``n`` measurements
  of the target's position and orientation (the scene's ``rotation``, ``R_tracker←target``) with
  per-measurement attitude noise ``attitude_noise_deg`` per axis; a plain reflector refuses
  ``POSE`` with ``NOT_6DOF``.
- Spiral search: an Archimedean spiral of pitch ``search_pitch_mm`` (default: the capture
  radius) around the current beam direction, at ``search_speed_mm_s`` in the plane of the current
  aim point; it takes simulated time π·ρ²/(pitch·speed) to reach radius ρ.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import select
import socket
import threading
import tty
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError
from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerScene
from drivers.tracker.air import REFLECTORS, Air, Reflector, range_scale
from drivers.tracker.codec import (
    PROTOCOL_VERSION,
    Aim,
    AimReply,
    AverageReply,
    PoseReply,
    Environment,
    EnvironmentReply,
    ErrorCode,
    ErrorReply,
    Event,
    GetStatus,
    Home,
    HomeReply,
    Identify,
    IdentifyReply,
    LineCodec,
    MeasureAverage,
    MeasurePose,
    MeasurePoint,
    Mode,
    ModeReply,
    PointReply,
    ReflectorReply,
    RequestError,
    Search,
    SearchReply,
    SelectReflector,
    SetMode,
    StatusReply,
    TrackerCodec,
)

log = logging.getLogger("remaster.fake.tracker")

_LOOPBACK = ("127.0.0.1", "localhost", "::1")


class DeviceRefusal(Exception):
    """A command the simulated tracker refuses, with the line protocol's error code (another
    front end, such as the emScon fake, translates the code into its own)."""

    def __init__(self, code: ErrorCode, text: str) -> None:
        super().__init__(text)
        self.code = code


_DeviceFault = DeviceRefusal


@dataclass(frozen=True)
class TrackerIdentity:
    vendor: str = "remaster"
    model: str = "SIMTRACKER-1"
    serial: str = "SIM0001"
    firmware: str = "1.0.0"


class FakeTracker:
    """Device logic of the simulated tracker; thread-safe (one lock around every command).

    ``scene.observe("tracker")`` must return the reflector named ``reflector`` (tracker frame,
    mm). Times (``warmup_s``, ``adm_lock_s`` ...) are device (simulated) seconds on ``clock``
    (a ``SimClock``, or anything with ``now()`` and ``sleep(sim_seconds)``).
    """

    def __init__(
        self,
        scene: MarkerScene,
        *,
        clock: SimClock | None = None,
        reflector: str = "smr",
        capture_radius_mm: float = 5.0,
        mode: Mode | str = Mode.ADM,
        warmup_s: float = 0.0,
        noise_um: float = 15.0,
        noise_um_per_m: float = 6.0,
        seed: int = 0,
        start_locked: bool = True,
        home_point_mm: tuple[float, float, float] = (1000.0, 0.0, 0.0),
        measure_time_s: float = 0.001,
        average_rate_hz: float = 1000.0,
        aim_slew_rad_s: float = math.pi,
        adm_lock_s: float = 0.1,
        home_s: float = 0.5,
        search_speed_mm_s: float = 200.0,
        search_pitch_mm: float | None = None,
        supports_average: bool = True,
        identity: TrackerIdentity = TrackerIdentity(),
        codec: TrackerCodec | None = None,
        air: Air = Air(),
        weather_station: bool = True,
        reflectors: tuple[Reflector, ...] = REFLECTORS,
        reflector_type: str = "RRR15",
        six_dof: bool = False,
        attitude_noise_deg: float = 0.01,
    ) -> None:
        for name, value in (("capture_radius_mm", capture_radius_mm), ("average_rate_hz", average_rate_hz),
                            ("aim_slew_rad_s", aim_slew_rad_s), ("search_speed_mm_s", search_speed_mm_s)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        for name, value in (("warmup_s", warmup_s), ("noise_um", noise_um), ("noise_um_per_m", noise_um_per_m),
                            ("measure_time_s", measure_time_s), ("adm_lock_s", adm_lock_s), ("home_s", home_s)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a non-negative number, got {value!r}")
        if not (math.isfinite(attitude_noise_deg) and attitude_noise_deg >= 0):
            raise ValueError(f"attitude_noise_deg must be a non-negative number, got {attitude_noise_deg!r}")
        self.six_dof = bool(six_dof)
        self.attitude_noise_rad = math.radians(attitude_noise_deg)
        self.scene = scene
        self.clock = clock or SimClock()
        self.reflector = reflector
        self.capture_radius_mm = float(capture_radius_mm)
        self.warmup_s = float(warmup_s)
        self.noise_um = float(noise_um)
        self.noise_um_per_m = float(noise_um_per_m)
        self.measure_time_s = float(measure_time_s)
        self.average_rate_hz = float(average_rate_hz)
        self.aim_slew_rad_s = float(aim_slew_rad_s)
        self.adm_lock_s = float(adm_lock_s)
        self.home_s = float(home_s)
        self.search_speed_mm_s = float(search_speed_mm_s)
        self.search_pitch_mm = float(search_pitch_mm or capture_radius_mm)
        self.supports_average = supports_average
        self.identity = identity
        self.codec = codec or LineCodec()
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        #: held around every command; another front end (the emScon fake) takes it too
        self.lock = self._lock
        self._listeners: list = []
        self._hooks: list = []
        self.air = air
        self.weather_station = bool(weather_station)
        self.assumed_air = Air()  # standard air until the host says otherwise
        self.env_source = "HOST"
        self.reflectors = {r.name: r for r in reflectors}
        if reflector_type not in self.reflectors:
            raise ValueError(f"reflector_type {reflector_type!r} is not among the reflectors {sorted(self.reflectors)}")
        self.reflector_kind = self.reflectors[reflector_type]
        self.reflector_offset_mm = self.reflector_kind.surface_offset_mm
        self._t0 = self.clock.now()
        self.mode = Mode(mode)
        self.locked = False
        self.distance_valid = False
        self.aim_point_mm = np.asarray(home_point_mm, dtype=float)
        if start_locked:
            pos, visible = self._observe()
            if visible:
                self.locked, self.distance_valid, self.aim_point_mm = True, True, pos

    # ----------------------------------------------------------------- plumbing
    def add_listener(self, send) -> None:
        """``send(line: bytes)`` receives every event line (BEAM_LOST, BEAM_LOCKED)."""
        with self._lock:
            self._listeners.append(send)

    def add_event_hook(self, hook) -> None:
        """``hook(name: str, device_time: float)`` is called for every event (any front end)."""
        with self._lock:
            self._hooks.append(hook)

    def remove_event_hook(self, hook) -> None:
        with self._lock:
            if hook in self._hooks:
                self._hooks.remove(hook)

    def remove_listener(self, send) -> None:
        with self._lock:
            if send in self._listeners:
                self._listeners.remove(send)

    def _emit(self, name: str) -> None:
        t = self.clock.now()
        line = self.codec.encode_reply(0, Event(name, t))
        log.info("event %s", name)
        for send in list(self._listeners):
            send(line)
        for hook in list(self._hooks):
            hook(name, t)

    def execute(self, command):
        """Run one command (a ``drivers.tracker.codec`` command object) and return its reply
        object; raises DeviceRefusal with the error code when the device refuses it."""
        with self._lock:
            try:
                return self._dispatch(command)
            except DeviceRefusal:
                raise
            except (ValueError, ArithmeticError, LookupError) as exc:  # a scene or geometry problem
                log.exception("internal error on %r", command)
                raise DeviceRefusal(ErrorCode.INTERNAL, f"internal: {exc}") from exc

    def range_scale(self) -> float:
        """Factor every measured position is scaled by: n(true air) / n(air in use)."""
        used = self.station_air() if self.env_source == "STATION" else self.assumed_air
        return range_scale(self.air, used)

    def station_air(self) -> Air:
        """What the simulated weather station reads (the true air at its resolution: 0.01)."""
        a = self.air
        return Air(round(a.temperature_c, 2), round(a.pressure_hpa, 2), round(a.humidity_pct, 2))

    def handle(self, line: bytes) -> bytes:
        """Answer one request line with one reply line (events go to the listeners first)."""
        with self._lock:
            try:
                rid, command = self.codec.decode_request(line)
            except RequestError as exc:
                log.debug("refused %r: %s", line[:80], exc)
                return self.codec.encode_reply(exc.rid, ErrorReply(int(exc.code), str(exc)))
            try:
                reply = self._dispatch(command)
            except _DeviceFault as exc:
                return self.codec.encode_reply(rid, ErrorReply(int(exc.code), str(exc)))
            except (ValueError, ArithmeticError, LookupError) as exc:  # a scene or geometry problem
                log.exception("internal error on %r", line[:80])
                return self.codec.encode_reply(rid, ErrorReply(int(ErrorCode.INTERNAL), f"internal: {exc}"))
            return self.codec.encode_reply(rid, reply)

    def tick(self) -> None:
        """Let the beam follow the scene now (servers call this while idle)."""
        with self._lock:
            try:
                self._update()
            except (ValueError, ArithmeticError, LookupError):  # a scene problem: keep serving
                log.exception("scene observation failed")

    # ----------------------------------------------------------------- state
    def _observe(self) -> tuple[np.ndarray, bool]:
        for obs in self.scene.observe("tracker"):
            if obs.name == self.reflector:
                pos = np.asarray(obs.position_mm, dtype=float).reshape(3)
                return pos, bool(obs.visible) and bool(np.all(np.isfinite(pos)))
        return np.full(3, np.nan), False

    def _update(self) -> tuple[np.ndarray, bool]:
        """Follow the reflector while locked; lose the lock (and IFM distance) on a break."""
        pos, visible = self._observe()
        if self.locked:
            if visible:
                self.aim_point_mm = pos
            else:
                self._lose_lock()
        return pos, visible

    def _lose_lock(self) -> None:
        self.locked = False
        self.distance_valid = False  # ADM re-measures on the next lock, IFM needs HOME
        self._emit("BEAM_LOST")

    def _acquire(self, pos: np.ndarray) -> None:
        self.locked = True
        self.aim_point_mm = pos
        if self.mode is Mode.ADM:
            self._spend(self.adm_lock_s)
            self.distance_valid = True
        self._emit("BEAM_LOCKED")

    def _spend(self, seconds: float) -> None:
        """Let ``seconds`` of device time pass (nothing at all for 0: time.sleep(0) yields)."""
        if seconds > 0:
            self.clock.sleep(seconds)

    def warmup_left_s(self) -> float:
        return max(0.0, self.warmup_s - (self.clock.now() - self._t0))

    def sigma_mm(self, distance_mm: float) -> float:
        """Per-axis 1σ noise at ``distance_mm``, mm."""
        return (self.noise_um + self.noise_um_per_m * distance_mm / 1000.0) / 1000.0

    def _ready_to_measure(self) -> np.ndarray:
        left = self.warmup_left_s()
        if left > 0:
            raise _DeviceFault(ErrorCode.WARMING_UP, f"warming up, {left:.1f} s left")
        pos, _ = self._update()
        if not self.locked:
            raise _DeviceFault(ErrorCode.BEAM_LOST, "beam not locked on a reflector; AIM or SEARCH first")
        if not self.distance_valid:
            raise _DeviceFault(ErrorCode.DISTANCE_INVALID, "interferometer distance lost; send HOME")
        return pos

    # ----------------------------------------------------------------- commands
    def _dispatch(self, cmd):
        if isinstance(cmd, Identify):
            i = self.identity
            return IdentifyReply(i.vendor, i.model, i.serial, i.firmware, PROTOCOL_VERSION)
        if isinstance(cmd, GetStatus):
            self._update()
            left = self.warmup_left_s()
            return StatusReply(self.locked, self.mode, left == 0, left, left == 0, self.distance_valid, self.clock.now())
        if isinstance(cmd, SetMode):
            self._update()
            self.mode = cmd.mode
            self.distance_valid = self.locked and cmd.mode is Mode.ADM
            return ModeReply(self.mode, self.distance_valid, self.clock.now())
        if isinstance(cmd, MeasurePoint):
            pos = self._ready_to_measure()
            self._spend(self.measure_time_s)
            sigma = self.sigma_mm(float(np.linalg.norm(pos)))
            p = pos * self.range_scale() + self._rng.normal(0.0, sigma, 3)
            return PointReply(p[0], p[1], p[2], sigma, self.clock.now())
        if isinstance(cmd, MeasureAverage):
            if not self.supports_average:
                raise _DeviceFault(ErrorCode.UNKNOWN_COMMAND, "unknown command 'AVG' (averaging disabled)")
            return self._average(cmd.n)
        if isinstance(cmd, MeasurePose):
            return self._pose(cmd.n)
        if isinstance(cmd, Aim):
            return self._aim(np.array([cmd.x, cmd.y, cmd.z]))
        if isinstance(cmd, Search):
            return self._search(cmd)
        if isinstance(cmd, Home):
            left = self.warmup_left_s()
            if left > 0:
                raise _DeviceFault(ErrorCode.WARMING_UP, f"warming up, {left:.1f} s left")
            self._update()
            if not self.locked:
                raise _DeviceFault(ErrorCode.BEAM_LOST, "HOME needs a locked reflector; AIM or SEARCH first")
            if not self.distance_valid:
                self._spend(self.home_s)
                self.distance_valid = True
            return HomeReply(True, self.clock.now())
        if isinstance(cmd, Environment):
            return self._environment(cmd)
        if isinstance(cmd, SelectReflector):
            if cmd.reflector_type is not None:
                refl = self.reflectors.get(cmd.reflector_type)
                if refl is None:
                    raise DeviceRefusal(ErrorCode.BAD_ARGUMENT, f"unknown reflector type {cmd.reflector_type!r}; "
                                                                f"known: {' '.join(self.reflectors)}")
                self.reflector_kind = refl
                self.reflector_offset_mm = refl.surface_offset_mm if cmd.offset_mm is None else float(cmd.offset_mm)
                log.info("reflector %s, offset %.4f mm", refl.name, self.reflector_offset_mm)
            return ReflectorReply(self.reflector_kind.name, self.reflector_offset_mm, self.clock.now())
        raise _DeviceFault(ErrorCode.UNKNOWN_COMMAND, f"unsupported command {cmd!r}")

    def _environment(self, cmd: Environment) -> EnvironmentReply:
        if cmd.source == "STATION":
            if not self.weather_station:
                raise DeviceRefusal(ErrorCode.NO_WEATHER_STATION,
                                    "no weather station connected; send ENV source=HOST temp= press= hum=")
            self.env_source = "STATION"
        elif cmd.source == "HOST":
            self.env_source = "HOST"
            self.assumed_air = Air(cmd.temperature_c, cmd.pressure_hpa, cmd.humidity_pct)
        used = self.station_air() if self.env_source == "STATION" else self.assumed_air
        if cmd.source is not None:
            log.info("air for refraction: %s (%s), range scale %.9f", used, self.env_source, self.range_scale())
        return EnvironmentReply(self.env_source, used.temperature_c, used.pressure_hpa, used.humidity_pct,
                                self.clock.now())

    def _average(self, n: int) -> AverageReply:
        start = self._ready_to_measure()
        self._spend(n / self.average_rate_hz)
        end, visible = self._update()
        if not self.locked:
            raise _DeviceFault(ErrorCode.BEAM_LOST, f"beam lost during the {n}-point average")
        sigma = self.sigma_mm(float(np.linalg.norm(start)))
        frac = np.linspace(0.0, 1.0, n)[:, None]
        pts = (start + frac * (end - start)) * self.range_scale() + self._rng.normal(0.0, sigma, (n, 3))
        mean = pts.mean(axis=0)
        std = pts.std(axis=0, ddof=1) if n > 1 else np.zeros(3)
        return AverageReply(mean[0], mean[1], mean[2], std[0], std[1], std[2], n, self.clock.now())

    def _observe_rotation(self) -> np.ndarray | None:
        for obs in self.scene.observe("tracker"):
            if obs.name == self.reflector:
                rot = getattr(obs, "rotation", None)
                return None if rot is None else np.asarray(rot, dtype=float).reshape(3, 3)
        return None

    def _pose(self, n: int) -> PoseReply:
        """``POSE``: the mean of ``n`` measurements of the 6-DoF target's position and orientation."""
        from calib.robot.transforms import exp_so3, log_so3, matrix_to_quat

        if not self.six_dof:
            raise _DeviceFault(ErrorCode.NOT_6DOF, f"the target {self.reflector!r} is a plain reflector, "
                                                   "not a 6-DoF target; use AVG")
        avg = self._average(n)
        rot = self._observe_rotation()
        if rot is None:
            raise _DeviceFault(ErrorCode.BEAM_LOST, "the 6-DoF target's orientation was lost during the measurement")
        samples = exp_so3(self._rng.normal(0.0, self.attitude_noise_rad, (n, 3))) @ rot
        u, _, vt = np.linalg.svd(samples.sum(axis=0))
        mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        spread = np.degrees(log_so3(samples @ mean.T).std(axis=0, ddof=1)) if n > 1 else np.zeros(3)
        q = matrix_to_quat(mean)
        return PoseReply(avg.x, avg.y, avg.z, avg.sx, avg.sy, avg.sz, q[0], q[1], q[2], q[3],
                         spread[0], spread[1], spread[2], n, avg.device_time)

    def _aim(self, target: np.ndarray) -> AimReply:
        pos, visible = self._update()
        u0 = self.aim_point_mm / np.linalg.norm(self.aim_point_mm)
        u1 = target / np.linalg.norm(target)
        angle = math.acos(float(np.clip(u0 @ u1, -1.0, 1.0)))
        self._spend(angle / self.aim_slew_rad_s)
        was_locked = self.locked
        self.aim_point_mm = target
        catch = visible and _ray_distance(u1, pos) <= self.capture_radius_mm
        if catch:
            if not was_locked:
                self._acquire(pos)
            else:
                self.aim_point_mm = pos
        elif was_locked:
            self._lose_lock()
        return AimReply(self.locked, self.clock.now())

    def _search(self, cmd: Search) -> SearchReply:
        pos, visible = self._update()
        if self.locked:
            return SearchReply(True, 0.0, 0.0, self.clock.now())
        pitch, speed = self.search_pitch_mm, self.search_speed_mm_s
        d = float(np.linalg.norm(self.aim_point_mm))
        u = self.aim_point_mm / d
        s_max = cmd.radius_mm if cmd.max_turns == 0 else min(cmd.radius_mm, cmd.max_turns * pitch)

        def time_to(s: float) -> float:  # arc length of r = pitch·θ/2π from 0 to s, over speed
            return math.pi * s * s / pitch / speed

        s_hit = math.inf  # where the spiral passes the reflector; it is seen only if visible then
        depth = float(pos @ u)
        if depth > 0:
            rho = float(np.linalg.norm(pos * (d / depth) - d * u))  # offset in the aim-point plane
            s_hit = max(0.0, rho - self.capture_radius_mm * d / depth)
        t_hit = time_to(s_hit) if math.isfinite(s_hit) else math.inf
        if s_hit <= s_max and t_hit <= cmd.timeout_s:
            self._spend(t_hit)
            pos, visible = self._observe()
            if visible:
                self._acquire(pos)
                log.info("search found the reflector after %.3f s at %.1f mm", t_hit, s_hit)
                return SearchReply(True, t_hit, s_hit / pitch, self.clock.now())
            elapsed, turns = t_hit, s_hit / pitch
        else:
            elapsed = min(cmd.timeout_s, time_to(s_max))
            turns = math.sqrt(elapsed * pitch * speed / math.pi) / pitch
            self._spend(elapsed)
        return SearchReply(False, elapsed, turns, self.clock.now())


def _ray_distance(u: np.ndarray, p: np.ndarray) -> float:
    """Distance (mm) from point ``p`` to the ray from the origin along unit vector ``u``."""
    along = float(p @ u)
    if along <= 0:
        return float(np.linalg.norm(p))
    return float(np.linalg.norm(p - along * u))


# =========================================================================== transports


class _LineServer:
    """Shared loop of both servers: read lines from an fd, answer through the device, faults."""

    poll_s = 0.05

    def __init__(self, device: FakeTracker, *, seed: int = 0) -> None:
        self.device = device
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._faults_lock = threading.Lock()
        self._garble_left = 0
        self._stall_s = 0.0
        self._rng = np.random.default_rng(seed)
        self.requests_seen = 0

    # fault hooks -------------------------------------------------------
    def garble(self, n: int = 1) -> None:
        """Corrupt one byte of each of the next ``n`` lines sent (the newline is kept)."""
        with self._faults_lock:
            self._garble_left += int(n)

    def stall(self, seconds: float) -> None:
        """Wait ``seconds`` (wall) before answering the next request (a hung device)."""
        with self._faults_lock:
            self._stall_s = float(seconds)

    def drop(self, timeout: float = 2.0) -> None:
        """Close every open connection now; returns once they are closed."""
        raise NotImplementedError

    # loop --------------------------------------------------------------
    def _mangle(self, line: bytes) -> bytes:
        with self._faults_lock:
            if self._garble_left <= 0:
                return line
            self._garble_left -= 1
        b = bytearray(line)
        i = int(self._rng.integers(0, max(1, len(b) - 1)))
        choices = [c for c in range(0x20, 0x7F) if c != b[i]]
        b[i] = choices[int(self._rng.integers(0, len(choices)))]
        return bytes(b)

    def _take_stall(self) -> float:
        with self._faults_lock:
            s, self._stall_s = self._stall_s, 0.0
        return s

    def _serve_fd(self, fd: int, write, dropped: threading.Event) -> None:
        """Read requests from ``fd`` until EOF, a drop or close; ``write(bytes)`` sends."""
        def send(line: bytes) -> None:
            write(self._mangle(line))

        self.device.add_listener(send)
        buf = bytearray()
        try:
            while not self._stop.is_set() and not dropped.is_set():
                ready, _, _ = select.select([fd], [], [], self.poll_s)
                if not ready:
                    self.device.tick()
                    continue
                try:
                    data = os.read(fd, 4096)
                except OSError as exc:
                    if exc.errno in (errno.EAGAIN, errno.EINTR):
                        continue
                    log.debug("read ended: %s", exc)
                    return
                if not data:
                    return
                buf += data
                try:
                    lines = self.device.codec.split_frames(buf)
                except ProtocolError as exc:
                    send(self.device.codec.encode_reply(0, ErrorReply(int(ErrorCode.SYNTAX), str(exc))))
                    continue
                for line in lines:
                    stall = self._take_stall()
                    if stall > 0 and self._stop.wait(stall):
                        return
                    if dropped.is_set():
                        return
                    self.requests_seen += 1
                    send(self.device.handle(line))
        finally:
            self.device.remove_listener(send)


class TcpTrackerServer(_LineServer):
    """Serves a ``FakeTracker`` on 127.0.0.1 (ephemeral port by default); many clients at once.

    Use as a context manager or call ``close()``; ``url`` is the pyserial URL to connect to.
    """

    def __init__(self, device: FakeTracker, *, host: str = "127.0.0.1", port: int = 0, seed: int = 0) -> None:
        if host not in _LOOPBACK:
            raise ValueError(f"the fake tracker listens on loopback only; got host {host!r}, allowed {_LOOPBACK}")
        super().__init__(device, seed=seed)
        self._listen = socket.create_server((host, port))
        self.host, self.port = self._listen.getsockname()[:2]
        self._conns: dict[socket.socket, threading.Event] = {}
        self._conn_done: dict[socket.socket, threading.Event] = {}
        self._conns_lock = threading.Lock()
        t = threading.Thread(target=self._accept_loop, name=f"fake-tracker-tcp-{self.port}", daemon=True)
        self._threads.append(t)
        t.start()
        log.info("fake tracker on %s", self.url)

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._listen], [], [], self.poll_s)
            if not ready:
                continue
            try:
                conn, peer = self._listen.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            dropped, done = threading.Event(), threading.Event()
            with self._conns_lock:
                self._conns[conn] = dropped
                self._conn_done[conn] = done
            t = threading.Thread(target=self._conn_loop, args=(conn, dropped, done), daemon=True,
                                 name=f"fake-tracker-conn-{peer[1]}")
            self._threads = [x for x in self._threads if x.is_alive()] + [t]
            t.start()

    def _conn_loop(self, conn: socket.socket, dropped: threading.Event, done: threading.Event) -> None:
        wlock = threading.Lock()

        def write(data: bytes) -> None:
            with wlock:
                try:
                    conn.sendall(data)
                except OSError as exc:
                    log.debug("send failed: %s", exc)

        try:
            self._serve_fd(conn.fileno(), write, dropped)
        finally:
            with self._conns_lock:
                self._conns.pop(conn, None)
                self._conn_done.pop(conn, None)
            with wlock:
                conn.close()
            done.set()

    @property
    def connection_count(self) -> int:
        with self._conns_lock:
            return len(self._conns)

    def drop(self, timeout: float = 2.0) -> None:
        """Close every connection the server has accepted (a client whose connect has not been
        accepted yet, i.e. that has not exchanged a line, is not affected)."""
        with self._conns_lock:
            items = [(c, self._conns[c], self._conn_done[c]) for c in self._conns]
        for conn, dropped, _ in items:
            dropped.set()
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for _, _, done in items:
            done.wait(timeout)
        log.info("dropped %d connection(s)", len(items))

    def close(self) -> None:
        """Stop accepting, close every connection and join the threads."""
        if self._stop.is_set():
            return
        self.drop()
        self._stop.set()
        for t in list(self._threads):
            t.join(timeout=2.0)
        self._listen.close()

    def __enter__(self) -> "TcpTrackerServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PtyTrackerServer(_LineServer):
    """Serves a ``FakeTracker`` on a pseudo-terminal; ``path`` is the serial device to open.

    ``drop()`` closes the terminal for good (like pulling a USB-serial adapter): the path goes
    away, so a client cannot reconnect to it.
    """

    def __init__(self, device: FakeTracker, *, seed: int = 0) -> None:
        super().__init__(device, seed=seed)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no CR/LF translation
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self._dropped = threading.Event()
        self._done = threading.Event()
        t = threading.Thread(target=self._loop, name="fake-tracker-pty", daemon=True)
        self._threads.append(t)
        t.start()
        log.info("fake tracker on %s", self.path)

    @property
    def url(self) -> str:
        return self.path

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
                view = view[n:]
            except BlockingIOError:
                _, ready, _ = select.select([], [self._master], [], 0.2)
                if not ready:  # nobody reads the terminal
                    log.warning("pty output full for 0.2 s; dropping %d bytes", len(view))
                    return
            except OSError as exc:
                log.debug("pty write failed: %s", exc)
                return

    def _loop(self) -> None:
        try:
            self._serve_fd(self._master, self._write, self._dropped)
        finally:
            os.close(self._master)
            os.close(self._slave)
            self._done.set()

    def drop(self, timeout: float = 2.0) -> None:
        self._dropped.set()
        self._done.wait(timeout)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)

    def __enter__(self) -> "PtyTrackerServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
