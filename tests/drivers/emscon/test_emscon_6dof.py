"""emScon 6-DoF measurements: ``ProbeStationaryResultT`` (``ES_DT_StationaryProbeMeasResult``) and
``GetMeasurementProbeInfoRT`` as ``ES_C_API_Def.h`` (TPI 3.6) lays them out, the fake serving a
T-Mac-like target in ``ES_MM_6DStationary``, and the client turning the result into a pose.

Packets are built and read here with ``struct`` from the header's field order (pack 4,
little-endian, enums and ES_BOOL 4 bytes), not with our encoder."""

from __future__ import annotations

import math
import socket
import struct

import numpy as np
import pytest

from drivers.emscon import codec as es
from drivers.emscon.client import EmsconSensor
from drivers.emscon.fake import EmsconServer, FakeEmscon
from drivers.errors import LimitError
from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerObservation
from drivers.tracker.fake import FakeTracker

#: ProbeStationaryResultT after its ReturnDataT {PacketHeaderT {long size; ES_DataType type}; status}:
#: measMode, bIsTryMode, triggerStatus, lRotationStatus, iInternalProbeId, iFieldNumber, tipStatus,
#: iInternalTipAdapterId, iTipAdapterInterface (9 × 4 bytes), then 41 doubles: position (3), its
#: std devs (3 + total), covariances (3), a-priori std devs (3 + total) and covariances (3),
#: quaternion (4), rotation angles (3), their std devs (3 + total), covariances (3), a-priori std
#: devs (3 + total) and covariances (3), temperature, pressure, humidity.
PROBE_RESULT = struct.Struct("<iII" + "IiIiiiIii" + "41d")
#: GetMeasurementProbeInfoRT: BasicCommandRT {header; command; status} + 14 four-byte fields.
PROBE_INFO = struct.Struct("<iIII" + "iiiIiiIiIiiiii")
ES_DT_COMMAND, ES_DT_STATIONARY_PROBE = 0, 4
ES_C_SET_MEAS_MODE, ES_C_START_MEAS, ES_C_GET_PROBE_INFO = 24, 49, 119
ES_MM_6D_STATIONARY, ES_PT_MACHINE_CONTROL_PROBE = 6, 4
TRUTH_MM = (2000.0, 300.0, -100.0)


