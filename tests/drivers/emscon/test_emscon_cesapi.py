"""The independent peer: CESAPI 1.1.3 (MIT, written against real AT4xx trackers) talks to our
fake emScon server, and our client reads a byte stream that CESAPI's packet classes encode.

CESAPI's ``Connection`` / ``PacketStream`` thread does the socket work and the framing; we poll
its buffer with a short sleep instead of its ``CommandSync`` (which busy-waits a core).
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from drivers.emscon.client import EmsconSensor

pytest.importorskip("CESAPI.connection", reason="CESAPI 1.1.3 (the test extra) is the independent peer")
from CESAPI import packet as P  # noqa: E402
from CESAPI.connection import Connection  # noqa: E402
from cesapi_helpers import execute  # noqa: E402

WAIT_S = 20.0




@pytest.fixture
def cesapi(server):
    conn = Connection()
    stream = conn.connect(host=server.host, port=server.port)
    yield stream
    conn.disconnect()


def test_cesapi_initialises_configures_and_measures_what_the_fake_meant(server, cesapi, scene):
    device = server.device
    assert not device.initialized
    before = P.StartMeasurementCT()
    refused = execute(cesapi, before, result=True)
    assert refused.packetInfo.status == P.ES_RS_TrackerNotInitialized

    assert execute(cesapi, P.InitializeCT()).packetInfo.status == P.ES_RS_AllOK
    assert device.initialized

    units = P.SetUnitsCT()
    units.unitsSettings.lenUnitType = P.ES_LU_Meter
    units.unitsSettings.angUnitType = P.ES_AU_Degree
    units.unitsSettings.tempUnitType = P.ES_TU_Fahrenheit
    units.unitsSettings.pressUnitType = P.ES_PU_HPascal
    units.unitsSettings.humUnitType = P.ES_HU_RH
    assert execute(cesapi, units).packetInfo.status == P.ES_RS_AllOK
    coords = P.SetCoordinateSystemTypeCT()
    coords.coordSysType = P.ES_CS_RHR
    assert execute(cesapi, coords).packetInfo.status == P.ES_RS_AllOK
    mode = P.SetMeasurementModeCT()
    mode.measMode = P.ES_MM_Stationary
    assert execute(cesapi, mode).packetInfo.status == P.ES_RS_AllOK
    stat = P.SetStationaryModeParamsCT()
    stat.stationaryModeData.lMeasTime = 500
    stat.stationaryModeData.bUseADM = 1
    assert execute(cesapi, stat).packetInfo.status == P.ES_RS_AllOK
    env = P.SetEnvironmentParamsCT()
    env.environmentData.dTemperature = 68.0  # °F = 20 °C
    env.environmentData.dPressure = 1013.25
    env.environmentData.dHumidity = 50.0
    assert execute(cesapi, env).packetInfo.status == P.ES_RS_AllOK
    assert device.tracker.assumed_air.temperature_c == pytest.approx(20.0)
    assert (device.meas_time_ms, device.use_adm) == (500, 1)

    got = execute(cesapi, P.StartMeasurementCT(), result=True)
    assert isinstance(got, P.SingleMeasResultT) and got.packetInfo.status == P.ES_RS_AllOK
    xyz_m = np.array([got.dVal1, got.dVal2, got.dVal3])
    std = device.tracker.sigma_mm(float(np.linalg.norm(scene.position_mm)))
    # metres, as CESAPI asked; a 500 ms stationary measurement averages 500 points
    assert np.all(np.abs(xyz_m * 1000.0 - scene.position_mm) < 5 * std / np.sqrt(500) + 1e-6)
    assert np.allclose([got.dStd1, got.dStd2, got.dStd3], std / 1000.0, rtol=0.2)
    assert got.dTemperature == pytest.approx(68.0) and got.dPressure == pytest.approx(1013.25)
    assert np.allclose(device.last_point_mm, xyz_m * 1000.0)


def test_cesapi_reads_the_reflector_list_and_system_status(server, cesapi):
    status = execute(cesapi, P.GetSystemStatusCT())
    assert status.packetInfo.status == P.ES_RS_AllOK
    assert (status.esVersionNumber.iMajorVersionNumber, status.esVersionNumber.iMinorVersionNumber) == (3, 6)
    assert status.lTrackerSerialNumber == server.device.serial
    cesapi.write(P.GetReflectorsCT())
    names = []
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and (not names or len(names) < total):
        if cesapi.unreadCount() == 0:
            time.sleep(0.01)
            continue
        got = cesapi.read()
        if P.packetType(got) == P.ES_DT_Command and got.packetInfo.command == P.ES_C_GetReflectors:
            total = got.iTotalReflectors
            names.append(got.cReflectorName.decode("utf-16-le").split("\0")[0])
    assert names == list(server.device.tracker.reflectors)


class CesapiScriptedServer:
    """A one-connection emScon server whose every answer is built and packed by CESAPI's own
    classes: decode our request with CESAPI's factory, answer with CESAPI's RT packet."""

    def __init__(self, point_mm) -> None:
        self.point_mm = point_mm
        self.seen: list[int] = []
        self.listen = socket.create_server(("127.0.0.1", 0))
        self.port = self.listen.getsockname()[1]
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _answer(self, request) -> list:
        cmd = request.packetInfo.command
        self.seen.append(cmd)
        name = next(k[len("ES_C_"):] for k, v in vars(P).items() if k.startswith("ES_C_") and v == cmd)
        name = name.replace("Parameter", "Param") if "SystemParameter" in name else name
        if cmd == P.ES_C_GetSystemStatus:
            rt = P.GetSystemStatusRT()
            rt.trackerProcessorStatus = P.ES_TPS_Initialized
            rt.laserStatus = P.ES_LPS_LaserReady
            rt.esVersionNumber.iMajorVersionNumber, rt.esVersionNumber.iMinorVersionNumber = 3, 6
            return [rt]
        if cmd == P.ES_C_GetTrackerStatus:
            rt = P.GetTrackerStatusRT()
            rt.trackerStatus = P.ES_TS_Ready
            return [rt]
        if cmd == P.ES_C_GetMeasurementStatusInfo:
            rt = P.GetMeasurementStatusInfoRT()
            rt.lMeasurementStatusInfo = P.ES_MSI_ReflectorFound | P.ES_MSI_Initialized
            return [rt]
        if cmd == P.ES_C_StartMeasurement:
            res = P.SingleMeasResultT()
            res.dVal1, res.dVal2, res.dVal3 = self.point_mm
            res.dStd1, res.dStd2, res.dStd3 = 0.011, 0.012, 0.013
            ssc = P.SystemStatusChangeT()
            ssc.systemStatusChange = P.ES_SSC_MeasStatus_Ready
            return [ssc, res]  # a notification before the result, as a real server may send
        return [getattr(P, name + "RT")()]

    def _serve(self) -> None:
        conn, _ = self.listen.accept()
        factory = P.PacketFactory()
        buf = b""
        with conn:
            while True:
                data = conn.recv(4096)
                if not data:
                    return
                buf += data
                while len(buf) >= 8:
                    size = int.from_bytes(buf[:4], "little")
                    if len(buf) < size:
                        break
                    request, buf = factory.packet(buf[:size], return_type=False), buf[size:]
                    for answer in self._answer(request):
                        conn.sendall(answer.pack())

    def close(self) -> None:
        self.listen.close()


def test_our_client_reads_what_cesapi_encodes():
    point = (1234.5678, -987.6543, 321.0987)
    srv = CesapiScriptedServer(point)
    try:
        with EmsconSensor(f"emscon://127.0.0.1:{srv.port}", reply_timeout=5.0) as sensor:
            m = sensor.measure("smr", 200, 5.0)
            assert tuple(m.mean_mm) == point
            assert tuple(m.std_mm) == (0.011, 0.012, 0.013) and m.count == 200
            assert sensor.beam_ready is True  # the notification before the result was read, not lost
    finally:
        srv.close()
    # CESAPI decoded every request we sent as the command we meant
    assert srv.seen[:3] == [P.ES_C_GetSystemStatus, P.ES_C_GetTrackerStatus, P.ES_C_GetMeasurementStatusInfo]
    assert P.ES_C_SetUnits in srv.seen and P.ES_C_SetCoordinateSystemType in srv.seen
    assert srv.seen[-2:] == [P.ES_C_SetStationaryModeParams, P.ES_C_StartMeasurement]
