"""OptiTrack's own Python client (``natnetsdk``) as the independent peer: it connects to
FakeMotive over real sockets and decodes its frames (3.0 and 4.1, unicast and multicast), and
its unpack functions read every section our encoder writes, consuming exactly the bytes."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
from natnet_helpers import (
    PLATE_MM, PLATE_ORIGIN_MM, VERSIONS, natnetsdk_client, rich_frame, rich_modeldef,
    stop_natnetsdk, wait_until,
)

from drivers.natnet import codec
from drivers.natnet.fake import FakeMotive

natnetsdk = pytest.importorskip("natnetsdk.NatNetClient", reason="natnetsdk (OptiTrack's client) is not installed")

END_OF_DATA = 4  # natnetsdk stops before the int32 end-of-data marker


def f32(values) -> np.ndarray:
    return np.asarray(values, dtype=np.float32)


def assert_same_frame(ours: codec.FrameOfData, theirs) -> None:
    """Every field natnetsdk decoded equals ours (float32-exact)."""
    assert theirs.prefix_data.frame_number == ours.frame_number
    ms = theirs.marker_set_data.marker_data_list
    assert [m.model_name.decode() for m in ms] == [m.name for m in ours.marker_sets]
    for m, o in zip(ms, ours.marker_sets):
        np.testing.assert_array_equal(f32(m.marker_pos_list).reshape(-1, 3), o.positions)
    np.testing.assert_array_equal(f32(theirs.legacy_other_markers.marker_pos_list).reshape(-1, 3), ours.unlabeled)
    rbs = theirs.rigid_body_data.rigid_body_list
    assert [rb.id_num for rb in rbs] == ours.rigid_bodies["id"].tolist()
    for rb, o in zip(rbs, ours.rigid_bodies):
        np.testing.assert_array_equal(f32(rb.pos), o["pos"])
        np.testing.assert_array_equal(f32(rb.rot), o["quat"])
        assert rb.tracking_valid == bool(o["params"] & 1)
        assert np.float32(rb.error) == o["mean_error"]
    sks = theirs.skeleton_data.skeleton_list
    assert [s.id_num for s in sks] == [s.id for s in ours.skeletons]
    for s, o in zip(sks, ours.skeletons):
        assert [b.id_num for b in s.rigid_body_list] == o.rigid_bodies["id"].tolist()
    if ours.assets:
        assets = theirs.asset_data.asset_list
        assert [a.asset_id for a in assets] == [a.id for a in ours.assets]
        for a, o in zip(assets, ours.assets):
            assert [m.marker_id for m in a.marker_list] == o.markers["id"].astype(np.int32).tolist()
            assert [b.id_num for b in a.rigid_body_list] == o.rigid_bodies["id"].tolist()
    lms = theirs.labeled_marker_data.labeled_marker_list
    assert [lm.id_num & 0xFFFFFFFF for lm in lms] == ours.labeled_markers["id"].tolist()
    for lm, o in zip(lms, ours.labeled_markers):
        np.testing.assert_array_equal(f32(lm.pos), o["pos"])
        assert np.float32(lm.size) == o["size"] and lm.param == o["params"]
        assert np.float32(lm.residual / 1000.0) == pytest.approx(o["residual"], rel=1e-6)  # it scales ×1000
    for theirs_list, ours_list in ((theirs.force_plate_data.force_plate_list, ours.force_plates),
                                   (theirs.device_data.device_list, ours.devices)):
        assert [p.id_num for p in theirs_list] == [p.id for p in ours_list]
        for p, o in zip(theirs_list, ours_list):
            got = [f32([v[0] for v in ch.frame_list]) for ch in p.channel_data_list]
            assert len(got) == len(o.channels)
            for g, c in zip(got, o.channels):
                np.testing.assert_array_equal(g, c)
    sfx = theirs.suffix_data
    assert (sfx.timecode, sfx.timecode_sub, sfx.timestamp) == (ours.timecode, ours.timecode_subframe, ours.timestamp)
    assert (sfx.stamp_camera_mid_exposure, sfx.stamp_data_received, sfx.stamp_transmit) == (
        ours.stamp_camera_mid_exposure, ours.stamp_data_received, ours.stamp_transmit)
    assert sfx.param == ours.params


@pytest.mark.parametrize("version", VERSIONS, ids=lambda v: f"{v[0]}.{v[1]}")
def test_natnetsdk_unpacks_every_section_we_encode(version):
    client = natnetsdk.NatNetClient()
    frame = rich_frame(np.random.default_rng(5), version)
    payload = codec.encode_frame(frame, version)
    with contextlib.redirect_stdout(io.StringIO()):
        offset, mocap = client._NatNetClient__unpack_mocap_data(payload, len(payload), version[0], version[1])
    assert offset == len(payload) - END_OF_DATA
    assert_same_frame(frame, mocap)


@pytest.mark.parametrize("version", VERSIONS, ids=lambda v: f"{v[0]}.{v[1]}")
def test_natnetsdk_unpacks_our_model_definitions(version):
    md = codec.ModelDef(tuple(d for d in rich_modeldef(version).datasets
                              if not isinstance(d, codec.UnknownDescription)))
    payload = codec.encode_modeldef(md, version)
    client = natnetsdk.NatNetClient()
    with contextlib.redirect_stdout(io.StringIO()):
        offset, descs = client._NatNetClient__unpack_data_descriptions(payload, len(payload), version[0], version[1])
    assert offset == len(payload)
    assert [d.marker_set_name.decode() for d in descs.marker_set_list] == [d.name for d in md.marker_sets]
    assert [[n.decode() for n in d.marker_names_list] for d in descs.marker_set_list] == [
        list(d.marker_names) for d in md.marker_sets]
    assert [d.name.decode() for d in descs.skeleton_list] == ["skel"]
    fp, dev = descs.force_plate_list[0], descs.device_list[0]
    assert (fp.id_num, fp.serial_number.decode(), [c.decode() for c in fp.channel_list]) == (
        5, "FP-0042", ["Fx", "Fy", "Fz"])
    assert fp.cal_matrix[11][11] == 143.0 and fp.corners[3] == [-9.0, -10.0, -11.0]
    assert (dev.id_num, dev.name.decode(), [c.decode() for c in dev.channel_list]) == (
        6, "NI-DAQ", ["ai0", "ai1"])
    assert [c.name.decode() for c in descs.camera_list] == ["cam 1"]
    assert [(d.sz_name.decode(), d.id_num) for d in descs.rigid_body_list] == [(d.name, d.id) for d in md.rigid_bodies]
    theirs = descs.rigid_body_list[0].rb_marker_list
    assert [tuple(np.float32(m.pos)) for m in theirs] == [tuple(np.float32(m.offset)) for m in md.rigid_bodies[0].markers]
    if version[0] >= 4:
        assert [m.marker_name for m in theirs] == [m.name for m in md.rigid_bodies[0].markers]
    # trained-markerset assets (4.1): natnetsdk reads the same name, type, id, bones, markers
    assert [(a.name.decode(), a.assetType, a.assetID) for a in descs.asset_list] == [
        (a.name, a.asset_type, a.id) for a in md.assets]
    for a, o in zip(descs.asset_list, md.assets):
        assert [b.sz_name.decode() for b in a.rigidbodyArray] == [b.name for b in o.rigid_bodies]
        assert [(m.name.decode(), m.marker_id, tuple(np.float32(m.position)), np.float32(m.marker_size),
                 m.marker_params) for m in a.markerArray] == [
            (m.name, m.id, tuple(np.float32(m.position)), np.float32(m.size), m.params) for m in o.markers]
    assert len(md.assets) == (1 if version[:2] >= (4, 1) else 0)


@pytest.mark.parametrize("multicast", [False, True], ids=["unicast", "multicast"])
@pytest.mark.parametrize("version", [(3, 0), (4, 1)], ids=["3.0", "4.1"])
def test_natnetsdk_client_receives_fake_motive_frames(still_scene, version, multicast):
    fake = FakeMotive(still_scene, natnet_version=version, multicast=multicast, rate_hz=240)
    # frames before its SERVERINFO would be decoded as version 0.0 by natnetsdk: start stalled
    fake.stall()
    fake.start()
    try:
        client, decoded = natnetsdk_client(fake, multicast)
        assert client.run()
        try:
            # connected() turns true a few statements before it stores the version it decodes with
            assert wait_until(lambda: client.connected() and client.get_major() == version[0]), (
                "natnetsdk never processed our SERVERINFO")
            assert client.get_application_name() == "Motive"
            assert client.get_nat_net_version_server()[:2] == list(version)
            fake.resume()
            assert wait_until(lambda: len(decoded) >= 10), f"natnetsdk decoded {len(decoded)} frames"
        finally:
            stop_natnetsdk(client, fake)
    finally:
        fake.close()
    for raw, offset, mocap, (major, minor) in decoded[:10]:
        assert (major, minor) == version, [(m.prefix_data.frame_number, v, len(r)) for r, _, m, v in decoded[:10]]
        assert offset == len(raw) - 4 - END_OF_DATA  # consumed the whole payload
        ours = codec.decode_packet(raw, codec.version_tuple(version))
        assert_same_frame(ours, mocap)
        lms = {lm.id_num: lm.pos for lm in mocap.labeled_marker_data.labeled_marker_list}
        for i, true_mm in enumerate(PLATE_MM + PLATE_ORIGIN_MM):
            np.testing.assert_allclose(np.asarray(lms[(1 << 16) | (i + 1)]) * 1000.0, true_mm, atol=1e-3)
    numbers = [m.prefix_data.frame_number for _, _, m, _ in decoded]
    assert numbers == sorted(numbers)


@pytest.mark.parametrize("asset, version", [("skeleton", (3, 0)), ("skeleton", (4, 1)), ("trained_markerset", (4, 1))],
                         ids=["skeleton-3.0", "skeleton-4.1", "trained-markerset-4.1"])
def test_natnetsdk_reads_the_fakes_skeleton_and_trained_markerset(still_scene, asset, version):
    """The bytes FakeMotive sends for a skeleton / trained markerset decode in natnetsdk to the
    same bone pose and markers, and its model definitions to the same names and ids."""
    from drivers.natnet.fake import BONE_ID, BONE_NAME

    fake = FakeMotive(still_scene, asset=asset, natnet_version=version)
    fake.stall()
    fake.start()
    try:
        frame, md = fake.make_frame(), fake.model_def()
    finally:
        fake.close()
    v = codec.version_tuple(version)
    payload, md_payload = codec.encode_frame(frame, v), codec.encode_modeldef(md, v)
    client = natnetsdk.NatNetClient()
    with contextlib.redirect_stdout(io.StringIO()):
        offset, mocap = client._NatNetClient__unpack_mocap_data(payload, len(payload), *version)
        md_offset, descs = client._NatNetClient__unpack_data_descriptions(md_payload, len(md_payload), *version)
    assert offset == len(payload) - END_OF_DATA and md_offset == len(md_payload)
    assert_same_frame(frame, mocap)
    if asset == "skeleton":
        (sk,) = mocap.skeleton_data.skeleton_list
        bone = sk.rigid_body_list[0]
        (desc,) = descs.skeleton_list
        assert (desc.name.decode(), desc.id_num) == ("tool", 1)
        assert [(b.sz_name.decode(), b.id_num) for b in desc.rigid_body_description_list] == [(BONE_NAME, BONE_ID)]
        lms = {lm.id_num: lm.pos for lm in mocap.labeled_marker_data.labeled_marker_list}
    else:
        (a,) = mocap.asset_data.asset_list
        bone = a.rigid_body_list[0]
        (desc,) = descs.asset_list
        assert (desc.name.decode(), desc.assetID) == ("tool", 1)
        assert [m.name.decode() for m in desc.markerArray] == ["m0", "m1", "m2", "m3"]
        lms = {m.marker_id: m.pos for m in a.marker_list}
    assert bone.id_num == (1 << 16) | BONE_ID
    np.testing.assert_allclose(np.asarray(bone.pos) * 1000.0, (PLATE_MM + PLATE_ORIGIN_MM).mean(axis=0), atol=1e-3)
    for i, true_mm in enumerate(PLATE_MM + PLATE_ORIGIN_MM):
        np.testing.assert_allclose(np.asarray(lms[(1 << 16) | (i + 1)]) * 1000.0, true_mm, atol=1e-3)
