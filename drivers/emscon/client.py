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

The sensor is a façade over collaborators, one module each: ``channel`` (the TCP connection,
one command in flight, answers matched by command id, notifications; after a timeout the
connection is closed and the next command opens a new one, so a late answer can never be taken
for the next), ``configuration`` (the connect-time preparation, status, air, reflector, probe),
``measuring`` (stationary measurements) and ``steering`` (aim, search, bird bath).
Errors: every refused command raises the class ``drivers.emscon.status`` maps its
``ES_ResultStatus`` to (with ``status`` / ``status_name``); no answer in time →
DeviceTimeoutError; transport closed → ConnectionLostError; unreadable bytes → ProtocolError.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from drivers.base import Clock, SensorBase, check_timeout
from drivers.emscon import codec as es
from drivers.emscon.channel import EmsconChannel, parse_url
from drivers.emscon.configuration import REFLECTOR_FOUND, EmsconStatus, TrackerConfiguration
from drivers.emscon.measuring import StationaryMeasurer
from drivers.emscon.steering import BeamSteering, SearchResult
from drivers.errors import TargetLostError
from drivers.protocols import MarkerMeasurement, MarkerSample
from drivers.tracker.air import Air, parse_environment, parse_reflector
from drivers.tracker.codec import MAX_AVERAGE

__all__ = ["EmsconSensor", "EmsconStatus", "SearchResult", "REFLECTOR_FOUND", "parse_url"]


def _held_by(part: str, name: str, doc: str) -> property:
    """A read-only attribute of the sensor that its collaborator ``part`` holds as ``name``."""
    return property(lambda self: getattr(getattr(self, part), name), doc=doc)


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
        self._channel = EmsconChannel(url, name=name, reply_timeout=reply_timeout, auto_reconnect=auto_reconnect,
                                      clock=clock, log=self.log)
        self.host, self.port, self.url = self._channel.host, self._channel.port, url
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
        self.marker = marker
        self.reply_timeout = self._channel.reply_timeout
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
        self._config = TrackerConfiguration(self._channel, initialize=initialize,
                                            initialize_timeout=self.initialize_timeout, pose=pose)
        self._measurer = StationaryMeasurer(self._channel)
        self._steering = BeamSteering(self._channel, search_radius_mm=self.search_radius_mm,
                                      approx_distance_mm=self.approx_distance_mm, clock=clock)

    @classmethod
    def from_url(cls, url: str, marker: str = "smr", **kwargs: Any) -> "EmsconSensor":
        """A sensor for ``url`` (not yet connected: ``connect()`` or ``with``)."""
        return cls(url, marker=marker, **kwargs)

    # ----------------------------------------------------------------- what the collaborators hold
    events = _held_by("_channel", "events", "Notifications as (ES_SystemStatusChange, host time), newest last.")
    beam_ready = _held_by("_channel", "beam_ready", "Beam state of the last MeasStatus notification (None: none yet).")
    probe_info = _held_by("_config", "probe_info", "``GetMeasurementProbeInfo`` of the 6-DoF probe, after connect.")
    air_in_use = _held_by("_config", "air_in_use", "The air (``Air``) the server reports using, after set_environment.")
    air_source = _held_by("_config", "air_source", "Where that air came from: ``station`` or ``host``.")
    reflector_in_use = _held_by("_config", "reflector_in_use", "(id, name, surface offset mm) of the reflector.")

    # ----------------------------------------------------------------- connection
    def connect(self) -> None:
        with self._channel.lock:
            if self._channel.connected:
                return
            self._channel.open()
            try:
                self._measurer.forget_parameters()
                self._steering.forget_parameters()
                self._config.prepare(self.environment, self.reflector)
            except BaseException:
                self.close()
                raise

    def close(self) -> None:
        self._channel.close()

    @property
    def connected(self) -> bool:
        return self._channel.connected

    def request(self, req: es.Request, timeout: float | None = None) -> es.Answer:
        """Send ``req`` and return its answer (raises the mapped error for a refusal)."""
        return self._channel.request(req, timeout)

    # ----------------------------------------------------------------- tracker commands
    def status(self) -> EmsconStatus:
        return self._config.status()

    def set_environment(self, air: Air | str | dict) -> Air:
        """See ``TrackerConfiguration.set_environment``: the air the server reports using."""
        return self._config.set_environment(air)

    def reflectors(self) -> list[tuple[int, str, int, float]]:
        """The server's reflectors: (id, name, ES_TargetType, surface offset mm)."""
        return self._config.reflectors()

    def select_reflector(self, reflector_type: str, offset_mm: float | None = None) -> tuple[int, str, float]:
        """See ``TrackerConfiguration.select_reflector``: (id, name, surface offset mm)."""
        return self._config.select_reflector(reflector_type, offset_mm)

    def go_birdbath(self, timeout: float = 30.0) -> None:
        """Send the beam to the bird bath (the reflector's home on the tracker)."""
        self._steering.go_birdbath(timeout)

    def aim(self, xyz_mm, timeout: float = 10.0) -> None:
        """``GoPosition`` to ``xyz_mm`` (shape (3,), mm); TargetLostError if nothing is locked there."""
        self._steering.aim(xyz_mm, timeout)

    def search(self, radius_mm: float, timeout: float, max_turns: int = 0) -> SearchResult:
        """``FindReflector`` within ``radius_mm`` for at most ``timeout`` s; TargetLostError if none."""
        return self._steering.search(radius_mm, timeout, max_turns)

    def reacquire(self, xyz_mm, search_radius_mm: float | None = None, timeout: float = 30.0) -> None:
        """Aim at the predicted reflector position, and ``FindReflector`` there if that fails."""
        self._steering.reacquire(xyz_mm, search_radius_mm, timeout)

    # ----------------------------------------------------------------- measuring
    def _stationary_measurement(self, meas_time_ms: int, timeout: float):
        """(xyz (3,) mm, std (3,) mm, host time, rotation (3, 3) or None, std_deg or None)."""
        out = self._measurer.measure(meas_time_ms, timeout)
        self._steering.last_xyz = out[0]
        return out

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