def _rot(axis: int, t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


TRUTH_R = _rot(2, 0.7) @ _rot(1, -0.2) @ _rot(0, 0.4)


class TmacScene:
    """One 6-DoF target ``tmac`` at TRUTH_MM with orientation TRUTH_R (tracker frame)."""

    def observe(self, sensor: str) -> list[MarkerObservation]:
        return [MarkerObservation("tmac", np.array(TRUTH_MM), True, TRUTH_R.copy())]


def _server(six_dof: bool = True) -> EmsconServer:
    tracker = FakeTracker(TmacScene(), clock=SimClock(time_scale=1000.0), reflector="tmac", seed=1,
                          six_dof=six_dof, attitude_noise_deg=0.01)
    return EmsconServer(FakeEmscon(tracker, require_initialize=False), seed=3)


def test_a_probe_result_packed_from_the_header_layout_decodes():
    values = np.arange(41, dtype=float) * 0.5
    values[17:21] = (0.5, 0.5, 0.5, 0.5)  # dQuaternion0..3 (after 17 position doubles)
    data = PROBE_RESULT.pack(PROBE_RESULT.size, ES_DT_STATIONARY_PROBE, 0,
                             ES_MM_6D_STATIONARY, 0, 1, 0, 7, 2, 0, 3, 0, *values)
    assert len(data) == 376
    packet = es.decode(data)
    assert packet.type is es.DataType.StationaryProbeMeasResult and packet.status == 0
    v = packet.values
    assert (v["measMode"], v["triggerStatus"], v["iInternalProbeId"], v["iFieldNumber"], v["iInternalTipAdapterId"]) \
        == (ES_MM_6D_STATIONARY, 1, 7, 2, 3)
    assert (v["dPosition1"], v["dPosition3"], v["dStdDevPositionTotal"]) == (0.0, 1.0, 3.0)
    assert [v[f"dQuaternion{i}"] for i in range(4)] == [0.5] * 4
    assert (v["dRotationAngleX"], v["dStdDevRotationAngleTotal"], v["dHumidity"]) == (10.5, 13.5, 20.0)
    assert es.encode(packet) == data


def test_probe_info_answer_packed_from_the_header_layout_decodes():
    data = PROBE_INFO.pack(PROBE_INFO.size, ES_DT_COMMAND, ES_C_GET_PROBE_INFO, 0,
                           2, 1, 4711, ES_PT_MACHINE_CONTROL_PROBE, 9, 0, 2, 1, 0, 1, 0, 1, 0, 0)
    packet = es.decode(data)
    assert packet.ok and packet.values["probeType"] == es.ProbeType.MachineControlProbe
    assert (packet.values["lSerialNumber"], packet.values["connectionType"]) == (4711, es.ProbeConnectionType.CableSensor)


def _raw_exchange(sock: socket.socket, request: bytes, want_type: int) -> bytes:
    """Send one request and return the first packet of ``want_type`` (skipping notifications)."""
    sock.sendall(request)
    buf = b""
    while True:
        while len(buf) < 8 or len(buf) < struct.unpack_from("<i", buf)[0]:
            chunk = sock.recv(65536)
            assert chunk, "server closed the connection"
            buf += chunk
        size, kind = struct.unpack_from("<iI", buf)
        packet, buf = buf[:size], buf[size:]
        if kind == want_type:
            return packet


def test_the_fake_serves_a_6d_result_a_header_reader_understands():
    with _server() as srv, socket.create_connection((srv.host, srv.port), timeout=10) as sock:
        info = _raw_exchange(sock, struct.pack("<iII", 12, ES_DT_COMMAND, ES_C_GET_PROBE_INFO), ES_DT_COMMAND)
        assert PROBE_INFO.unpack(info)[3 + 4] == ES_PT_MACHINE_CONTROL_PROBE
        ans = _raw_exchange(sock, struct.pack("<iIII", 16, ES_DT_COMMAND, ES_C_SET_MEAS_MODE, ES_MM_6D_STATIONARY),
                            ES_DT_COMMAND)
        assert struct.unpack_from("<II", ans, 8) == (ES_C_SET_MEAS_MODE, 0)
        res = PROBE_RESULT.unpack(_raw_exchange(sock, struct.pack("<iII", 12, ES_DT_COMMAND, ES_C_START_MEAS),
                                                ES_DT_STATIONARY_PROBE))
    d = res[12:]
    np.testing.assert_allclose(d[0:3], TRUTH_MM, atol=0.01)  # dPosition1..3, mm (the fake's default units), 15 µm noise averaged
    w, x, y, z = d[17:21]
    # The header's sample: x axis of the probe in tracker coordinates = (q0²+q1²−q2²−q3², 2(q1q2+q0q3), 2(q1q3−q0q2)).
    x_axis = [w * w + x * x - y * y - z * z, 2 * (x * y + w * z), 2 * (x * z - w * y)]
    z_axis = [2 * (x * z + w * y), 2 * (y * z - w * x), w * w - x * x - y * y + z * z]
    np.testing.assert_allclose(x_axis, TRUTH_R[:, 0], atol=2e-3)  # 0.01° draws, averaged
    np.testing.assert_allclose(z_axis, TRUTH_R[:, 2], atol=2e-3)
    assert 0.0 < d[24] < 0.05  # dStdDevRotationAngleX, degrees


def test_client_pose_measurement_gives_the_probe_orientation():
    with _server() as srv, EmsconSensor(srv.url, marker="tmac", pose=True, reply_timeout=5.0) as sensor:
        assert sensor.probe_info["probeType"] == es.ProbeType.MachineControlProbe
        m = sensor.measure("tmac", 200, 10.0)
        sample = sensor.read(5.0)[0]
    np.testing.assert_allclose(m.mean_mm, TRUTH_MM, atol=0.01)
    angle = math.degrees(math.acos(np.clip((np.trace(m.rotation @ TRUTH_R.T) - 1) / 2, -1, 1)))
    assert angle < 0.005
    assert 0.005 < m.std_deg < 0.02
    assert sample.rotation is not None


def test_pose_without_a_6dof_probe_is_refused_on_connect():
    with _server(six_dof=False) as srv:
        with pytest.raises(LimitError, match="6-DoF probe"):
            EmsconSensor(srv.url, marker="tmac", pose=True, reply_timeout=5.0).connect()
        with EmsconSensor(srv.url, marker="tmac", reply_timeout=5.0) as plain:
            assert plain.measure("tmac", 10, 5.0).rotation is None
