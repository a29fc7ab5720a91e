"""URDF in and out (``calib.robot.urdf``, ``calib.robot.dh_convert``), checked against yourdfpy's own FK.

Fixture URDFs (tests/calib/urdf/, sources and licences in their headers): the KUKA KR 6 R900-2
from ROS-Industrial's kuka_experimental and the LBR iiwa 14 R820 from iiwa_stack — the same
published files the PoE references of test_fk_reference.py copy their joint data from.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model, model_yaml, robot_model_from_dict
from calib.robot.urdf import (UrdfError, export_urdf, fk_difference, import_urdf, load_urdf, random_configurations,
                        urdf_fk)

HERE = Path(__file__).resolve().parent
URDFS = HERE / "urdf"
KR6_URDF = URDFS / "kuka_kr6r900_2.urdf"
IIWA_URDF = URDFS / "kuka_iiwa14.urdf"
UR5E_URDF = URDFS / "ur5e.urdf"
ROBOTS = HERE.parents[1] / "fixtures" / "robots"
SHIPPED = sorted(p.name for p in ROBOTS.glob("*.yaml"))


def _against_urdf(path: Path, imp, n: int = 60, seed: int = 1) -> tuple[float, float]:
    q = random_configurations(imp.model, n, seed=seed)
    return fk_difference(Chain(imp.model).fk(q), urdf_fk(load_urdf(path), imp.joints, imp.base, imp.tip, q))


# --- import: FK equality with the URDF itself ------------------------------------------------------
@pytest.mark.parametrize("path, tip, convention", [
    (KR6_URDF, None, "auto"), (KR6_URDF, None, "dh"), (KR6_URDF, None, "mdh"),
    (IIWA_URDF, "iiwa_link_ee_kuka", "auto"), (IIWA_URDF, "iiwa_link_ee", "auto"), (IIWA_URDF, "iiwa_link_5", "mdh"),
    (UR5E_URDF, "tool0", "auto"), (UR5E_URDF, "ee_link", "dh"),
])
def test_imported_model_has_the_urdfs_forward_kinematics(path, tip, convention):
    imp = import_urdf(path, tip=tip, convention=convention)
    pos, rot = _against_urdf(path, imp)
    assert pos < 1e-9 and rot < 1e-9, (pos, rot)
    # The check can fail: the same model driven with one sign flipped is far from the URDF.
    q = random_configurations(imp.model, 5, seed=2)
    flipped = q * np.r_[-1.0, np.ones(imp.model.n_joints - 1)]
    far = fk_difference(Chain(imp.model).fk(flipped), urdf_fk(load_urdf(path), imp.joints, imp.base, imp.tip, q))
    assert far[0] > 1.0


def test_kr6_urdf_gives_the_shipped_dh_table_signs_limits_and_speeds():
    """The shipped KR 6 table was written from the OPW parameters, not from this URDF."""
    shipped = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    imp = import_urdf(KR6_URDF, convention="dh", axes=shipped.axis_names)
    assert imp.tip == "tool0" and imp.base == "base_link"  # the fixed 'base' branch is not the flange
    assert imp.model.convention == "dh"
    for ours, ref in zip(imp.model.joints, shipped.joints):
        for f in ("theta", "d", "a", "alpha", "beta", "sign", "max_speed"):
            assert getattr(ours, f) == pytest.approx(getattr(ref, f), abs=1e-9), (ref.axis, f)
        assert ours.limits == pytest.approx(ref.limits, abs=1e-9)
    assert imp.model.base.matrix() == pytest.approx(np.eye(4)) and imp.model.flange.matrix() == pytest.approx(np.eye(4), abs=1e-12)
    assert [j.sign for j in imp.model.joints] == [-1, 1, 1, -1, 1, -1]  # axes 0 0 -1 and -1 0 0 in the URDF


def test_auto_convention_takes_hayati_for_the_parallel_shoulder_and_elbow():
    imp = import_urdf(KR6_URDF)
    assert imp.model.convention == "mdh"
    assert any("axes 2 and 3 are parallel" in n for n in imp.notes)
    assert import_urdf(IIWA_URDF, tip="iiwa_link_ee_kuka").model.convention == "dh"
    ur = import_urdf(UR5E_URDF, tip="tool0")  # shoulder, elbow and wrist 1 parallel (to 1e-12 rad)
    assert ur.model.convention == "mdh" and "axes 2 and 3 are parallel; axes 3 and 4 are parallel" in ur.notes[0]
    assert ur.base == "world" and [j.limits for j in ur.model.joints][2] == (-180.0, 180.0)


def test_iiwa_import_equals_the_shipped_model_with_its_masses_and_centres_of_mass():
    """The shipped iiwa 14 model's link masses were moved from this URDF's <inertial> by hand."""
    shipped = load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml")
    imp = import_urdf(IIWA_URDF, tip="iiwa_link_ee_kuka")
    q = random_configurations(shipped, 40, seed=3)
    pos, rot = fk_difference(Chain(imp.model).fk(q), Chain(shipped).fk(q))
    assert pos < 1e-9 and rot < 1e-9
    assert imp.model.has_dynamics
    for ours, ref in zip(imp.model.joints, shipped.joints):
        assert ours.mass_kg == pytest.approx(ref.mass_kg)
        assert ours.com_mm == pytest.approx(ref.com_mm, abs=1e-9), ref.axis
    np.testing.assert_allclose([j.limits for j in imp.model.joints], [j.limits for j in shipped.joints], rtol=1e-6)
    assert all(j.max_speed == pytest.approx(math.degrees(10.0)) for j in imp.model.joints)  # the xacro's max_velocity


def test_written_yaml_reads_back_to_the_same_kinematics(tmp_path):
    imp = import_urdf(IIWA_URDF, tip="iiwa_link_ee")
    path = tmp_path / "iiwa.yaml"
    path.write_text(model_yaml(imp.model, "imported"), encoding="utf-8")
    back = load_robot_model(path)
    q = random_configurations(back, 30, seed=4)
    assert fk_difference(Chain(back).fk(q), Chain(imp.model).fk(q))[0] < 1e-9
    assert back.joints == imp.model.joints


# --- near-parallel axes ----------------------------------------------------------------------------
def _tx60_with_beta(beta_deg: float):
    d = load_robot_model(ROBOTS / "staubli_tx60.yaml").model_dump()
    d["joints"][1]["beta"] = beta_deg
    return robot_model_from_dict(d)


def test_near_parallel_axes_come_back_as_the_same_hayati_beta(tmp_path):
    model = _tx60_with_beta(0.05)
    path = export_urdf(model, tmp_path / "tx60.urdf")
    imp = import_urdf(path)
    assert imp.model.convention == "mdh"
    j2 = imp.model.joints[1]
    assert j2.beta == pytest.approx(0.05, abs=1e-9) and j2.d == pytest.approx(0.0, abs=1e-9) and j2.a == pytest.approx(290.0)
    assert _against_urdf(path, imp)[0] < 1e-8


def test_a_dh_table_for_near_parallel_axes_is_exact_but_says_it_is_ill_conditioned(tmp_path):
    path = export_urdf(_tx60_with_beta(0.05), tmp_path / "tx60.urdf")
    imp = import_urdf(path, convention="dh")
    assert imp.model.convention == "dh" and abs(imp.model.joints[1].d) > 1e4  # the common normal runs off
    assert any("near-parallel in a dh table" in n for n in imp.notes)
    assert _against_urdf(path, imp)[0] < 1e-6


# --- export ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SHIPPED)
def test_exported_urdf_has_the_models_kinematics_in_yourdfpy_and_imports_back(tmp_path, name):
    model = load_robot_model(ROBOTS / name)
    path = export_urdf(model, tmp_path / "robot.urdf")
    q = random_configurations(model, 40, seed=5)
    pos, rot = fk_difference(Chain(model).fk(q), urdf_fk(load_urdf(path), model.axis_names, "base_link", "flange", q))
    assert pos < 1e-8 and rot < 1e-9
    imp = import_urdf(path, convention=model.convention)
    assert imp.tip == "flange" and imp.model.axis_names == model.axis_names
    assert np.abs(Chain(imp.model).marker_positions(q) - Chain(model).marker_positions(q)).max() < 1e-8
    assert imp.model.marker_names == model.marker_names
    np.testing.assert_allclose([j.limits for j in imp.model.joints], [j.limits for j in model.joints], rtol=1e-6)
    assert [j.max_speed for j in imp.model.joints] == pytest.approx([j.max_speed for j in model.joints])
    assert imp.model.has_dynamics == model.has_dynamics
    if model.has_dynamics:
        for got, ref in zip([j.com_mm for j in imp.model.joints], [j.com_mm for j in model.joints]):
            np.testing.assert_allclose(got, ref, atol=1e-8)


def test_exported_urdf_joint_values_are_the_controllers_angles(tmp_path):
    """KR 6 A1 turns clockwise seen from above for positive A1 (sign -1): so must the URDF joint."""
    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    u = load_urdf(export_urdf(model, tmp_path / "kr6.urdf"))
    q = np.zeros((1, 6))
    q[0, 0] = math.radians(30)
    flange = urdf_fk(u, model.axis_names, "base_link", "flange", q)[0, :3, 3]
    assert flange[1] < -100  # stretched along +x at zero, swung to −y by +30° of A1
    assert flange == pytest.approx(Chain(model).fk(q[0])[:3, 3])


# --- what is refused ---------------------------------------------------------------------------------
ARM = """<robot name="arm">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="tool"/>
  <joint name="j1" type="{t1}"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.3"/>
    <axis xyz="{axis}"/>{limit}{mimic}</joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.4 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" velocity="3" effort="0"/></joint>
  <joint name="jt" type="fixed"><parent link="l2"/><child link="tool"/><origin xyz="0.1 0 0"/></joint>
  {extra}
