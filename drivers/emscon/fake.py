"""A fake Leica emScon server (TPI 3.6, an AT401-like ADM-only sensor) over real TCP.

``FakeEmscon`` is the server logic: it decodes the binary packets of ``drivers.emscon.codec``,
keeps the server's settings (units, coordinate system, measurement mode, stationary and search
parameters, reflector, weather monitor, initialisation) and drives a ``FakeTracker``
(``drivers.tracker.fake``) for everything physical: the reflector's true position from the
simulated scene, beam lock and breaks, re-acquisition by aim and spiral search, warm-up, noise,
refraction. One ``FakeTracker`` may sit behind both the line-protocol server and this one.
``EmsconServer`` serves it on 127.0.0.1 (the real server's port is 700; the fake takes an
ephemeral one by default) with the line server's fault hooks (``drop``, ``stall``, ``garble``).

Behaviour, from the TPI header and manual where they say it, our choice (marked) where not:

- Every command is answered with its ``...RT`` struct (full size, result fields zero when the
  status is not ``ES_RS_AllOK``), except ``StartMeasurement`` in stationary mode, which is
  answered by one ``SingleMeasResultT`` only (the SDK's ``OnStartMeasurementAnswer`` is "called
  only in continuous mode"); a refused ``StartMeasurement`` gets its ``RT`` with the status.
- ``GetReflectors`` answers one ``GetReflectorsRT`` per reflector (``iTotalReflectors`` in each).
- A packet that cannot be read as a command (bad size, type, unknown command id) is answered
  with ``ErrorResponseT`` (``ES_DT_Error``) — *our choice*.
- Notifications (``SystemStatusChangeT``): ``MeasStatus_NotReady`` when the beam breaks,
  ``MeasStatus_Ready`` when it locks, ``DistanceSet`` once the ADM has measured the distance,
  ``LaserWarmedUp`` at the end of warm-up, and the ``...Changed`` notification after each
  setting, sent after the command's answer.
- Refusals: no reflector locked → ``MeasurementStatusNotReady``; beam lost during a stationary
  measurement → ``NoStationaryResult``; warming up → ``SensorNotWarmedUp``; measuring or moving
  before ``Initialize`` → ``TrackerNotInitialized``; ``FindReflector`` that finds nothing →
  ``MeasurementStatusNotReady`` (*our choice; unverified*); ``GoPosition`` always succeeds (the
  beam moved) and the lock shows in ``GetTrackerStatus`` and the notifications.
- 6-DoF: when the tracker carries a 6-DoF target (``FakeTracker(six_dof=True)``, a T-Mac:
  ``GetMeasurementProbeInfo`` says ``ES_PT_MachineControlProbe``), ``SetMeasurementMode
  (ES_MM_6DStationary)`` is accepted and ``StartMeasurement`` answers one ``ProbeStationaryResultT``
  (``ES_DT_StationaryProbeMeasResult``): the tracker's ``POSE`` average (position, quaternion
  ``R_tracker←probe`` scalar first, per-axis spreads). Without one, 6D modes are refused with
  ``ES_RS_6DModeNotAllowed`` and ``GetMeasurementProbeInfo`` with ``ES_RS_NoMeasurementProbe``.
  The rotation angles ``dRotationAngleX/Y/Z`` are filled as R = Rz(Z)·Ry(Y)·Rx(X) in the angle
  unit set (*our choice*: the header does not state their convention; our client reads the
  quaternion), their std devs with the rotation-vector spread per axis.
- Only the RHR (Cartesian, right-handed) coordinate system and stationary (3D or 6D) modes are
  emulated; the others are refused with ``NotImplemented``. Every length, temperature and pressure on the
  wire is in the units set with ``SetUnits`` (default after start: mm, °C, mbar... as ``units``).
- A stationary measurement of ``lMeasTime`` ms averages lMeasTime·rate/1000 points of the
  tracker (``FakeTracker.average_rate_hz``); ``dStd1..3`` are their per-axis spread,
  ``dAprioriStd*`` the tracker's noise model, ``dTemperature/dPressure/dHumidity`` the air used.
"""

from __future__ import annotations

import logging
import math
import threading

import numpy as np

