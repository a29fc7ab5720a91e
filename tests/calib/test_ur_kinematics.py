"""UR's kinematics parameters file: written from a (calibrated) UR10 and read back as
ur_description builds its chain — the joint origins of ``urdf/ur_macro.xacro`` with the file's
x, y, z, roll, pitch, yaw, evaluated by an independent URDF library (yourdfpy)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from calib.robot.calibrated import apply_result
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, robot_model_from_dict
from calib.robot.ur_kinematics import UR_JOINTS, UR_LINKS, UrKinematicsError, read_ur_kinematics, ur_kinematics, write_ur_kinematics
from calib.robot.urdf import fk_difference, random_configurations
from tests.calib.calibrated_sim import full_result

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
UR10 = load_robot_model(ROBOTS / "ur10.yaml")


def ur_description_urdf(kinematics: dict) -> str:
    """The kinematic skeleton ur_description's ur_macro.xacro makes of a kinematics file: base_link,
    base_link_inertia (rpy 0 0 π), the six revolute joints about z with the file's origins,
    flange (rpy 0 −π/2 −π/2), tool0 (rpy π/2 π π/2) and the controller's ``base`` (rpy 0 0 π)."""
    k = kinematics["kinematics"]
    links = ["base_link", "base_link_inertia", "shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link",
             "wrist_2_link", "wrist_3_link", "flange", "tool0", "base"]
    pi = math.pi
    joints = [f'<joint name="base_link-base_link_inertia" type="fixed"><parent link="base_link"/><child link="base_link_inertia"/>'
              f'<origin xyz="0 0 0" rpy="0 0 {pi!r}"/></joint>']
    for i, (entry, joint) in enumerate(zip(UR_LINKS, UR_JOINTS)):
        e = k[entry]
        joints.append(f'<joint name="{joint}" type="revolute"><parent link="{links[i + 1]}"/><child link="{links[i + 2]}"/>'
                      f'<origin xyz="{e["x"]!r} {e["y"]!r} {e["z"]!r}" rpy="{e["roll"]!r} {e["pitch"]!r} {e["yaw"]!r}"/>'
                      '<axis xyz="0 0 1"/><limit lower="-6.283" upper="6.283" effort="1" velocity="1"/></joint>')
    joints.append(f'<joint name="wrist_3-flange" type="fixed"><parent link="wrist_3_link"/><child link="flange"/>'
                  f'<origin xyz="0 0 0" rpy="0 {-pi / 2!r} {-pi / 2!r}"/></joint>')
    joints.append(f'<joint name="flange-tool0" type="fixed"><parent link="flange"/><child link="tool0"/>'
                  f'<origin xyz="0 0 0" rpy="{pi / 2!r} {pi!r} {pi / 2!r}"/></joint>')
    joints.append(f'<joint name="base_link-base_fixed_joint" type="fixed"><parent link="base_link"/><child link="base"/>'
                  f'<origin xyz="0 0 0" rpy="0 0 {pi!r}"/></joint>')
    return ('<?xml version="1.0"?><robot name="ur">' + "".join(f'<link name="{n}"/>' for n in links) + "".join(joints)
            + "</robot>")


def ur_description(kinematics_file: Path, tmp_path: Path):
    """yourdfpy's robot of ``ur_description_urdf`` for a kinematics file."""
    import yourdfpy

    path = tmp_path / "ur_description.urdf"
    path.write_text(ur_description_urdf(yaml.safe_load(kinematics_file.read_text())))
    return yourdfpy.URDF.load(str(path), load_meshes=False)


def yourdfpy_fk(robot, q: np.ndarray, tip: str = "wrist_3_link") -> np.ndarray:
    """``tip`` in the controller's ``base`` frame (4, 4) mm for q (k, 6) rad."""
    out = np.empty((len(q), 4, 4))
    for i, row in enumerate(q):
        robot.update_cfg(dict(zip(UR_JOINTS, row)))
        out[i] = robot.get_transform(tip, "base")
    out[:, :3, 3] *= 1000.0
    return out


def test_the_nominal_ur10_file_has_urs_layout_and_values(tmp_path):
    path = tmp_path / "ur10.yaml"
    kin = write_ur_kinematics(UR10, path)
    doc = yaml.safe_load(path.read_text())
    assert list(doc["kinematics"]) == [*UR_LINKS, "hash"]
    k = doc["kinematics"]
    # UR's published UR10 DH as ur_calibration lays it out: d1 in the shoulder, a2, a3 and d4 in
    # forearm / wrist_1, d5 along −y of wrist_2, d6 along y of wrist_3.
    assert k["shoulder"]["z"] == pytest.approx(0.1273) and k["upper_arm"]["roll"] == pytest.approx(math.pi / 2)
    assert k["forearm"]["x"] == pytest.approx(-0.612) and k["wrist_1"]["x"] == pytest.approx(-0.5723)
    assert k["wrist_1"]["z"] == pytest.approx(0.163941)
    assert k["wrist_2"]["y"] == pytest.approx(-0.1157) and k["wrist_3"]["y"] == pytest.approx(0.0922)
    np.testing.assert_allclose(kin.residual, np.eye(4), atol=1e-12)


def test_a_calibrated_ur10_read_back_as_ur_description_builds_it_reproduces_the_model(tmp_path):
    masses = UR10  # the UR10 model carries link masses: its result has compliances too
    mdh = robot_model_from_dict({**masses.model_dump(mode="json"), "convention": "mdh"})
    cal = apply_result(mdh, full_result(mdh, seed=11))
    assert any(j.beta != 0 for j in cal.model.joints) and any(j.theta != 0 for j in cal.model.joints)
    path = tmp_path / "ur10_calibration.yaml"
    kin = write_ur_kinematics(cal.model, path, header="test")
    q = random_configurations(cal.model, 300, seed=2)
    ours = Chain(cal.model).fk(q)
    pos, rot = fk_difference(ours, read_ur_kinematics(path).wrist3(q) @ kin.residual)
    assert pos < 1e-6 and rot < 1e-6
    # ur_description's chain, built by yourdfpy from the file as its xacro builds it (fewer
    # configurations: yourdfpy walks its scene graph per configuration)
    robot = ur_description(path, tmp_path)
    pos, rot = fk_difference(ours[:40], yourdfpy_fk(robot, q[:40]) @ kin.residual)
    assert pos < 1e-6 and rot < 1e-6
    # tool0 = wrist_3_link · Rz(180°), as ur_description's fixed flange and tool0 joints make it
    np.testing.assert_allclose(yourdfpy_fk(robot, q[:5], tip="tool0"), read_ur_kinematics(path).tool0(q[:5]), atol=1e-9)
    # and the residual (the sixth link's a, α, β) is what the file cannot hold
    assert not np.allclose(kin.residual, np.eye(4))


def test_models_ur_description_cannot_hold_are_refused():
    with pytest.raises(UrKinematicsError, match="six joints, the model has 7"):
        ur_kinematics(load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml"))
    with pytest.raises(UrKinematicsError, match="sign -1"):
        ur_kinematics(load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml"))


def test_a_file_that_is_not_a_kinematics_file_is_refused_naming_the_entry(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("kinematics:\n  shoulder: {x: 0, y: 0, z: 0.1, roll: 0, pitch: 0}\n")
    with pytest.raises(UrKinematicsError, match="kinematics.shoulder must have numbers x, y, z, roll, pitch, yaw"):
        read_ur_kinematics(bad)
