"""Selecting more than rigid bodies: skeleton bones (``sk:``) and an asset's markers by name
(``ms:``) from a fake Motive whose plate is a rigid body, a skeleton or a NatNet 4.1 trained
markerset, and from the real Motive 2.1 model definitions."""

from __future__ import annotations

import numpy as np
import pytest
from natnet_helpers import PLATE_MM, PLATE_ORIGIN_MM, capture

from drivers.natnet import codec
from drivers.natnet.client import MarkerSelector, NatNetSensor
from drivers.natnet.samples import find_bone
from drivers.natnet.selection import resolve_by_name
from drivers.natnet.fake import BONE_ID, FakeMotive

TRUE_MM = PLATE_MM + PLATE_ORIGIN_MM


def sensor_for(fake, markers) -> NatNetSensor:
    return NatNetSensor.from_url(f"natnet://127.0.0.1:{fake.command_port}", markers=markers)


def by_name(samples):
    return {s.marker: s for s in samples}


ASSETS = [
    pytest.param("skeleton", (3, 0), id="skeleton-3.0"),
    pytest.param("skeleton", (4, 1), id="skeleton-4.1"),
    pytest.param("trained_markerset", (4, 1), id="trained-markerset-4.1"),
]


@pytest.mark.parametrize("asset, version", ASSETS)
def test_bones_and_asset_markers_by_name_and_by_id(still_scene, asset, version):
    markers = {
        "bone": "sk:tool:plate", "bone_by_id": f"sk:1:{BONE_ID}",
        "corner": "ms:tool:m1", "far": "ms:tool:m3", "far_by_id": "lm:1:4",
    }
    with FakeMotive(still_scene, asset=asset, natnet_version=version, rate_hz=240) as fake:
        with sensor_for(fake, markers) as sensor:
            frame_has_assets = asset == "trained_markerset"
            for _ in range(3):
                s = by_name(sensor.read(1.0))
                assert all(x.visible for x in s.values()), {k: v.visible for k, v in s.items()}
                np.testing.assert_allclose(s["bone"].position_mm, TRUE_MM.mean(axis=0), atol=1e-3)
                np.testing.assert_array_equal(s["bone"].position_mm, s["bone_by_id"].position_mm)
                np.testing.assert_allclose(s["corner"].position_mm, TRUE_MM[1], atol=1e-3)
                np.testing.assert_allclose(s["far"].position_mm, TRUE_MM[3], atol=1e-3)
                np.testing.assert_array_equal(s["far"].position_mm, s["far_by_id"].position_mm)
            frame = fake.make_frame()
            assert len(frame.rigid_bodies) == 0  # no rigid body: only the asset carries the pose
            assert bool(frame.assets) == frame_has_assets and bool(frame.skeletons) != frame_has_assets


def test_a_bone_is_invisible_when_its_skeleton_is_lost(still_scene):
    with FakeMotive(still_scene, asset="skeleton", rate_hz=240) as fake:
        with sensor_for(fake, {"bone": "sk:tool:plate", "corner": "ms:tool:m1"}) as sensor:
            assert by_name(sensor.read(1.0))["bone"].visible
            still_scene.hidden = {"m2", "m3"}
            for _ in range(200):
                s = by_name(sensor.read(1.0))
                if not s["bone"].visible:
                    break
            assert not s["bone"].visible and s["corner"].visible


@pytest.mark.parametrize("asset, version, selector, match", [
    ("skeleton", (3, 0), "sk:tool:elbow", r"'tool' has no bone 'elbow'; its bones are \['plate'\]"),
    ("skeleton", (3, 0), "sk:arm:plate", r"no skeleton or asset 'arm'; Motive defines skeletons \['tool'\]"),
    ("skeleton", (3, 0), "sk:9:plate", "no skeleton or asset 9"),
    ("trained_markerset", (4, 1), "ms:tool:m9", r"asset 'tool' has no marker 'm9'; its markers are \['m0'"),
    ("rigid_body", (3, 0), "sk:tool:plate", r"no skeleton or asset 'tool'.*skeletons \[\] and assets \[\]"),
])
def test_names_motive_does_not_define_are_refused_at_connect(still_scene, asset, version, selector, match):
    with FakeMotive(still_scene, asset=asset, natnet_version=version) as fake:
        with pytest.raises(ValueError, match=match):
            sensor_for(fake, {"x": selector}).connect()


@pytest.mark.parametrize("text, expected", [
    ("sk:robot:link6", MarkerSelector("sk", body="robot", name="link6")),
    ("sk:3:7", MarkerSelector("sk", body=3, name=7)),
    ("sk:robot:7", MarkerSelector("sk", body="robot", name=7)),
    ("ms:Arm Asset:Marker 2", MarkerSelector("ms", body="Arm Asset", name="Marker 2")),
])
def test_bone_and_asset_selectors_parse(text, expected):
    assert MarkerSelector.parse(text) == expected


@pytest.mark.parametrize("text", ["sk:", "sk:robot", "sk::7", "sk:robot:", "sk:70000:1", "sk:1:65536", "ms:tool"])
def test_bad_bone_selectors_are_refused_with_the_syntax(text):
    with pytest.raises(ValueError, match=r"is not one of .*'sk:<skeleton id or name>:<bone id or name>'"):
        MarkerSelector.parse(text)


# ----------------------------------------------------------------------------- real Motive 2.1 definitions


def test_real_modeldef_resolves_a_rigid_bodys_markers_by_name():
    """RaceQuad (rigid body 2) with marker set RaceQuad: Marker1..5; the real frame labels
    them 2:1 … 2:5 (mocapframe_packet_v3.expected.txt)."""
    md = codec.decode_packet(capture("modeldef_packet_v3.bin"), (3, 0, 0, 0))
    frame = codec.decode_packet(capture("mocapframe_packet_v3.bin"), (3, 0, 0, 0))
    for i in range(5):
        kind, ident = resolve_by_name(md, MarkerSelector.parse(f"ms:RaceQuad:Marker{i + 1}"), "t")
        assert (kind, ident) == ("lm", (2 << 16) | (i + 1))
        assert ident in frame.labeled_markers["id"].tolist()
    assert resolve_by_name(md, MarkerSelector.parse("rb:RaceQuad"), "t") == ("rb", 2)
    with pytest.raises(ValueError, match=r"no skeleton or asset 'RaceQuad'; Motive defines skeletons \[\]"):
        resolve_by_name(md, MarkerSelector.parse("sk:RaceQuad:1"), "t")
    with pytest.raises(ValueError, match="marker set 'all' belongs to no rigid body, skeleton or asset"):
        resolve_by_name(md, MarkerSelector("ms", body="all", name="RaceQuad_1"), "t")


def test_frame_bone_ids_are_matched_on_their_member_id():
    rb = np.zeros(2, codec.RIGID_BODY_DTYPE)
    rb["id"] = [(4 << 16) | 1, (4 << 16) | 2]  # frame data: skeleton id << 16 | bone id
    rb["pos"] = [[1, 2, 3], [4, 5, 6]]
    frame = codec.FrameOfData(1, skeletons=(codec.SkeletonData(4, rb),))
    assert find_bone(frame, 4, 2)["pos"].tolist() == [4, 5, 6]
    assert find_bone(frame, 4, 3) is None and find_bone(frame, 5, 1) is None