from drivers.emscon import codec as es
from drivers.emscon.codec import Cmd, SSC, Status
from drivers.tracker.air import Air
from drivers.tracker.codec import (
    MAX_AVERAGE,
    Aim,
    Environment,
    ErrorCode,
    MeasureAverage,
    MeasurePose,
    Search,
    SelectReflector,
)
from drivers.tracker.fake import DeviceRefusal, FakeTracker, TcpTrackerServer

log = logging.getLogger("remaster.fake.emscon")

#: millimetres per length unit.
MM_PER_UNIT = {es.LengthUnit.Meter: 1000.0, es.LengthUnit.Millimeter: 1.0, es.LengthUnit.Micron: 1e-3,
               es.LengthUnit.Foot: 304.8, es.LengthUnit.Yard: 914.4, es.LengthUnit.Inch: 25.4}
#: hPa per pressure unit.
HPA_PER_UNIT = {es.PressureUnit.Mbar: 1.0, es.PressureUnit.HPascal: 1.0, es.PressureUnit.KPascal: 10.0,
                es.PressureUnit.MmHg: 1.333224, es.PressureUnit.Psi: 68.94757, es.PressureUnit.InH2O: 2.490889,
                es.PressureUnit.InHg: 33.86389}

_UNIT_ENUMS = (("lenUnitType", es.LengthUnit), ("angUnitType", es.AngleUnit), ("tempUnitType", es.TemperatureUnit),
               ("pressUnitType", es.PressureUnit), ("humUnitType", es.HumidityUnit))

#: Tracker-side refusal → emScon status.
_REFUSAL_STATUS = {
    ErrorCode.BEAM_LOST: Status.MeasurementStatusNotReady,
    ErrorCode.DISTANCE_INVALID: Status.NoDistanceSet,
    ErrorCode.WARMING_UP: Status.SensorNotWarmedUp,
    ErrorCode.NO_WEATHER_STATION: Status.NoWeathermonitorFound,
    ErrorCode.BAD_ARGUMENT: Status.WrongParameter,
}


class _Refused(Exception):
    def __init__(self, status: Status, text: str = "") -> None:
        super().__init__(text or status.name)
        self.status = Status(status)


class _Framing:
    """What the shared TCP server loop needs from a codec: framing, and an answer to a stream
    whose framing broke (``ErrorResponseT`` with ``InvalidInputData``)."""

    @staticmethod
    def split_frames(buffer: bytearray) -> list[bytes]:
        return es.split_frames(buffer)

    @staticmethod
    def encode_reply(_rid, _reply) -> bytes:
        return es.encode(es.ErrorAnswer(Cmd.Unknown, Status.InvalidInputData))


