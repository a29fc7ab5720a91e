"""A rigid body's quaternion (NatNet x, y, z, w) reaches the sample, the averaged measurement,
the run record and the dataset as R_sensor←body, for the 3.x and 4.x frame layouts."""

from __future__ import annotations

import itertools
import math
import struct

import numpy as np
import pytest
from natnet_helpers import PlateScene

from drivers.base import mean_rotation
from drivers.natnet.client import NatNetSensor, body_rotation
from drivers.natnet.fake import FakeMotive


def test_scalar_last_quaternion_is_read_as_motive_sends_it():
    # 90° about Motive's y (up) axis, written by hand: (x, y, z, w) = (0, sin 45°, 0, cos 45°).
    s = math.sqrt(0.5)
    raw = struct.unpack("<4f", struct.pack("<4f", 0.0, s, 0.0, s))  # float32 on the wire
    r = body_rotation(raw)
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 0, -1], atol=1e-6)  # the body's x → Motive's −z
    assert body_rotation((0.0, 0.0, 0.0, 0.0)) is None


def test_mean_rotation_and_spread():
    a = np.radians(0.1)
    rz = lambda t: np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]])
    mean, sd = mean_rotation([rz(a), rz(-a)])
    np.testing.assert_allclose(mean, np.eye(3), atol=1e-12)
    assert sd == pytest.approx(math.degrees(math.sqrt(2 * a * a / 3)))
    assert mean_rotation([rz(a), None]) == (None, None)


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1)])
def test_rigid_body_orientation_reaches_the_measurement(version):
    """Motive defines the body at creation (the fake: when it starts); the plate has then turned
    by 0.5 rad about Motive's z, so the body's orientation is Rz(0.5) and its x axis is seen
    along (cos 0.5, sin 0.5, 0)."""
    # The clock reads 0 for the scene's t0 and for the body's definition in ``start``, then 0.5
    # for every frame: no frame can be built before the plate has turned (the fake streams from
    # its own thread as soon as it starts, however loaded the machine).
    ticks = itertools.chain([0.0, 0.0], itertools.repeat(0.5))
    scene = PlateScene(omega_rad_s=1.0, clock=lambda: next(ticks))
    with FakeMotive(scene, natnet_version=version, rate_hz=240) as fake:
        url = f"natnet://127.0.0.1:{fake.command_port}?local=127.0.0.1"
        with NatNetSensor.from_url(url, markers={"plate": "rb:tool", "corner": "ms:tool:m1"}) as sensor:
            samples = {s.marker: s for s in sensor.read(2.0)}
            assert samples["corner"].rotation is None  # a single marker has no orientation
            expected_x = [math.cos(0.5), math.sin(0.5), 0.0]
            np.testing.assert_allclose(samples["plate"].rotation @ [1, 0, 0], expected_x, atol=1e-5)
            np.testing.assert_allclose(samples["plate"].rotation @ [0, 0, 1], [0, 0, 1], atol=1e-5)
            m = sensor.measure("plate", 6, 3.0)
            np.testing.assert_allclose(m.rotation @ [1, 0, 0], expected_x, atol=1e-5)
            assert m.std_deg is not None and m.std_deg < 1e-3


def _frame_bytes(version: tuple[int, int], quat_xyzw, pos_m) -> bytes:
    """A FRAMEOFDATA with one tracked rigid body, written here from the wire facts (PROTOCOLS.md),
    not by our encoder: sections in order, NatNet 4.1's byte count after each section's count,
    4.x's two precision-time words."""
    sized = version >= (4, 1)

    def section(count: int, body: bytes) -> bytes:
        return struct.pack("<i", count) + (struct.pack("<i", len(body)) if sized else b"") + body

    body = struct.pack("<i3f4ffh", 3, *pos_m, *quat_xyzw, 0.0002, 1)  # id, pos, quat x y z w, mean error, tracked
    payload = struct.pack("<i", 1234)  # frame number
    payload += section(0, b"") + section(0, b"") + section(1, body) + section(0, b"")  # marker sets, legacy, bodies, skeletons
    if version >= (4, 1):
        payload += section(0, b"")  # assets
    payload += section(0, b"") + section(0, b"") + section(0, b"")  # labeled markers, force plates, devices
    payload += struct.pack("<IId3Q", 0, 0, 10.5, 1, 2, 3)  # timecode, subframe, timestamp, three tick stamps
    if version >= (4, 0):
        payload += struct.pack("<II", 0, 0)  # precision timestamp
    payload += struct.pack("<hi", 0, 0)  # params, end of data
    return struct.pack("<HH", 7, len(payload)) + payload


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1)])
def test_a_hand_built_frame_gives_the_bodys_orientation_in_motives_frame(version):
    """Motive's quaternion (x, y, z, w) = 90° about its y (up) axis; the body's x axis is then
    Motive's −z, its z axis Motive's +x, whatever the frame layout."""
    from drivers.natnet import codec

    s = math.sqrt(0.5)
    frame = codec.decode_packet(_frame_bytes(version, (0.0, s, 0.0, s), (0.1, 1.2, -0.3)), version)
    (row,) = frame.rigid_bodies
    assert row["id"] == 3
    np.testing.assert_allclose(row["pos"], (0.1, 1.2, -0.3), rtol=1e-6)
    r = body_rotation(row["quat"])
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-6)
