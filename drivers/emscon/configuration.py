"""``TrackerConfiguration``: what the tracker is told before it measures, and what it says of itself.

On connect a metrology engineer's preparation: ``Initialize`` (only if the server reports the
tracker not initialised, or always with ``initialize="always"``), units mm / degree / °C / hPa /
%RH, right-handed Cartesian coordinates (RHR), the 6-DoF probe checked (pose mode), stationary
(or 6D stationary) measurement mode; then the air for the refraction correction and the
reflector, if given. ``status()`` reads ``GetSystemStatus`` / ``GetTrackerStatus`` /
``GetMeasurementStatusInfo``.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.emscon import codec as es
from drivers.emscon.channel import EmsconChannel
from drivers.emscon.codec import Cmd
from drivers.emscon.probe import check_probe
from drivers.errors import DeviceFaultError, LimitError
from drivers.tracker.air import STATION, Air, parse_environment

#: ``ES_MeasurementStatusInfo`` flag: a reflector is locked.
REFLECTOR_FOUND = 2048


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


class TrackerConfiguration:
    """Units, coordinates, mode, air, reflector and probe of the tracker behind ``channel``.

    initialize: ``"auto"`` / ``"always"`` / ``"never"``; initialize_timeout: seconds
    ``Initialize`` may take; pose: 6D stationary mode with a 6-DoF probe. After ``prepare``:
    ``air_in_use`` (``Air``) and ``air_source`` (``"station"`` / ``"host"``), ``reflector_in_use``
    (id, name, surface offset mm), ``probe_info`` (``GetMeasurementProbeInfo`` values, pose mode).
    """

    def __init__(self, channel: EmsconChannel, *, initialize: str, initialize_timeout: float, pose: bool) -> None:
        self.channel = channel
        self.name = channel.name
        self.log = channel.log
        self.initialize = initialize
        self.initialize_timeout = initialize_timeout
        self.pose = pose
        self.probe_info: dict | None = None
        self.air_in_use: Air | None = None
        self.air_source: str | None = None
        self.reflector_in_use: tuple[int, str, float] | None = None

    def prepare(self, environment: Air | None, reflector: tuple | None) -> None:
        """The connect-time preparation (see the module docstring)."""
        request = self.channel.request
        st = self.status()
        self.log.info("emScon server %d.%d.%d, tracker serial %d, %s, %s", *st.server_version, st.serial_number,
                      "initialised" if st.initialized else "not initialised",
                      "warm" if st.warmed_up else "warming up")
        if self.initialize == "always" or (self.initialize == "auto" and not st.initialized):
            self.log.info("initialising the tracker (may take up to %.0f s)", self.initialize_timeout)
            request(es.Request(Cmd.Initialize), timeout=self.initialize_timeout)
        request(es.Request(Cmd.SetUnits, {
            "lenUnitType": int(es.LengthUnit.Millimeter), "angUnitType": int(es.AngleUnit.Degree),
            "tempUnitType": int(es.TemperatureUnit.Celsius), "pressUnitType": int(es.PressureUnit.HPascal),
            "humUnitType": int(es.HumidityUnit.RH)}))
        request(es.Request(Cmd.SetCoordinateSystemType, {"coordSysType": int(es.CoordinateSystem.RHR)}))
        if self.pose:
            self.select_probe()
        request(es.Request(Cmd.SetMeasurementMode, {"measMode": int(
            es.MeasMode.SixDStationary if self.pose else es.MeasMode.Stationary)}))
        if environment is not None:
            self.set_environment(environment)
        if reflector is not None:
            self.select_reflector(*reflector)

    def status(self) -> EmsconStatus:
        request = self.channel.request
        sysst = request(es.Request(Cmd.GetSystemStatus)).values
        trk = request(es.Request(Cmd.GetTrackerStatus)).values
        info = request(es.Request(Cmd.GetMeasurementStatusInfo)).values
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
        request = self.channel.request
        air = parse_environment(air)
        if air is None:
            raise ValueError("set_environment needs an Air or 'station'")
        if air == STATION:
            request(es.Request(Cmd.SetLongSystemParameter, {
                "systemParam": int(es.SystemParameter.WeatherMonitorSetting),
                "lParameter": int(es.WeatherMonitorStatus.ReadAndCalculateRefractions)}))
        else:
            request(es.Request(Cmd.SetEnvironmentParams, {
                "dTemperature": air.temperature_c, "dPressure": air.pressure_hpa, "dHumidity": air.humidity_pct}))
        v = request(es.Request(Cmd.GetEnvironmentParams)).values
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
        answers = self.channel.exchange(es.Request(Cmd.GetReflectors))[0]
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
        self.channel.request(es.Request(Cmd.SetReflector, {"iInternalReflectorId": rid}))
        self.reflector_in_use = (rid, name, offset)
        self.log.info("reflector %s (id %d), surface offset %.4f mm", name, rid, offset)
        return self.reflector_in_use

    def select_probe(self) -> None:
        """Check that a 6-DoF probe is there (``GetMeasurementProbeInfo``) and log what it is."""
        try:
            info = dict(self.channel.request(es.Request(Cmd.GetMeasurementProbeInfo)).values)
        except (LimitError, DeviceFaultError) as exc:
            raise LimitError(f"{self.name}: pose measurement needs a 6-DoF probe (a T-Mac) on the tracker; the "
                             f"server has none ({exc}); measure the reflector's position instead (pose: false)") from None
        check_probe(info, self.name)
        self.probe_info = info
        self.log.info("6-DoF probe %s, serial %d", es.ProbeType(info["probeType"]).name, info["lSerialNumber"])
