"""The line protocol's ``POSE``: a 6-DoF target's position and orientation (PROTOCOL.md) on the
wire, from the fake tracker through the client to a measurement with ``R_tracker←target``."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from drivers.errors import DeviceFaultError
from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerObservation
from drivers.tracker.client import TrackerSensor
from drivers.tracker.codec import LineCodec, MeasurePose, PoseReply
from drivers.tracker.fake import FakeTracker, TcpTrackerServer

#: Where the target is, tracker frame, mm (about 2.03 m from the head).
REFLECTOR_MM = (2000.0, 300.0, -100.0)


def _rz(t: float) -> np.ndarray:
    return np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])


def _rx(t: float) -> np.ndarray:
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])


class SixDofScene:
    """One T-Mac-like target ``tmac``: a position and an orientation, both fixed by the test."""

    def __init__(self, rotation: np.ndarray) -> None:
        self.position_mm = np.asarray(REFLECTOR_MM, dtype=float)
        self.rotation = rotation

    def observe(self, sensor: str) -> list[MarkerObservation]:
        return [MarkerObservation("tmac", self.position_mm.copy(), True, self.rotation.copy())]


def _line(body: str) -> bytes:
    """A device line with its checksum computed here: XOR of every byte of the body."""
    cs = functools.reduce(lambda a, b: a ^ b, body.encode("ascii"), 0)
    return f"{body}*{cs:02X}\n".encode("ascii")


def test_a_pose_reply_written_by_hand_decodes():
    # 90° about the tracker's z: (w, x, y, z) = (cos 45°, 0, 0, sin 45°), written out by hand.
    body = ("12 OK POSE x=2000.0002 y=300.0001 z=-99.9999 sx=0.0100 sy=0.0110 sz=0.0120 "
            "qw=0.707106781 qx=0.000000000 qy=0.000000000 qz=0.707106781 "
            "srx=0.010000 sry=0.020000 srz=0.030000 n=100 t=13.102000")
    rid, reply = LineCodec(require_checksum=True).decode_reply(_line(body))
    assert rid == 12 and isinstance(reply, PoseReply)
    np.testing.assert_allclose(reply.xyz_mm, [2000.0002, 300.0001, -99.9999])
    np.testing.assert_allclose(reply.quat_wxyz, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-9)
    np.testing.assert_allclose(reply.std_rot_deg, [0.01, 0.02, 0.03])
    assert reply.n == 100
    assert LineCodec().encode_request(5, MeasurePose(250)).startswith(b"5 POSE n=250*")


def test_pose_measurement_carries_the_targets_orientation():
    truth = _rz(0.4) @ _rx(-0.3)
    device = FakeTracker(SixDofScene(truth), clock=SimClock(time_scale=1000.0), reflector="tmac", seed=2,
                         six_dof=True, attitude_noise_deg=0.01)
    with TcpTrackerServer(device, seed=3) as srv:
        with TrackerSensor.from_url(srv.url, marker="tmac", pose=True, reply_timeout=5.0) as sensor:
            m = sensor.measure("tmac", 200, 10.0)
    np.testing.assert_allclose(m.mean_mm, REFLECTOR_MM, atol=0.01)
    # the target's x axis as the tracker sees it: the mean of 200 draws of 0.01° is within 0.005°
    err_deg = math.degrees(np.arccos(np.clip((np.trace(m.rotation @ truth.T) - 1) / 2, -1, 1)))
    assert err_deg < 0.005
    assert 0.005 < m.std_deg < 0.02  # per-axis spread of 0.01° draws
    assert m.count == 200


def test_pose_of_a_plain_reflector_is_refused_with_not_6dof():
    device = FakeTracker(SixDofScene(np.eye(3)), clock=SimClock(time_scale=1000.0), reflector="tmac", seed=2)
    with TcpTrackerServer(device, seed=3) as srv:
        with TrackerSensor.from_url(srv.url, marker="tmac", pose=True, reply_timeout=5.0) as sensor:
            with pytest.raises(DeviceFaultError, match="not a 6-DoF target"):
                sensor.measure("tmac", 10, 5.0)
            sensor.pose = False
            assert sensor.measure("tmac", 10, 5.0).rotation is None