class FakeEmscon:
    """emScon server logic around ``tracker``; thread-safe (the tracker's lock serialises).

    require_initialize: refuse measurements and moves until ``Initialize`` (a real server after
    start-up). initialize_s: device seconds ``Initialize`` takes. serial: the tracker's serial
    number. units: the units in force at start (``SystemUnitsDataT`` values; default mm, degree,
    °C, mbar, %RH).
    """

    def __init__(
        self,
        tracker: FakeTracker,
        *,
        require_initialize: bool = True,
        initialize_s: float = 0.5,
        serial: int = 390_001,
        build: int = 1234,
        units: dict | None = None,
    ) -> None:
        if not (math.isfinite(initialize_s) and initialize_s >= 0):
            raise ValueError(f"initialize_s must be a non-negative number of seconds, got {initialize_s!r}")
        self.tracker = tracker
        self.codec = _Framing()
        self.initialized = not require_initialize
        self.initialize_s = float(initialize_s)
        self.serial = int(serial)
        self.build = int(build)
        self.units = {"lenUnitType": es.LengthUnit.Millimeter, "angUnitType": es.AngleUnit.Degree,
                      "tempUnitType": es.TemperatureUnit.Celsius, "pressUnitType": es.PressureUnit.Mbar,
                      "humUnitType": es.HumidityUnit.RH}
        if units:
            self.units.update({k: int(v) for k, v in units.items()})
        self.coord_sys = es.CoordinateSystem.RHR
        self.meas_mode = es.MeasMode.Stationary
        self.meas_time_ms = 1000
        self.use_adm = 1
        self.search_radius_mm = 50.0
        self.search_timeout_ms = 10_000
        self.reflector_names = list(tracker.reflectors)
        self.long_params: dict[int, int] = {int(es.SystemParameter.WeatherMonitorSetting):
                                            int(es.WeatherMonitorStatus.ReadOnly if tracker.weather_station
                                                else es.WeatherMonitorStatus.NotConnected)}
        self.last_status = Status.AllOK
        self.last_point_mm: np.ndarray | None = None
        self.commands_seen = 0
        self._listeners: list = []
        self._warm_notified = tracker.warmup_left_s() == 0
        tracker.add_event_hook(self._on_event)

    # ----------------------------------------------------------------- plumbing
    @property
    def _lock(self) -> threading.RLock:
        return self.tracker.lock

    def add_listener(self, send) -> None:
        """``send(packet: bytes)`` receives every notification packet."""
        with self._lock:
            self._listeners.append(send)

    def remove_listener(self, send) -> None:
        with self._lock:
            if send in self._listeners:
                self._listeners.remove(send)

    def close(self) -> None:
        self.tracker.remove_event_hook(self._on_event)

    def _notify(self, change: SSC) -> None:
        packet = es.encode(es.StatusChange(int(change)))
        for send in list(self._listeners):
            send(packet)

    def _on_event(self, name: str, _t: float) -> None:
        if name == "BEAM_LOST":
            self._notify(SSC.MeasStatus_NotReady)
        elif name == "BEAM_LOCKED":
            self._notify(SSC.MeasStatus_Ready)
            if self.tracker.distance_valid:
                self._notify(SSC.DistanceSet)

    def tick(self) -> None:
        """Let the beam follow the scene; announce the end of warm-up once."""
        with self._lock:
            self.tracker.tick()
            if not self._warm_notified and self.tracker.warmup_left_s() == 0:
                self._warm_notified = True
                self._notify(SSC.LaserWarmedUp)

    def handle(self, frame: bytes) -> bytes:
        """Answer one request packet: the answer packet(s), then any setting notifications."""
        with self._lock:
            self.commands_seen += 1
            try:
                req = es.decode_request(frame)
            except es.RequestRefused as exc:
                log.debug("refused packet: %s", exc)
                self.last_status = exc.status
                if exc.as_error:
                    return es.encode(es.ErrorAnswer(int(exc.command), exc.status))
                return es.encode(es.Answer(int(exc.command), exc.status))
            after: list[SSC] = []
            try:
                out = self._dispatch(req, after)
            except _Refused as exc:
                log.info("%s refused: %s (%s)", req.command.name, exc.status.name, exc)
                self.last_status = exc.status
                return es.encode(es.Answer(req.command, exc.status))
            self.last_status = Status.AllOK
            packets = b"".join(es.encode(p) for p in out)
            return packets + b"".join(es.encode(es.StatusChange(int(c))) for c in after)

    # ----------------------------------------------------------------- units
    def _mm(self, value: float) -> float:
        return value * MM_PER_UNIT[es.LengthUnit(self.units["lenUnitType"])]

    def _from_mm(self, mm):
        return mm / MM_PER_UNIT[es.LengthUnit(self.units["lenUnitType"])]

    def _celsius(self, t: float) -> float:
        return (t - 32.0) / 1.8 if self.units["tempUnitType"] == es.TemperatureUnit.Fahrenheit else t

    def _from_celsius(self, t: float) -> float:
        return t * 1.8 + 32.0 if self.units["tempUnitType"] == es.TemperatureUnit.Fahrenheit else t

    def _hpa(self, p: float) -> float:
        return p * HPA_PER_UNIT[es.PressureUnit(self.units["pressUnitType"])]

    def _from_hpa(self, p: float) -> float:
        return p / HPA_PER_UNIT[es.PressureUnit(self.units["pressUnitType"])]

    def _air_values(self) -> dict:
        t = self.tracker
        air = t.station_air() if t.env_source == "STATION" else t.assumed_air
        return {"dTemperature": self._from_celsius(air.temperature_c), "dPressure": self._from_hpa(air.pressure_hpa),
                "dHumidity": air.humidity_pct}

    # ----------------------------------------------------------------- commands
    def _run(self, command):
        try:
            return self.tracker.execute(command)
        except DeviceRefusal as exc:
            raise _Refused(_REFUSAL_STATUS.get(exc.code, Status.Unknown), str(exc)) from None

    def _need_initialized(self) -> None:
        if not self.initialized:
            raise _Refused(Status.TrackerNotInitialized, "send Initialize first")

    def _dispatch(self, req: es.Request, after: list[SSC]) -> list:
        c, p = req.command, req.params
        ok = es.Answer

        if c is Cmd.Initialize:
            if self.initialize_s > 0:
                self.tracker.clock.sleep(self.initialize_s)
            self.initialized = True
            after.append(SSC.SCC_InitializationStatusChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetSystemStatus:
            warm = self.tracker.warmup_left_s() == 0
            wm = self.long_params[int(es.SystemParameter.WeatherMonitorSetting)]
            return [ok(c, Status.AllOK, {
                "lastResultStatus": int(self.last_status),
                "trackerProcessorStatus": int(es.TrackerProcessorStatus.Initialized if self.initialized
                                              else es.TrackerProcessorStatus.CompensationSet),
                "laserStatus": int(es.LaserProcessorStatus.LaserReady if warm else es.LaserProcessorStatus.LaserHeatingUp),
                "admStatus": int(es.ADMStatus.ADMReady),
                "iMajorVersionNumber": es.API_VERSION[0], "iMinorVersionNumber": es.API_VERSION[1],
                "iBuildNumber": self.build, "weatherMonitorStatus": wm, "lFlagsValue": 0,
                "lTrackerSerialNumber": self.serial})]
        if c is Cmd.GetTrackerStatus:
            t = self.tracker
            t.tick()
            ready = self.initialized and t.locked and t.distance_valid and t.warmup_left_s() == 0
            return [ok(c, Status.AllOK, {"trackerStatus": int(es.TrackerStatus.Ready if ready else es.TrackerStatus.NotReady)})]
        if c is Cmd.GetMeasurementStatusInfo:
            t = self.tracker
            t.tick()
            flags = 1 | 2 | 4 | 8 | 4096 | (2048 if t.locked else 0) | (65536 if self.initialized else 0)
            return [ok(c, Status.AllOK, {"lastResultStatus": int(self.last_status), "lMeasurementStatusInfo": flags})]
        if c is Cmd.GetMeasurementProbeInfo:
            if not self.tracker.six_dof:
                raise _Refused(Status.NoMeasurementProbe, "no 6-DoF probe on this tracker")
            return [ok(c, Status.AllOK, {
                "iFirmwareMajorVersionNumber": 1, "iFirmwareMinorVersionNumber": 0, "lSerialNumber": self.serial + 1,
                "probeType": int(es.ProbeType.MachineControlProbe), "lCompensationIdNumber": 1, "lActiveField": 0,
                "connectionType": int(es.ProbeConnectionType.CableSensor), "lNumberOfTipAdapters": 1,
                "probeButtonType": int(es.ProbeButtonType.None_), "lNumberOfFields": 1, "bHasWideAngleReceiver": 0,
                "lNumberOfTipDataSets": 1, "lNumberOfMelodies": 0, "lNumberOfLoudnesSteps": 0})]
        if c is Cmd.GetSystemSoftwareVersion:
            return [ok(c, Status.AllOK, {"cSoftwareVersion": f"emScon {es.API_VERSION[0]}.{es.API_VERSION[1]}.{self.build} (remaster fake)"[:32]})]
        if c is Cmd.SetUnits:
            for i, (name, enum) in enumerate(_UNIT_ENUMS):
                try:
                    enum(p[name])
                except ValueError:
                    raise _Refused(es.wrong_parameter(i + 1), f"{name}={p[name]} is not one of "
                                   f"{[int(x) for x in enum]}") from None
            self.units = dict(p)
            after.append(SSC.UnitsChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetUnits:
            return [ok(c, Status.AllOK, dict(self.units))]
        if c is Cmd.SetCoordinateSystemType:
            if p["coordSysType"] != es.CoordinateSystem.RHR:
                raise _Refused(Status.NotImplemented, "this fake emulates the RHR coordinate system only")
            self.coord_sys = es.CoordinateSystem.RHR
            after.append(SSC.CoordinateSystemTypeChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetCoordinateSystemType:
            return [ok(c, Status.AllOK, {"coordSysType": int(self.coord_sys)})]
        if c is Cmd.SetMeasurementMode:
            mode = p["measMode"]
            if mode == es.MeasMode.SixDStationary and not self.tracker.six_dof:
                raise _Refused(Status.SixDModeNotAllowed, "no 6-DoF probe on this tracker")
            if mode not in (es.MeasMode.Stationary, es.MeasMode.SixDStationary):
                raise _Refused(Status.NotImplemented, "this fake emulates stationary (3D and 6D) measurements only")
            self.meas_mode = es.MeasMode(mode)
            after.append(SSC.MeasurementModeChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetMeasurementMode:
            return [ok(c, Status.AllOK, {"measMode": int(self.meas_mode)})]
        if c is Cmd.SetStationaryModeParams:
            if not 1 <= p["lMeasTime"] <= MAX_AVERAGE:
                raise _Refused(Status.Parameter1OutOfRangeNOK, f"lMeasTime must be 1..{MAX_AVERAGE} ms")
            if p["bUseADM"] not in (0, 1):
                raise _Refused(Status.WrongParameter2, "bUseADM must be 0 or 1")
            self.meas_time_ms, self.use_adm = p["lMeasTime"], p["bUseADM"]
            after.append(SSC.StationaryModeParamsChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetStationaryModeParams:
            return [ok(c, Status.AllOK, {"lMeasTime": self.meas_time_ms, "bUseADM": self.use_adm})]
        if c is Cmd.SetSearchParams:
            radius = self._mm(p["dSearchRadius"])
            if not 0.001 <= radius <= 10_000:
                raise _Refused(Status.Parameter1OutOfRangeNOK, "search radius must be 0.001..10000 mm")
            if not 1 <= p["lTimeOut"] <= 3_600_000:
                raise _Refused(Status.Parameter2OutOfRangeNOK, "search timeout must be 1..3600000 ms")
            self.search_radius_mm, self.search_timeout_ms = radius, p["lTimeOut"]
            after.append(SSC.SearchParamsChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetSearchParams:
            return [ok(c, Status.AllOK, {"dSearchRadius": self._from_mm(self.search_radius_mm),
                                         "lTimeOut": self.search_timeout_ms})]
        if c is Cmd.SetEnvironmentParams:
            try:
                air = Air(self._celsius(p["dTemperature"]), self._hpa(p["dPressure"]), p["dHumidity"])
            except ValueError as exc:
                raise _Refused(Status.MeteoDataOutOfRange, str(exc)) from None
            self._run(Environment("HOST", air.temperature_c, air.pressure_hpa, air.humidity_pct))
            if self.long_params[int(es.SystemParameter.WeatherMonitorSetting)] == es.WeatherMonitorStatus.ReadAndCalculateRefractions:
                self.long_params[int(es.SystemParameter.WeatherMonitorSetting)] = int(es.WeatherMonitorStatus.ReadOnly)
            after.append(SSC.EnvironmentParamsChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetEnvironmentParams:
            return [ok(c, Status.AllOK, self._air_values())]
        if c is Cmd.SetLongSystemParameter:
            param, value = p["systemParam"], p["lParameter"]
            if param == es.SystemParameter.WeatherMonitorSetting:
                if value not in [int(x) for x in es.WeatherMonitorStatus]:
                    raise _Refused(Status.WrongParameter2, "weather monitor setting must be 0, 1 or 2")
                if value == es.WeatherMonitorStatus.ReadAndCalculateRefractions:
                    self._run(Environment("STATION"))
                elif value != es.WeatherMonitorStatus.NotConnected and not self.tracker.weather_station:
                    raise _Refused(Status.NoWeathermonitorFound, "no weather station connected")
                else:
                    a = self.tracker.assumed_air
                    self._run(Environment("HOST", a.temperature_c, a.pressure_hpa, a.humidity_pct))
                after.append(SSC.EnvironmentParamsChanged)
            self.long_params[int(param)] = int(value)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetLongSystemParameter:
            return [ok(c, Status.AllOK, {"systemParam": p["systemParam"],
                                         "lParameter": self.long_params.get(int(p["systemParam"]), 0)})]
        if c is Cmd.SetReflector:
            rid = p["iInternalReflectorId"]
            if not 0 <= rid < len(self.reflector_names):
                raise _Refused(Status.WrongParameter1, f"no reflector with id {rid}; ids 0..{len(self.reflector_names) - 1}")
            self._run(SelectReflector(self.reflector_names[rid]))
            after.append(SSC.ReflectorChanged)
            return [ok(c, Status.AllOK)]
        if c is Cmd.GetReflector:
            return [ok(c, Status.AllOK, {"iInternalReflectorId": self.reflector_names.index(self.tracker.reflector_kind.name)})]
        if c is Cmd.GetReflectors:
            n = len(self.reflector_names)
            out = []
            for i, name in enumerate(self.reflector_names):
                r = self.tracker.reflectors[name]
                out.append(ok(c, Status.AllOK, {"iTotalReflectors": n, "iInternalReflectorId": i,
                                                "targetType": r.target_type,
                                                "dSurfaceOffset": self._from_mm(r.surface_offset_mm),
                                                "cReflectorName": r.name}))
            return out
        if c is Cmd.StartMeasurement:
            self._need_initialized()
            return [self._six_d() if self.meas_mode == es.MeasMode.SixDStationary else self._stationary()]
        if c is Cmd.StopMeasurement or c is Cmd.ExitApplication:
            return [ok(c, Status.AllOK)]
        if c in (Cmd.GoPosition, Cmd.PointLaser, Cmd.GoBirdBath, Cmd.Park, Cmd.GoLastMeasuredPoint):
            self._need_initialized()
            if c is Cmd.GoBirdBath or c is Cmd.Park:
                target = np.array([1000.0, 0.0, 0.0]) if c is Cmd.GoBirdBath else np.array([0.0, 0.0, 1000.0])
            elif c is Cmd.GoLastMeasuredPoint:
                if self.last_point_mm is None:
                    raise _Refused(Status.NoLastMeasuredPoint, "nothing measured yet")
                target = self.last_point_mm
            else:
                target = np.array([self._mm(p["dVal1"]), self._mm(p["dVal2"]), self._mm(p["dVal3"])])
            try:
                aim = Aim(*map(float, target))
            except ValueError as exc:
                raise _Refused(Status.WrongParameter, str(exc)) from None
            self._run(aim)
            return [ok(c, Status.AllOK)]
        if c is Cmd.FindReflector:
            self._need_initialized()
            if not p["dAproxDistance"] > 0:
                raise _Refused(Status.WrongParameter1, "dAproxDistance must be positive")
            reply = self._run(Search(min(self.search_radius_mm, 10_000.0), self.search_timeout_ms / 1000.0, 0))
            if not reply.found:
                raise _Refused(Status.MeasurementStatusNotReady,
                               f"no reflector within {self.search_radius_mm:g} mm in {reply.elapsed_s:.2f} s")
            return [ok(c, Status.AllOK)]
        raise _Refused(Status.NotImplemented, f"{c.name} is not emulated")

    def _stationary(self) -> es.DataResult:
        t = self.tracker
        avg = self._averaged(MeasureAverage)
        xyz = avg.xyz_mm
        std = avg.std_xyz_mm
        self.last_point_mm = xyz
        sigma = t.sigma_mm(float(np.linalg.norm(xyz)))
        air = self._air_values()
        v = self._from_mm
        return es.DataResult(es.DataType.SingleMeasResult, Status.AllOK, {
            "measMode": int(es.MeasMode.Stationary), "bIsTryMode": 0,
            "dVal1": v(xyz[0]), "dVal2": v(xyz[1]), "dVal3": v(xyz[2]),
            "dStd1": v(std[0]), "dStd2": v(std[1]), "dStd3": v(std[2]),
            "dStdTotal": v(float(np.linalg.norm(std))),
            "dPointingError1": 0.0, "dPointingError2": 0.0, "dPointingError3": 0.0,
            "dAprioriStd1": v(sigma), "dAprioriStd2": v(sigma), "dAprioriStd3": v(sigma),
            "dAprioriStdTotal": v(sigma * math.sqrt(3.0)), **air})

    def _averaged(self, command):
        """Run ``command(n)`` (``MeasureAverage`` or ``MeasurePose``) over the stationary
        measurement time: a beam break before it is NotReady, one during it NoStationaryResult."""
        t = self.tracker
        n = max(1, min(MAX_AVERAGE, round(self.meas_time_ms * t.average_rate_hz / 1000.0)))
        t.tick()
        was_locked = t.locked
        try:
            return self._run(command(n))
        except _Refused as exc:
            if exc.status is Status.MeasurementStatusNotReady and was_locked and not t.locked:
                raise _Refused(Status.NoStationaryResult, "the beam broke during the measurement") from None
            raise

    def _six_d(self) -> es.DataResult:
        """A 6-DoF stationary measurement (``ProbeStationaryResultT``) from the tracker's POSE."""
        from calib.robot.transforms import matrix_to_euler_zyx, quat_to_matrix

        t = self.tracker
        pose = self._averaged(MeasurePose)
        xyz, std = pose.xyz_mm, pose.std_xyz_mm
        self.last_point_mm = xyz
        sigma = t.sigma_mm(float(np.linalg.norm(xyz)))
        a_sigma = math.degrees(t.attitude_noise_rad)
        yaw, pitch, roll = matrix_to_euler_zyx(quat_to_matrix(pose.quat_wxyz))
        ang = {es.AngleUnit.Radian: math.radians(1.0), es.AngleUnit.Degree: 1.0,
               es.AngleUnit.Gon: 400.0 / 360.0}[es.AngleUnit(self.units["angUnitType"])]  # per degree
        srot = pose.std_rot_deg * ang
        v = self._from_mm
        return es.DataResult(es.DataType.StationaryProbeMeasResult, Status.AllOK, {
            "measMode": int(es.MeasMode.SixDStationary), "bIsTryMode": 0,
            "triggerStatus": int(es.TriggerStatus.TriggerNotPressed), "lRotationStatus": 0,
            "iInternalProbeId": 1, "iFieldNumber": 0, "tipStatus": int(es.MeasurementTipStatus.TipOK),
            "iInternalTipAdapterId": 1, "iTipAdapterInterface": 0,
            "dPosition1": v(xyz[0]), "dPosition2": v(xyz[1]), "dPosition3": v(xyz[2]),
            "dStdDevPosition1": v(std[0]), "dStdDevPosition2": v(std[1]), "dStdDevPosition3": v(std[2]),
            "dStdDevPositionTotal": v(float(np.linalg.norm(std))),
            "dCovarPosition12": 0.0, "dCovarPosition13": 0.0, "dCovarPosition23": 0.0,
            "dAprioriStdDevPosition1": v(sigma), "dAprioriStdDevPosition2": v(sigma),
            "dAprioriStdDevPosition3": v(sigma), "dAprioriStdDevPositionTotal": v(sigma * math.sqrt(3.0)),
            "dAprioriCovarPosition12": 0.0, "dAprioriCovarPosition13": 0.0, "dAprioriCovarPosition23": 0.0,
            "dQuaternion0": pose.qw, "dQuaternion1": pose.qx, "dQuaternion2": pose.qy, "dQuaternion3": pose.qz,
            "dRotationAngleX": math.degrees(roll) * ang, "dRotationAngleY": math.degrees(pitch) * ang,
            "dRotationAngleZ": math.degrees(yaw) * ang,
            "dStdDevRotationAngleX": float(srot[0]), "dStdDevRotationAngleY": float(srot[1]),
            "dStdDevRotationAngleZ": float(srot[2]), "dStdDevRotationAngleTotal": float(np.linalg.norm(srot)),
            "dCovarRotationAngleXY": 0.0, "dCovarRotationAngleXZ": 0.0, "dCovarRotationAngleYZ": 0.0,
            "dAprioriStdDevRotationAngleX": a_sigma * ang, "dAprioriStdDevRotationAngleY": a_sigma * ang,
            "dAprioriStdDevRotationAngleZ": a_sigma * ang, "dAprioriStdDevRotationAngleTotal": a_sigma * ang * math.sqrt(3.0),
            "dAprioriCovarRotationAngleXY": 0.0, "dAprioriCovarRotationAngleXZ": 0.0,
            "dAprioriCovarRotationAngleYZ": 0.0, **self._air_values()})


class EmsconServer(TcpTrackerServer):
    """Serves a ``FakeEmscon`` on 127.0.0.1 (ephemeral port by default), many clients at once;
    ``url`` is ``emscon://host:port``. Fault hooks: ``drop()``, ``stall(s)``, ``garble(n)``."""

    def __init__(self, device: FakeEmscon, *, host: str = "127.0.0.1", port: int = 0, seed: int = 0) -> None:
        if not isinstance(device, FakeEmscon):
            raise TypeError(f"EmsconServer serves a FakeEmscon, got {type(device).__name__}")
        super().__init__(device, host=host, port=port, seed=seed)

    @property
    def url(self) -> str:
        return f"emscon://{self.host}:{self.port}"

    def close(self) -> None:
        super().close()
        self.device.close()
