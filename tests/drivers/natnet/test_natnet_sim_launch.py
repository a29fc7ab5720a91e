"""OptiTrack's own Python client (``natnetsdk``) against the simulated cell's fake Motive, at
every NatNet version ``acquire sim`` serves (3.0–4.1) and with the tool as a rigid body, a
skeleton or a trained markerset: it learns the version from SERVERINFO, decodes every frame
to the end of its payload, agrees with our decoder field by field, and sees the marker where
the cell's truth puts it."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
from natnet_helpers import natnetsdk_client, stop_natnetsdk, wait_until
from test_natnet_natnetsdk import END_OF_DATA, assert_same_frame

from drivers.natnet import codec
from drivers.sim.cell import SimCell
from drivers.sim.config import DEFAULT_CONFIG_PATH
from drivers.sim.launch import SimLaunch

natnetsdk = pytest.importorskip("natnetsdk.NatNetClient", reason="natnetsdk (OptiTrack's client) is not installed")


@pytest.mark.parametrize("version, asset", [
    ("3.0", "rigid_body"), ("3.1", "skeleton"), ("4.0", "rigid_body"), ("4.0", "skeleton"),
    ("4.1", "rigid_body"), ("4.1", "trained_markerset"),
])
def test_natnetsdk_reads_the_simulated_cells_motive(version, asset):
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=2)
    with SimLaunch(cell, controller=False, natnet_version=version, mocap_asset=asset) as launch:
        assert f"NatNet {version}" in launch.addresses["mocap"].note
        motive = launch.motives["mocap"]
        motive.stall()  # natnetsdk decodes frames that come before SERVERINFO as version 0.0
        client, decoded = natnetsdk_client(motive, multicast=False)
        assert client.run()
        try:
            major, minor = (int(x) for x in version.split("."))
            assert wait_until(lambda: client.connected() and client.get_major() == major, timeout=10.0)
            assert client.get_nat_net_version_server()[:2] == [major, minor]
            motive.resume()
            assert wait_until(lambda: len(decoded) >= 5, timeout=10.0), f"natnetsdk decoded {len(decoded)} frames"
            with contextlib.redirect_stdout(io.StringIO()):  # its model-definition unpacker prints
                md_raw = codec.encode_packet(motive.model_def(), codec.version_tuple(version))[4:]
                md_offset, descs = client._NatNetClient__unpack_data_descriptions(md_raw, len(md_raw), major, minor)
        finally:
            stop_natnetsdk(client, motive)
    assert md_offset == len(md_raw)
    owners = {"rigid_body": [d.sz_name.decode() for d in descs.rigid_body_list],
              "skeleton": [d.name.decode() for d in descs.skeleton_list],
              "trained_markerset": [d.name.decode() for d in descs.asset_list]}[asset]
    assert owners == ["tool"]
    q = cell.joint_positions()
    truth_mm = cell.true_marker_positions(q, frame="mocap")[cell.marker_names.index("sir")]
    for raw, offset, mocap, got_version in decoded[:5]:
        assert got_version == (major, minor)
        assert offset == len(raw) - 4 - END_OF_DATA  # consumed the whole payload
        assert_same_frame(codec.decode_packet(raw, codec.version_tuple(version)), mocap)
        if asset == "trained_markerset":
            positions = [m.pos for a in mocap.asset_data.asset_list for m in a.marker_list]
        else:
            positions = [lm.pos for lm in mocap.labeled_marker_data.labeled_marker_list]
        assert len(positions) == 4  # the bar sees the infrared marker and its rigid-body cluster (the SIR first)
        np.testing.assert_allclose(np.asarray(positions[0]) * 1000.0, truth_mm, atol=0.3)  # noise 0.03 mm


def test_natnetsdk_joins_the_multicast_stream_a_cell_file_asks_for(tmp_path):
    """``natnet: {version: 4.0, multicast: true}`` in the cell file: Motive's default transmission
    (group 239.255.42.99, announced in SERVERINFO), received by natnetsdk in multicast mode."""
    from natnet_helpers import need_loopback_multicast

    from drivers.sim.config import SimConfig, load_sim_config

    need_loopback_multicast()
    data = load_sim_config(DEFAULT_CONFIG_PATH).model_dump()
    data["sensors"][0]["natnet"] = {"version": "4.0", "multicast": True}
    cell = SimCell(SimConfig.model_validate(data))
    with SimLaunch(cell, controller=False) as launch:
        assert "multicast 239.255.42.99" in launch.addresses["mocap"].note
        motive = launch.motives["mocap"]
        motive.stall()
        client, decoded = natnetsdk_client(motive, multicast=True)
        assert client.run()
        try:
            assert wait_until(lambda: client.connected() and client.get_major() == 4, timeout=10.0)
            motive.resume()
            assert wait_until(lambda: len(decoded) >= 5, timeout=10.0), f"natnetsdk decoded {len(decoded)} frames"
        finally:
            stop_natnetsdk(client, motive)
    for raw, offset, mocap, got_version in decoded[:5]:
        assert got_version == (4, 0) and offset == len(raw) - 4 - END_OF_DATA
        assert_same_frame(codec.decode_packet(raw, codec.version_tuple("4.0")), mocap)