</robot>
"""
LIMIT = '<limit lower="-3" upper="3" velocity="2" effort="0"/>'


def _arm(tmp_path, t1="revolute", axis="0 0 1", limit=LIMIT, mimic="", extra="") -> Path:
    path = tmp_path / "arm.urdf"
    path.write_text(ARM.format(t1=t1, axis=axis, limit=limit, mimic=mimic, extra=extra), encoding="utf-8")
    return path


def test_the_small_arm_itself_imports(tmp_path):
    imp = import_urdf(_arm(tmp_path))
    assert imp.joints == ["j1", "j2"] and imp.tip == "tool"
    assert _against_urdf(tmp_path / "arm.urdf", imp)[0] < 1e-9


@pytest.mark.parametrize("kwargs, message", [
    ({"t1": "prismatic"}, "joint 'j1' is prismatic"),
    ({"t1": "continuous", "limit": ""}, "joint 'j1' is continuous (no position limits)"),
    ({"t1": "floating"}, "joint 'j1' is floating"),
    ({"limit": ""}, "joint 'j1' has no <limit>"),
    ({"limit": '<limit lower="-3" upper="3" effort="0"/>'}, "<limit> lacks velocity="),
    ({"limit": '<limit upper="3" velocity="2" effort="0"/>'}, "<limit> lacks lower="),
    ({"limit": '<limit lower="3" upper="-3" velocity="2" effort="0"/>'}, "lower must be below upper"),
    ({"limit": '<limit lower="-170" upper="170" velocity="2" effort="0"/>'}, "URDF limits are radians"),
    ({"limit": '<limit lower="-3" upper="3" velocity="0" effort="0"/>'}, "velocity=0.0> must be positive"),
    ({"axis": "0 0 0"}, "has axis [0.0, 0.0, 0.0]"),
    ({"mimic": '<mimic joint="j2"/>'}, "joint 'j1' mimics 'j2'"),
    ({"extra": '<joint name="again" type="fixed"><parent link="base"/><child link="l2"/></joint>'},
     "link 'l2' is the child of joints 'j2' and 'again': not a tree"),
    ({"extra": '<joint name="bad" type="fixed"><parent link="base"/><child link="ghost"/></joint>'},
     "joint 'bad' names child link 'ghost', which is not a <link>"),
    ({"extra": '<link name="stray"/>'}, "2 links have no parent (base, stray)"),
    ({"extra": '<link name="l3"/><joint name="j3" type="revolute"><parent link="l1"/><child link="l3"/>'
               '<axis xyz="1 0 0"/><limit lower="-1" upper="1" velocity="1" effort="0"/></joint>'
               '<link name="l4"/><joint name="j4" type="fixed"><parent link="l3"/><child link="l4"/></joint>'},
     "2 end links are reached through 2 movable joints (l4, tool): choose the flange with --tip"),
])
def test_urdfs_that_are_not_a_revolute_serial_chain_are_refused_naming_the_joint(tmp_path, kwargs, message):
    path = _arm(tmp_path, **kwargs)
    with pytest.raises(UrdfError) as err:
        import_urdf(path)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)


def test_bad_link_choices_and_files_are_refused(tmp_path):
    path = _arm(tmp_path)
    with pytest.raises(UrdfError, match=r"no link 'flange' \(--tip\); links: base, l1, l2, tool"):
        import_urdf(path, tip="flange")
    with pytest.raises(UrdfError, match=r"link 'l1' \(--tip\) is not below link 'l2' \(--base\)"):
        import_urdf(path, base="l2", tip="l1")
    with pytest.raises(UrdfError, match="no revolute joint between 'l2' and 'tool'"):
        import_urdf(path, base="l2")
    with pytest.raises(UrdfError, match="3 axis names given for 2 revolute joints"):
        import_urdf(path, axes=["A1", "A2", "A3"])
    with pytest.raises(UrdfError, match="no such URDF file"):
        import_urdf(tmp_path / "missing.urdf")
    broken = tmp_path / "broken.urdf"
    broken.write_text('<robot name="x"><link name="a"/><joint name="j" type="fixed"><child link="a"/></joint></robot>')
    with pytest.raises(UrdfError, match="not a readable URDF"):
        import_urdf(broken)
    with pytest.raises(ValueError, match="convention must be dh, mdh or auto"):
        import_urdf(path, convention="poe")


# --- arbitrary geometry ------------------------------------------------------------------------------
def _random_chain_urdf(path: Path, seed: int) -> Path:
    """A 7-joint chain with random origins and axes, and on purpose: an exactly parallel pair, an
    anti-parallel pair, a near-parallel pair (0.06°), intersecting axes and a tilted, offset base."""
    rng = np.random.default_rng(seed)
    links = "".join(f'<link name="l{i}"/>' for i in range(9))
    joints = ['<joint name="mount" type="fixed"><parent link="l0"/><child link="l1"/>'
              f'<origin xyz="{rng.uniform(-1, 1):.6f} {rng.uniform(-1, 1):.6f} 0.5" rpy="0.3 -0.2 1.1"/></joint>']
    for i in range(1, 8):
        rpy = rng.uniform(-math.pi, math.pi, 3)
        xyz = rng.uniform(-0.3, 0.3, 3)
        axis = _unit(rng.normal(size=3))
        if i == 3:  # parallel to joint 2: no rotation between them, same axis
            rpy, axis = np.zeros(3), prev_axis
        elif i == 4:  # anti-parallel to joint 3
            rpy, axis = np.zeros(3), -prev_axis
        elif i == 5:  # near-parallel to joint 4
            rpy, axis = np.array([1e-3, 0.0, 0.0]), prev_axis
        elif i == 6:  # intersects joint 5's axis at the joint origin
            xyz = np.zeros(3)
        prev_axis = axis
        joints.append(f'<joint name="j{i}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/>'
                      f'<origin xyz="{" ".join(repr(float(v)) for v in xyz)}" rpy="{" ".join(repr(float(v)) for v in rpy)}"/>'
                      f'<axis xyz="{" ".join(repr(float(v)) for v in axis)}"/><limit lower="-3" upper="3" velocity="1" effort="0"/></joint>')
    joints.append('<joint name="tool" type="fixed"><parent link="l8"/><child link="tcp"/>'
                  '<origin xyz="0.01 -0.02 0.15" rpy="0.4 0.5 -0.6"/></joint><link name="tcp"/>')
    path.write_text(f'<robot name="random">{links}{"".join(joints)}</robot>', encoding="utf-8")
    return path


def _unit(v):
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("convention", ["auto", "dh", "mdh"])
def test_any_serial_geometry_converts_exactly(tmp_path, seed, convention):
    path = _random_chain_urdf(tmp_path / "random.urdf", seed)
    imp = import_urdf(path, convention=convention)
    assert imp.tip == "tcp" and len(imp.joints) == 7
    assert imp.model.convention == ("mdh" if convention == "auto" else convention)
    tol = 1e-6 if convention == "dh" else 1e-9  # a dh table puts a frame far out along the near-parallel pair
    pos, rot = _against_urdf(path, imp, n=25, seed=seed)
    assert pos < tol and rot < 1e-9, (pos, rot)
    if convention != "dh":
        assert abs(imp.model.joints[3].beta) > 0.01 and all(abs(j.d) < 1e4 for j in imp.model.joints)


# unclosed_link.urdf: links and joints interleaved as ROS writes them, with <link name="l1"> left open (line 6): yourdfpy
# alone logs the error, re-parses with recover=True, finds j2 and l2 inside link l1 and returns a
# 1-joint robot (base → l1), which used to be imported without a word.
UNCLOSED = Path(__file__).parent / "urdf" / "unclosed_link.urdf"


def test_a_malformed_urdf_is_refused_naming_line_and_parser_message_not_recovered(tmp_path):
    path = tmp_path / "two.urdf"
    path.write_text(UNCLOSED.read_text())
    with pytest.raises(UrdfError) as err:
        import_urdf(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}:10:") and "not well-formed XML" in msg, msg
    assert "Opening and ending tag mismatch: link line 6 and robot" in msg, msg
    with pytest.raises(UrdfError, match="not well-formed XML"):
        load_urdf(path)
    # Closed, the same file is the 2-joint arm.
    path.write_text(UNCLOSED.read_text().replace('<link name="l1">', '<link name="l1"/>'))
    assert import_urdf(path).joints == ["j1", "j2"]

def test_a_urdf_with_entities_is_refused(tmp_path):
    path = tmp_path / "xxe.urdf"
    path.write_text('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY x SYSTEM "file:///etc/hostname">]>\n'
                    + ARM.format(t1="revolute", axis="0 0 1", limit=LIMIT, mimic="", extra="<!-- &x; -->"))
    with pytest.raises(UrdfError, match=rf"^{path}:1:1: a DOCTYPE is not allowed in a URDF"):
        import_urdf(path)
