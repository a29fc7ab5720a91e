"""``EmsconSensor``: a Leica laser tracker behind an emScon server as a ``PositionSensor``.

``emscon://host[:port]`` (port 700 by default). On ``connect()`` the sensor opens the TCP
connection and prepares the tracker as a metrology engineer would: ``Initialize`` (only if the
server reports the tracker not initialised, or always with ``initialize="always"``), units mm /
degree / °C / hPa / %RH, right-handed Cartesian coordinates (RHR), stationary measurement mode,
then the air for the refraction correction and the reflector, if given.

Measuring: ``measure(marker, n)`` is one stationary measurement whose measure time averages
``n`` of the tracker's internal points (``n·1000/point_rate_hz`` ms, or ``measure_time_ms``):
mean position (mm, tracker frame), per-axis spread ``dStd1..3`` and ``count = n``. ``read()``
is a short stationary measurement (``read_time_ms``). emScon results carry no time stamp:
``device_time`` is NaN, ``host_time`` the sensor clock when the result arrived.

6-DoF (``pose=True``, a T-Mac or another probe on the tracker): on ``connect()`` the sensor asks
``GetMeasurementProbeInfo`` (refused with LimitError unless a 6-DoF probe is there) and selects
``ES_MM_6DStationary``; ``measure`` then reads the ``ProbeStationaryResultT``: the probe's
position (``dPosition1..3``, mm) with ``dStdDevPosition1..3``, and its orientation from
``dQuaternion0..3`` (scalar first; ``R_tracker←probe``) as ``rotation`` with ``std_deg`` the RMS
over the axes of ``dStdDevRotationAngleX..Z`` (degrees: the units set on connect).

Re-acquisition (as ``TrackerSensor``): ``aim(xyz)`` sends ``GoPosition`` (with ADM) to the
predicted reflector position and checks ``GetMeasurementStatusInfo`` for a found reflector;
``search(radius, timeout)`` sets the search parameters and sends ``FindReflector``.

One command is in flight at a time (a lock serialises callers). Answers match commands by
command id (emScon has no request ids), so after a timeout the connection is closed and the next
command opens a new one (``auto_reconnect``): a late answer can never be taken for the next.
Errors: every refused command raises the class ``drivers.emscon.status`` maps its
``ES_ResultStatus`` to (with ``status`` / ``status_name``); no answer in time →
DeviceTimeoutError; transport closed → ConnectionLostError; unreadable bytes → ProtocolError.
"""

from __future__ import annotations

import collections
import math
import select
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from drivers.base import Clock, SensorBase, check_timeout
from drivers.emscon import codec as es
from drivers.emscon.codec import Cmd, SSC, Status
from drivers.emscon.probe import check_probe, probe_pose
from drivers.emscon.status import WARNINGS, error_for, status_name
from drivers.errors import (
    ConnectionLostError,
    DeviceFaultError,
    DeviceTimeoutError,
    LimitError,
    ProtocolError,
    TargetLostError,
)
from drivers.protocols import MarkerMeasurement, MarkerSample
from drivers.tracker.air import STATION, Air, parse_environment, parse_reflector
from drivers.tracker.codec import MAX_AVERAGE

#: ``ES_MeasurementStatusInfo`` flag: a reflector is locked.
REFLECTOR_FOUND = 2048


@dataclass(frozen=True)
class SearchResult:
    """A ``FindReflector`` that found the reflector; ``elapsed_s`` on the sensor's clock."""

    found: bool
    elapsed_s: float


@dataclass(frozen=True)
class EmsconStatus:
    """What ``GetSystemStatus`` / ``GetTrackerStatus`` / ``GetMeasurementStatusInfo`` say."""

    ready: bool  # ES_TS_Ready: initialised, warm, reflector locked with a distance
    locked: bool  # a reflector is found (ES_MSI_ReflectorFound)
    initialized: bool
    warmed_up: bool  # laser ready
    weather_monitor: int  # ES_WeatherMonitorStatus
    server_version: tuple[int, int, int]
    serial_number: int
    last_status: int


def parse_url(url: str) -> tuple[str, int]:
    """``emscon://host[:port]`` → (host, port); port 700 by default."""
    if not isinstance(url, str):
        raise ValueError(f"url must be emscon://host[:port], got {url!r}")
    parts = urlsplit(url)
    if parts.scheme != "emscon" or not parts.hostname or parts.path not in ("", "/") or parts.query:
        raise ValueError(f"url must be emscon://host[:port] (port {es.DEFAULT_PORT} by default), got {url!r}")
    try:
        port = parts.port or es.DEFAULT_PORT
    except ValueError:
        raise ValueError(f"bad port in {url!r}: emscon://host[:port] with a port 1..65535") from None
    return parts.hostname, port


class EmsconSensor(SensorBase):
    """A laser tracker on an emScon server that follows one reflector (``marker``), mm.

    reply_timeout: seconds for an ordinary answer (commands that take device time get it on
    top); initialize_timeout: seconds ``Initialize`` may take. initialize: ``"auto"`` (only when
    the server says the tracker is not initialised), ``"always"`` or ``"never"``.
    point_rate_hz: the tracker's internal point rate, to turn ``n`` points into a measure time;
    measure_time_ms fixes the measure time instead; read_time_ms: measure time of ``read()``.
    environment: ``Air`` / ``"station"`` / the plan's mapping; reflector: type name or
    ``{type, offset_mm}``; both applied on connect when given. pose: measure a 6-DoF probe's pose
    (ES_MM_6DStationary) instead of a reflector's position. search_radius_mm: default spiral
    radius of ``search``; approx_distance_mm: distance given to ``FindReflector`` before
    anything was aimed at or measured.
    """

    def __init__(
        self,
        url: str,
        *,
        marker: str = "smr",
        name: str = "emscon",
        reply_timeout: float = 5.0,
        initialize_timeout: float = 120.0,
        initialize: str = "auto",
        point_rate_hz: float = 1000.0,
        measure_time_ms: int | None = None,
        read_time_ms: int = 10,
        environment: Air | str | dict | None = None,
        reflector: str | dict | None = None,
        pose: bool = False,
        search_radius_mm: float = 50.0,
        approx_distance_mm: float = 2000.0,
        auto_reconnect: bool = True,
        clock: Clock = time.monotonic,
    ) -> None:
        super().__init__(name, clock=clock)
        self.host, self.port = parse_url(url)
        self.url = url
        if not isinstance(marker, str) or not marker:
            raise ValueError(f"marker must be a non-empty name, got {marker!r}")
        if initialize not in ("auto", "always", "never"):
            raise ValueError(f"initialize must be 'auto', 'always' or 'never', got {initialize!r}")
        if not (isinstance(point_rate_hz, (int, float)) and math.isfinite(point_rate_hz) and point_rate_hz > 0):
            raise ValueError(f"point_rate_hz must be a positive number, got {point_rate_hz!r}")
        for label, v in (("measure_time_ms", measure_time_ms), ("read_time_ms", read_time_ms)):
            if v is not None and not (isinstance(v, int) and 1 <= v <= MAX_AVERAGE):
                raise ValueError(f"{label} must be an integer number of ms in 1..{MAX_AVERAGE}, got {v!r}")
        for label, v in (("search_radius_mm", search_radius_mm), ("approx_distance_mm", approx_distance_mm)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 < v <= 1e5):
                raise ValueError(f"{label} must be a positive number of mm, got {v!r}")
        if not isinstance(pose, bool):
            raise ValueError(f"pose must be true (a 6-DoF probe such as a T-Mac) or false, got {pose!r}")
        self.pose = pose
        #: ``GetMeasurementProbeInfo`` values of the 6-DoF probe (pose mode), after connect
        self.probe_info: dict | None = None
        self.marker = marker
        self.reply_timeout = check_timeout(reply_timeout)
        self.initialize_timeout = check_timeout(initialize_timeout)
        self.initialize = initialize
        self.point_rate_hz = float(point_rate_hz)
        self.measure_time_ms = measure_time_ms
        self.read_time_ms = read_time_ms
        self.environment = parse_environment(environment)
        self.reflector = parse_reflector(reflector)
        self.search_radius_mm = float(search_radius_mm)
        self.approx_distance_mm = float(approx_distance_mm)
        self.auto_reconnect = auto_reconnect
        #: notifications as (ES_SystemStatusChange, host time), newest last
        self.events: collections.deque[tuple[int, float]] = collections.deque(maxlen=256)
        #: beam state from the last MeasStatus notification (None: not told yet)
        self.beam_ready: bool | None = None
        self.air_in_use: Air | None = None
        self.air_source: str | None = None
        self.reflector_in_use: tuple[int, str, float] | None = None  # id, name, surface offset mm
        self._sock: socket.socket | None = None
        self._buf = bytearray()
        self._frames: collections.deque[bytes] = collections.deque()
        self._lock = threading.RLock()
        self._stationary: tuple[int, int] | None = None  # (lMeasTime, bUseADM) last set
        self._search: tuple[float, int] | None = None
        self._last_xyz: np.ndarray | None = None

    @classmethod
    def from_url(cls, url: str, marker: str = "smr", **kwargs: Any) -> "EmsconSensor":
        """A sensor for ``url`` (not yet connected: ``connect()`` or ``with``)."""
        return cls(url, marker=marker, **kwargs)

    # ----------------------------------------------------------------- connection
    def connect(self) -> None:
        with self._lock:
            if self._sock is not None:
                return
            self._open()
            try:
                self._configure()
            except BaseException:
                self.close()
                raise

    def _open(self) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.reply_timeout)
        except socket.timeout as exc:
            raise DeviceTimeoutError(f"{self.name}: no emScon server answered at {self.host}:{self.port} "
                                     f"within {self.reply_timeout:.3g} s") from exc
        except OSError as exc:
            raise ConnectionLostError(f"{self.name}: cannot connect to the emScon server at {self.host}:{self.port}: "
                                      f"{exc}; is the server running and the port right (default 700)?") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self._sock = sock
        self._buf.clear()
        self._frames.clear()
        self.log.info("connected to emScon server %s:%d", self.host, self.port)

    def close(self) -> None:
        with self._lock:
            if self._sock is None:
                return
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._sock.close()
            self._sock = None
            self.log.info("closed %s:%d", self.host, self.port)

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def _configure(self) -> None:
        st = self.status()
        self.log.info("emScon server %d.%d.%d, tracker serial %d, %s, %s", *st.server_version, st.serial_number,
                      "initialised" if st.initialized else "not initialised",
                      "warm" if st.warmed_up else "warming up")
        if self.initialize == "always" or (self.initialize == "auto" and not st.initialized):
            self.log.info("initialising the tracker (may take up to %.0f s)", self.initialize_timeout)
            self.request(es.Request(Cmd.Initialize), timeout=self.initialize_timeout)
        self.request(es.Request(Cmd.SetUnits, {
            "lenUnitType": int(es.LengthUnit.Millimeter), "angUnitType": int(es.AngleUnit.Degree),
            "tempUnitType": int(es.TemperatureUnit.Celsius), "pressUnitType": int(es.PressureUnit.HPascal),
            "humUnitType": int(es.HumidityUnit.RH)}))
        self.request(es.Request(Cmd.SetCoordinateSystemType, {"coordSysType": int(es.CoordinateSystem.RHR)}))
        if self.pose:
            self._select_probe()
        self.request(es.Request(Cmd.SetMeasurementMode, {"measMode": int(
            es.MeasMode.SixDStationary if self.pose else es.MeasMode.Stationary)}))
        self._stationary = None
        self._search = None
        if self.environment is not None:
            self.set_environment(self.environment)
        if self.reflector is not None:
            self.select_reflector(*self.reflector)

    # ----------------------------------------------------------------- exchange
    def request(self, req: es.Request, timeout: float | None = None) -> es.Answer:
        """Send ``req`` and return its answer (raises the mapped error for a refusal)."""
        return self._exchange(req, timeout)[0]

    def _exchange(self, req: es.Request, timeout: float | None = None, *, want_result: bool = False):
        """Send ``req``; return (answer, host time). ``want_result``: wait for the
        ``SingleMeasResult`` (StartMeasurement). GetReflectors returns the list of its answers
        (the server sends one per reflector and says how many in each)."""
        timeout = self.reply_timeout if timeout is None else check_timeout(timeout)
        with self._lock:
            if self._sock is None:
                if not self.auto_reconnect:
                    raise ConnectionLostError(f"{self.name}: not connected to {self.url}; call connect()")
                self._open()
            data = es.encode(req)
            self._send(data)
            deadline = time.monotonic() + timeout
            got: list[es.Answer] = []
            what = f"{self.name}: {req.command.name}"
            while True:
                frame = self._read_frame(deadline)
                if frame is None:
                    self.close()  # a late answer must not be taken for the next command's
                    raise DeviceTimeoutError(f"{what}: no answer within {timeout:.3g} s from {self.host}:{self.port}")
                host_time = self.clock()
                try:
                    packet = es.decode(frame)
                except ProtocolError as exc:
                    self.close()
                    raise ProtocolError(f"{what}: unreadable packet from the server: {exc}") from None
                if isinstance(packet, es.StatusChange):
                    self._note(packet.change, host_time)
                    continue
                if isinstance(packet, es.ErrorAnswer):
                    if packet.command in (req.command, Cmd.Unknown):
                        raise error_for(packet.status, f"{what} (ES_DT_Error)")
                    self.log.debug("discarding an error answer to command %d", packet.command)
                    continue
                if isinstance(packet, es.DataResult):
                    if want_result and packet.type in (es.DataType.SingleMeasResult, es.DataType.SingleMeasResult2,
                                                       es.DataType.StationaryProbeMeasResult):
                        if packet.status != Status.AllOK and packet.status not in WARNINGS:
                            raise error_for(packet.status, f"{what} result")
                        return packet, host_time
                    self.log.debug("discarding an unexpected %s", packet.type.name)
                    continue
                if packet.command != req.command:
                    self.log.debug("discarding an answer to %s while waiting for %s", packet.command, req.command.name)
                    continue
                if packet.status != Status.AllOK:
                    if packet.status not in WARNINGS:
                        raise error_for(packet.status, what)
                    self.log.warning("%s: executed with %s", what, status_name(packet.status))
                if want_result:
                    continue  # the continuous-mode style confirmation; the result follows
                if req.command is not Cmd.GetReflectors:
                    return packet, host_time
                got.append(packet)
                if len(got) >= max(1, int(packet.values.get("iTotalReflectors", 1))):
                    return got, host_time

    def _note(self, change: int, host_time: float) -> None:
        self.events.append((change, host_time))
        try:
            name = SSC(change).name
        except ValueError:
            name = str(change)
        if change == SSC.MeasStatus_NotReady:
            self.beam_ready = False
        elif change == SSC.MeasStatus_Ready:
            self.beam_ready = True
        self.log.info("server notification %s", name)

    def _send(self, data: bytes) -> None:
        view = memoryview(data)
        deadline = time.monotonic() + self.reply_timeout
        while view:
            try:
                n = self._sock.send(view)
                view = view[n:]
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([], [self._sock], [], left)[1]:
                    self.close()
                    raise DeviceTimeoutError(f"{self.name}: could not send to {self.host}:{self.port} "
                                             f"within {self.reply_timeout:.3g} s") from None
            except OSError as exc:
                self.close()
                raise ConnectionLostError(f"{self.name}: connection to {self.host}:{self.port} lost: {exc}") from exc

    def _read_frame(self, deadline: float) -> bytes | None:
        while not self._frames:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                ready, _, _ = select.select([self._sock], [], [], remaining)
                if not ready:
                    return None
                data = self._sock.recv(65536)
            except BlockingIOError:
                continue
            except OSError as exc:
                self.close()
                raise ConnectionLostError(f"{self.name}: connection to {self.host}:{self.port} lost: {exc}") from exc
            if not data:
                self.close()
                raise ConnectionLostError(f"{self.name}: the emScon server at {self.host}:{self.port} closed the connection")
            self._buf += data
            try:
                self._frames.extend(es.split_frames(self._buf))
            except ProtocolError as exc:
                self.close()
                raise ProtocolError(f"{self.name}: {exc}") from None
        return self._frames.popleft()

    # ----------------------------------------------------------------- tracker commands
    def status(self) -> EmsconStatus:
        sysst = self.request(es.Request(Cmd.GetSystemStatus)).values
        trk = self.request(es.Request(Cmd.GetTrackerStatus)).values
        info = self.request(es.Request(Cmd.GetMeasurementStatusInfo)).values
        return EmsconStatus(
            ready=trk["trackerStatus"] == es.TrackerStatus.Ready,
            locked=bool(info["lMeasurementStatusInfo"] & REFLECTOR_FOUND),
            initialized=sysst["trackerProcessorStatus"] == es.TrackerProcessorStatus.Initialized,
            warmed_up=sysst["laserStatus"] == es.LaserProcessorStatus.LaserReady,
            weather_monitor=sysst["weatherMonitorStatus"],
            server_version=(sysst["iMajorVersionNumber"], sysst["iMinorVersionNumber"], sysst["iBuildNumber"]),
            serial_number=sysst["lTrackerSerialNumber"],
            last_status=sysst["lastResultStatus"],
        )

    def set_environment(self, air: Air | str | dict) -> Air:
        """Air for the refraction correction: an ``Air`` (°C, hPa, %RH) sent with
        ``SetEnvironmentParams``, or ``"station"``: the server's weather monitor reads and applies
        it (``SetLongSystemParameter(WeatherMonitorSetting, ReadAndCalculateRefractions)``).
        Returns the air the server reports using (``GetEnvironmentParams``); raises
        DeviceFaultError if it is not the air given (a weather monitor overriding it)."""
        air = parse_environment(air)
        if air is None:
            raise ValueError("set_environment needs an Air or 'station'")
        if air == STATION:
            self.request(es.Request(Cmd.SetLongSystemParameter, {
                "systemParam": int(es.SystemParameter.WeatherMonitorSetting),
                "lParameter": int(es.WeatherMonitorStatus.ReadAndCalculateRefractions)}))
        else:
            self.request(es.Request(Cmd.SetEnvironmentParams, {
                "dTemperature": air.temperature_c, "dPressure": air.pressure_hpa, "dHumidity": air.humidity_pct}))
        v = self.request(es.Request(Cmd.GetEnvironmentParams)).values
        used = Air(v["dTemperature"], v["dPressure"], v["dHumidity"])
        if air != STATION and max(abs(used.temperature_c - air.temperature_c), abs(used.pressure_hpa - air.pressure_hpa),
                                   abs(used.humidity_pct - air.humidity_pct)) > 0.01:
            raise DeviceFaultError(f"{self.name}: the server uses {used} instead of the {air} sent; is its weather "
                                   "monitor set to ReadAndCalculateRefractions? Use environment: {source: station} "
                                   "or switch the monitor to read-only")
        self.air_in_use, self.air_source = used, ("station" if air == STATION else "host")
        self.log.info("air for refraction (%s): %.2f °C, %.2f hPa, %.1f %%", self.air_source, used.temperature_c,
                      used.pressure_hpa, used.humidity_pct)
        return used

    def reflectors(self) -> list[tuple[int, str, int, float]]:
        """The server's reflectors: (id, name, ES_TargetType, surface offset mm)."""
        answers = self._exchange(es.Request(Cmd.GetReflectors))[0]
        return [(a.values["iInternalReflectorId"], a.values["cReflectorName"], a.values["targetType"],
                 a.values["dSurfaceOffset"]) for a in answers]

    def select_reflector(self, reflector_type: str, offset_mm: float | None = None) -> tuple[int, str, float]:
        """Select the server's reflector named ``reflector_type`` (or of that ES_TargetType
        name, e.g. RRR15); with ``offset_mm``, its surface offset in the server's database must
        agree within 1 µm. Raises LimitError naming the reflectors the server knows."""
        known = self.reflectors()

        def norm(s: str) -> str:
            return "".join(ch for ch in s.upper() if ch.isalnum())

        want = norm(reflector_type)
        hits = [r for r in known if norm(r[1]) == want]
        if not hits:
            hits = [r for r in known if r[2] in [t.value for t in es.TargetType if norm(t.name) == want]]
        listing = ", ".join(f"{n!r} (id {i}, {es.TargetType(t).name if t in es.TargetType._value2member_map_ else t}, "
                            f"offset {o:.4f} mm)" for i, n, t, o in known)
        if not hits:
            raise LimitError(f"{self.name}: the emScon server has no reflector {reflector_type!r}; it has {listing}")
        rid, name, _, offset = hits[0]
        if offset_mm is not None and abs(offset - offset_mm) > 0.001:
            raise LimitError(f"{self.name}: reflector {name!r} has surface offset {offset:.4f} mm in the emScon "
                             f"database, the plan says {offset_mm:.4f} mm; correct one of them")
        self.request(es.Request(Cmd.SetReflector, {"iInternalReflectorId": rid}))
        self.reflector_in_use = (rid, name, offset)
        self.log.info("reflector %s (id %d), surface offset %.4f mm", name, rid, offset)
        return self.reflector_in_use

    def go_birdbath(self, timeout: float = 30.0) -> None:
        """Send the beam to the bird bath (the reflector's home on the tracker)."""
        self.request(es.Request(Cmd.GoBirdBath), timeout=self.reply_timeout + check_timeout(timeout))

    def aim(self, xyz_mm, timeout: float = 10.0) -> None:
        """``GoPosition`` (with ADM) to ``xyz_mm`` (shape (3,), tracker frame, mm); raises
        TargetLostError if no reflector is locked there afterwards."""
        p = np.asarray(xyz_mm, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"aim point must be 3 finite numbers (mm), got {xyz_mm!r}")
        self.request(es.Request(Cmd.GoPosition, {"dVal1": p[0], "dVal2": p[1], "dVal3": p[2], "bUseADM": 1}),
                     timeout=self.reply_timeout + check_timeout(timeout))
        self._last_xyz = p
        info = self.request(es.Request(Cmd.GetMeasurementStatusInfo)).values["lMeasurementStatusInfo"]
        if not info & REFLECTOR_FOUND:
            raise TargetLostError(f"{self.name}: GoPosition to ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm found no "
                                  "reflector there; try search()")

    def search(self, radius_mm: float, timeout: float, max_turns: int = 0) -> SearchResult:
        """``FindReflector`` within ``radius_mm`` around the current beam direction, for at most
        ``timeout`` seconds (``max_turns`` is not an emScon parameter and is ignored). Raises
        TargetLostError when nothing is found."""
        if not (isinstance(radius_mm, (int, float)) and math.isfinite(radius_mm) and 0 < radius_mm <= 10_000):
            raise ValueError(f"radius_mm must be in (0, 10000] mm, got {radius_mm!r}")
        timeout = check_timeout(timeout)
        params = (float(radius_mm), max(1, int(round(timeout * 1000))))
        if self._search != params:
            self.request(es.Request(Cmd.SetSearchParams, {"dSearchRadius": params[0], "lTimeOut": params[1]}))
            self._search = params
        approx = float(np.linalg.norm(self._last_xyz)) if self._last_xyz is not None else self.approx_distance_mm
        t0 = self.clock()
        try:
            self.request(es.Request(Cmd.FindReflector, {"dAproxDistance": approx}),
                         timeout=self.reply_timeout + timeout)
        except TargetLostError as exc:
            raise TargetLostError(f"{self.name}: FindReflector within {radius_mm:g} mm found no reflector "
                                  f"({exc})") from None
        return SearchResult(True, self.clock() - t0)

    def reacquire(self, xyz_mm, search_radius_mm: float | None = None, timeout: float = 30.0) -> None:
        """Aim at the predicted reflector position, and ``FindReflector`` there if that fails."""
        try:
            self.aim(xyz_mm, timeout)
        except TargetLostError:
            self.search(search_radius_mm or self.search_radius_mm, timeout)

    # ----------------------------------------------------------------- measuring
    def _set_stationary(self, meas_time_ms: int) -> None:
        want = (int(meas_time_ms), 1)
        if self._stationary != want:
            self.request(es.Request(Cmd.SetStationaryModeParams, {"lMeasTime": want[0], "bUseADM": want[1]}))
            self._stationary = want

    def _select_probe(self) -> None:
        """Check that a 6-DoF probe is there (``GetMeasurementProbeInfo``) and log what it is."""
        try:
            info = dict(self.request(es.Request(Cmd.GetMeasurementProbeInfo)).values)
        except (LimitError, DeviceFaultError) as exc:
            raise LimitError(f"{self.name}: pose measurement needs a 6-DoF probe (a T-Mac) on the tracker; the "
                             f"server has none ({exc}); measure the reflector's position instead (pose: false)") from None
        check_probe(info, self.name)
        self.probe_info = info
        self.log.info("6-DoF probe %s, serial %d", es.ProbeType(info["probeType"]).name, info["lSerialNumber"])

    def _stationary_measurement(self, meas_time_ms: int, timeout: float):
        """(xyz (3,) mm, std (3,) mm, host time, rotation (3, 3) or None, std_deg or None)."""
        self._set_stationary(meas_time_ms)
        result, host_time = self._exchange(es.Request(Cmd.StartMeasurement),
                                           timeout=max(timeout, meas_time_ms / 1000.0 + self.reply_timeout),
                                           want_result=True)
        v = result.values
        rotation = std_deg = None
        if result.type is es.DataType.StationaryProbeMeasResult:
            xyz, std, rotation, std_deg = probe_pose(v, self.name)  # degrees: the angle unit set on connect
        else:
            xyz = np.array([v["dVal1"], v["dVal2"], v["dVal3"]], dtype=float)
            std = np.array([v["dStd1"], v["dStd2"], v["dStd3"]], dtype=float)
        if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(std))):
            raise ProtocolError(f"{self.name}: the server sent a non-finite measurement {xyz} ± {std}")
        self._last_xyz = xyz
        return xyz, std, host_time, rotation, std_deg

    def marker_names(self) -> list[str]:
        return [self.marker]

    def _read_internal(self, timeout: float) -> list[MarkerSample]:
        """One short stationary measurement; ``visible=False`` (NaN) when no reflector is locked."""
        try:
            xyz, std, host_time, rotation, _ = self._stationary_measurement(self.read_time_ms, timeout)
        except TargetLostError as exc:
            self.log.info("%s", exc)
            return [MarkerSample(self.marker, np.full(3, np.nan), math.nan, self.clock(), visible=False)]
        return [MarkerSample(self.marker, xyz, math.nan, host_time, visible=True, std_mm=float(np.mean(std)),
                             rotation=rotation)]

    def measure(self, marker: str, n: int, timeout: float) -> MarkerMeasurement:
        """One stationary measurement averaging ``n`` internal points (see the module
        docstring). Raises TargetLostError when no reflector is locked or the beam breaks."""
        if marker != self.marker:
            raise ValueError(f"{self.name} measures marker {self.marker!r}, not {marker!r}")
        if not (isinstance(n, int) and 1 <= n <= MAX_AVERAGE):
            raise ValueError(f"n must be an integer in 1..{MAX_AVERAGE}, got {n!r}")
        timeout = check_timeout(timeout)
        meas_ms = self.measure_time_ms or max(1, math.ceil(n * 1000.0 / self.point_rate_hz))
        xyz, std, host_time, rotation, std_deg = self._stationary_measurement(meas_ms, timeout)
        return MarkerMeasurement(self.marker, xyz, std, n, math.nan, host_time, rotation=rotation, std_deg=std_deg)
