"""Forward kinematics of every shipped robot model against INDEPENDENT references.

* Product-of-exponentials (PoE) models built here from each robot's published URDF joint
  origins and axes (numbers copied below, sources named per robot). The PoE code shares
  nothing with ``calib.robot.kinematics``: screws from the zero-configuration frames, matrix
  exponentials, one configuration at a time.
* For the KUKA KR 6 R900-2 also the OPW closed form (Brandstötter, Angerer, Hofbaur 2014) as
  implemented in ROS-Industrial's opw_kinematics ``forward()``, with the kr6r900_2 parameters.
* Published zero-pose flange positions (data-sheet geometry) as plain numbers.

URDF joint positions are the controller's angles for these robots: ROS-Industrial's KUKA and
Stäubli URDFs flip axes (e.g. KR 6 A1 about −z) so that a URDF angle equals the pendant's, and
their zero is the controller's zero (KUKA: upper arm horizontal at A2 = 0, as in KSS). The
iiwa_stack URDF is driven with Sunrise's joint angles unchanged.

Also here: the analytic parameter Jacobians against central finite differences (every
parameter, seeded configurations and perturbed parameter vectors), batched shapes, and bad
model files rejected with file, line and field.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import euler_zyx_to_matrix, exp_so3, homogeneous, skew
from calib.io.yamlfile import ConfigError

ROBOTS = Path(__file__).resolve().parents[2] / "fixtures" / "robots"
PI = math.pi

# --- URDF joint data: (origin xyz in m, origin rpy in rad, axis) per revolute joint -------------
# Source: IFL-CAMP/iiwa_stack, iiwa_description/urdf/iiwa14.xacro (joints iiwa_joint_1..7 and the
# fixed iiwa_joint_ee to link_ee_kuka, the media flange: xyz 0 0 0.045, rpy π π π = identity).
IIWA14_URDF = [
    ((0, 0, 0.1575), (0, 0, 0), (0, 0, 1)),
    ((0, 0, 0.2025), (PI / 2, 0, PI), (0, 0, 1)),
    ((0, 0.2045, 0), (PI / 2, 0, PI), (0, 0, 1)),
    ((0, 0, 0.2155), (PI / 2, 0, 0), (0, 0, 1)),
    ((0, 0.1845, 0), (-PI / 2, PI, 0), (0, 0, 1)),
    ((0, 0, 0.2155), (PI / 2, 0, 0), (0, 0, 1)),
    ((0, 0.081, 0), (-PI / 2, PI, 0), (0, 0, 1)),
]
IIWA_FLANGE = ((0, 0, 0.045), (PI, PI, PI))

# Source: IFL-CAMP/iiwa_stack, iiwa_description/urdf/iiwa7.xacro (same flange joint as iiwa14;
# note the 60.7 mm y/z steps at joints 6 and 7 that cancel).
IIWA7_URDF = [
    ((0, 0, 0.15), (0, 0, 0), (0, 0, 1)),
    ((0, 0, 0.19), (PI / 2, 0, PI), (0, 0, 1)),
    ((0, 0.21, 0), (PI / 2, 0, PI), (0, 0, 1)),
    ((0, 0, 0.19), (PI / 2, 0, 0), (0, 0, 1)),
    ((0, 0.21, 0), (-PI / 2, PI, 0), (0, 0, 1)),
    ((0, 0.0607, 0.19), (PI / 2, 0, 0), (0, 0, 1)),
    ((0, 0.081, 0.0607), (-PI / 2, PI, 0), (0, 0, 1)),
]

# Source: ros-industrial/kuka_experimental, kuka_kr6_support/urdf/kr6r900_2_macro.xacro
# (joint_a1..a6; tool0 = KUKA $FLANGE: joint_a6-tool0 rpy 0 90° 0).
KR6_URDF = [
    ((0, 0, 0.400), (0, 0, 0), (0, 0, -1)),
    ((0.025, 0, 0), (0, 0, 0), (0, 1, 0)),
    ((0.455, 0, 0), (0, 0, 0), (0, 1, 0)),
    ((0, 0, 0.025), (0, 0, 0), (-1, 0, 0)),
    ((0.420, 0, 0), (0, 0, 0), (0, 1, 0)),
    ((0.090, 0, 0), (0, 0, 0), (-1, 0, 0)),
]
KR6_FLANGE = ((0, 0, 0), (0, PI / 2, 0))

# Source: ros-industrial/staubli_experimental, staubli_tx60_support/urdf/tx60_macro.xacro
# (joint_1..6 from base_link on the mounting face; tool0 = link_6 via flange rpy 0 −90° 0 then
# 0 +90° 0, i.e. identity).
TX60_URDF = [
    ((0, 0, 0.375), (0, 0, 0), (0, 0, 1)),
    ((0, 0.2175, 0), (0, 0, 0), (0, 1, 0)),
    ((0, 0, 0.290), (0, 0, 0), (0, 1, 0)),
    ((0, -0.1975, 0), (0, 0, 0), (0, 0, 1)),
    ((0, 0, 0.310), (0, 0, 0), (0, 1, 0)),
    ((0, 0, 0.070), (0, 0, 0), (0, 0, 1)),
]
TX60_FLANGE = ((0, 0, 0), (0, 0, 0))

# Source: frankaemika/franka_ros, franka_description/robots/panda_arm.xacro (panda_joint1..7,
# then the fixed panda_joint8 to panda_link8, the flange: xyz 0 0 0.107).
PANDA_URDF = [
    ((0, 0, 0.333), (0, 0, 0), (0, 0, 1)),
    ((0, 0, 0), (-PI / 2, 0, 0), (0, 0, 1)),
    ((0, -0.316, 0), (PI / 2, 0, 0), (0, 0, 1)),
    ((0.0825, 0, 0), (PI / 2, 0, 0), (0, 0, 1)),
    ((-0.0825, 0.384, 0), (-PI / 2, 0, 0), (0, 0, 1)),
    ((0, 0, 0), (PI / 2, 0, 0), (0, 0, 1)),
    ((0.088, 0, 0), (PI / 2, 0, 0), (0, 0, 1)),
]
PANDA_FLANGE = ((0, 0, 0.107), (0, 0, 0))

# Source: ros-industrial/universal_robot, ur_description/urdf/ur10.urdf.xacro (shoulder_pan_joint
# .. wrist_3_joint, then tool0: xyz 0 0.0922 0, rpy -π/2 0 0). ROS's base_link faces the other way
# from UR's DH base frame (the controller's "base"): a yaw of π before the first joint.
UR10_URDF = [
    ((0, 0, 0.1273), (0, 0, PI), (0, 0, 1)),
    ((0, 0.220941, 0), (0, PI / 2, 0), (0, 1, 0)),
    ((0, -0.1719, 0.612), (0, 0, 0), (0, 1, 0)),
    ((0, 0, 0.5723), (0, PI / 2, 0), (0, 1, 0)),
    ((0, 0.1149, 0), (0, 0, 0), (0, 0, 1)),
    ((0, 0, 0.1157), (0, 0, 0), (0, 1, 0)),
]
UR10_FLANGE = ((0, 0.0922, 0), (-PI / 2, 0, 0))

REFERENCES = {
    "kuka_iiwa14_r820.yaml": (IIWA14_URDF, IIWA_FLANGE),
    "kuka_iiwa7_r800.yaml": (IIWA7_URDF, IIWA_FLANGE),
    "kuka_kr6_r900_2.yaml": (KR6_URDF, KR6_FLANGE),
    "staubli_tx60.yaml": (TX60_URDF, TX60_FLANGE),
    "franka_panda.yaml": (PANDA_URDF, PANDA_FLANGE),
    "ur10.yaml": (UR10_URDF, UR10_FLANGE),
}

# Flange position (mm) at the controller's zero, from the data-sheet link lengths.
ZERO_FLANGE_MM = {
    "kuka_iiwa14_r820.yaml": (0.0, 0.0, 360 + 420 + 400 + 126),  # arm straight up
    "kuka_iiwa7_r800.yaml": (0.0, 0.0, 340 + 400 + 400 + 126),
    "kuka_kr6_r900_2.yaml": (25 + 455 + 420 + 90, 0.0, 400 + 25),  # arm stretched forward
    "staubli_tx60.yaml": (0.0, 20.0, 375 + 290 + 310 + 70),  # arm straight up, 20 mm shoulder step
    "franka_panda.yaml": (82.5 - 82.5 + 88, 0.0, 333 + 316 + 384 - 107),  # the flange pointing down
    "ur10.yaml": (-(612 + 572.3), -(163.941 + 92.2), 127.3 - 115.7),  # arm stretched along the base's -x
}

SHIPPED = sorted(p.name for p in ROBOTS.glob("*.yaml"))


# --- the independent PoE reference ---------------------------------------------------------
def _urdf_origin(xyz_m, rpy) -> np.ndarray:
    """URDF origin: translation (m → mm) and fixed-axis roll-pitch-yaw, R = Rz(y) Ry(p) Rx(r)."""
    r, p, y = rpy
    return homogeneous(euler_zyx_to_matrix(y, p, r), np.array(xyz_m, float) * 1000.0)


def poe_from_urdf(joints, flange):
    """Space-frame screws (ω, v) per joint and the home flange frame M (mm)."""
    t = np.eye(4)
    screws = []
    for xyz, rpy, axis in joints:
        t = t @ _urdf_origin(xyz, rpy)
        w = t[:3, :3] @ np.array(axis, float)
        w /= np.linalg.norm(w)
        screws.append((w, -np.cross(w, t[:3, 3])))
    return screws, t @ _urdf_origin(*flange)


def _exp_twist(w, v, theta) -> np.ndarray:
    big_w = skew(w)
    g = np.eye(3) * theta + (1 - math.cos(theta)) * big_w + (theta - math.sin(theta)) * big_w @ big_w
    return homogeneous(exp_so3(w * theta), g @ v)


def poe_fk(screws, home, q) -> np.ndarray:
    t = np.eye(4)
    for (w, v), theta in zip(screws, q):
        t = t @ _exp_twist(w, v, float(theta))
    return t @ home


def opw_forward(qs, a1=25.0, a2=-25.0, b=0.0, c1=400.0, c2=455.0, c3=420.0, c4=90.0,
                signs=(-1, 1, 1, -1, 1, -1), offsets=(0.0, -PI / 2, 0.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """OPW forward kinematics (opw_kinematics_impl.h ``forward``), mm; KR 6 R900-2 parameters."""
    q = [qs[i] * signs[i] - offsets[i] for i in range(6)]
    psi3, k = math.atan2(a2, c3), math.hypot(a2, c3)
    cx1 = c2 * math.sin(q[1]) + k * math.sin(q[1] + q[2] + psi3) + a1
    cz1 = c2 * math.cos(q[1]) + k * math.cos(q[1] + q[2] + psi3)
    centre = np.array([cx1 * math.cos(q[0]) - b * math.sin(q[0]), cx1 * math.sin(q[0]) + b * math.cos(q[0]), cz1 + c1])
    s1, s2, s3, s4, s5, s6 = (math.sin(x) for x in q)
    k1, k2, k3, k4, k5, k6 = (math.cos(x) for x in q)
    r_0c = np.array([
        [k1 * k2 * k3 - k1 * s2 * s3, -s1, k1 * k2 * s3 + k1 * s2 * k3],
        [s1 * k2 * k3 - s1 * s2 * s3, k1, s1 * k2 * s3 + s1 * s2 * k3],
        [-s2 * k3 - k2 * s3, 0.0, -s2 * s3 + k2 * k3],
    ])
    r_ce = np.array([
        [k4 * k5 * k6 - s4 * s6, -k4 * k5 * s6 - s4 * k6, k4 * s5],
        [s4 * k5 * k6 + k4 * s6, -s4 * k5 * s6 + k4 * k6, s4 * s5],
        [-s5 * k6, s5 * s6, k5],
    ])
    r = r_0c @ r_ce
    return homogeneous(r, centre + c4 * r[:, 2])


def _configs(model, n, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(model.lower_limits_rad, model.upper_limits_rad, (n, model.n_joints))


def _describe_mismatch(chain, screws, home, model) -> str:
    """Name the first joint whose motion the model gets wrong (sign or offset) for the report."""
    msgs = []
    for i, ax in enumerate(model.axis_names):
        for deg in (0.0, 30.0):
            q = np.zeros(model.n_joints)
            q[i] = math.radians(deg)
            a, b = chain.fk(q), poe_fk(screws, home, q)
            if not np.allclose(a, b, atol=1e-6):
                msgs.append(f"{ax} at {deg:+.0f}°: model {a[:3, 3].round(3)} vs URDF {b[:3, 3].round(3)}")
                break
    return "; ".join(msgs)


# --- tests -----------------------------------------------------------------------------------
def test_every_shipped_robot_has_an_independent_reference():
    assert SHIPPED, "no robot models found"
    assert set(SHIPPED) <= set(REFERENCES), f"add a URDF reference for {sorted(set(SHIPPED) - set(REFERENCES))}"


@pytest.mark.parametrize("name", SHIPPED)
def test_fk_matches_the_urdf_product_of_exponentials(name):
    model = load_robot_model(ROBOTS / name)
    chain = Chain(model)
    screws, home = poe_from_urdf(*REFERENCES[name])
    q = np.concatenate([np.zeros((1, model.n_joints)), _configs(model, 40, seed=11)])
    ours = chain.fk(q)
    ref = np.stack([poe_fk(screws, home, x) for x in q])
    worst = np.abs(ours[:, :3, 3] - ref[:, :3, 3]).max()
    assert worst < 1e-9, f"{name}: position off by {worst:.3g} mm; " + _describe_mismatch(chain, screws, home, model)
    np.testing.assert_allclose(ours[:, :3, :3], ref[:, :3, :3], atol=1e-12, err_msg=f"{name}: flange orientation")


@pytest.mark.parametrize("name", SHIPPED)
def test_zero_pose_flange_is_where_the_data_sheet_puts_it(name):
    model = load_robot_model(ROBOTS / name)
    t = Chain(model).fk(np.zeros(model.n_joints))
    np.testing.assert_allclose(t[:3, 3], ZERO_FLANGE_MM[name], atol=1e-9)


@pytest.mark.parametrize("name", SHIPPED)
def test_markers_ride_on_the_reference_flange(name):
    model = load_robot_model(ROBOTS / name)
    chain = Chain(model)
    screws, home = poe_from_urdf(*REFERENCES[name])
    q = _configs(model, 10, seed=12)
    ours = chain.marker_positions(q)
    mk = np.array([m.xyz for m in model.tool.markers])
    ref = np.stack([poe_fk(screws, home, x)[:3, :3] @ mk.T + poe_fk(screws, home, x)[:3, 3:] for x in q])
    np.testing.assert_allclose(ours, np.swapaxes(ref, 1, 2), atol=1e-9)


def test_kr6_matches_the_opw_closed_form():
    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    chain = Chain(model)
    home = np.radians([0, -90, 90, 0, 0, 0])  # KUKA's home: upper arm up, forearm forward
    q = np.concatenate([np.zeros((1, 6)), home[None], _configs(model, 40, seed=13)])
    ours = chain.fk(q)
    ref = np.stack([opw_forward(x) for x in q])
    np.testing.assert_allclose(ours[:, :3, 3], ref[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(ours[:, :3, :3], ref[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(ours[1, :3, 3], [25 + 420 + 90, 0, 400 + 455 + 25], atol=1e-9)


def test_the_references_themselves_see_a_wrong_sign_or_offset():
    """Guards the guard: a flipped A1 sign or a 1° offset must be caught by both references."""
    model = load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml")
    chain = Chain(model)
    screws, home = poe_from_urdf(*REFERENCES["kuka_kr6_r900_2.yaml"])
    q = _configs(model, 5, seed=14)
    flipped = q * np.array([-1, 1, 1, 1, 1, 1])
    assert np.abs(chain.fk(flipped)[:, :3, 3] - np.stack([poe_fk(screws, home, x) for x in q])[:, :3, 3]).max() > 10
    offset = chain.with_offsets(np.radians([0, 1, 0, 0, 0, 0]))
    assert np.abs(chain.fk(q, offset)[:, :3, 3] - np.stack([opw_forward(x) for x in q])[:, :3, 3]).max() > 5


# --- Jacobians against finite differences --------------------------------------------------------
def _perturbed(chain, n_sets, seed):
    rng = np.random.default_rng(seed)
    n, m = chain.n, chain.m
    scale = np.concatenate([np.full(n, 0.01), np.full(2 * n, 1.0), np.full(2 * n, 0.01), np.full(3 * m, 1.0)])
    return chain.nominal + rng.normal(size=(n_sets, chain.n_params)) * scale


@pytest.mark.parametrize("name", SHIPPED)
def test_marker_and_flange_jacobians_match_central_differences(name):
    model = load_robot_model(ROBOTS / name)
    chain = Chain(model)
    q = _configs(model, 4, seed=21)
    params = np.concatenate([chain.nominal[None], _perturbed(chain, 2, seed=22)])  # (3, P)
    h = 1e-6
    n_p = chain.n_params
    for p in params:
        _, jac = chain.marker_jacobian(q, p)  # (n_q, m, 3, P)
        fj = chain.flange_jacobian(q, p)
        plus = p + h * np.eye(n_p)
        minus = p - h * np.eye(n_p)
        num = (chain.marker_positions(q, plus) - chain.marker_positions(q, minus)) / (2 * h)  # (P, n_q, m, 3)
        np.testing.assert_allclose(jac, np.moveaxis(num, 0, -1), atol=2e-5, rtol=1e-6, err_msg=f"{name} markers")
        r_plus, t_plus = chain.flange_pose(q, plus)
        r_minus, t_minus = chain.flange_pose(q, minus)
        np.testing.assert_allclose(fj.jp, np.moveaxis((t_plus - t_minus) / (2 * h), 0, -1), atol=2e-5, rtol=1e-6)
        d_r = (r_plus - r_minus) / (2 * h)  # (P, n_q, 3, 3)
        omega = d_r @ np.swapaxes(fj.rotation, -1, -2)
        w_num = 0.5 * np.stack([omega[..., 2, 1] - omega[..., 1, 2], omega[..., 0, 2] - omega[..., 2, 0], omega[..., 1, 0] - omega[..., 0, 1]], -1)
        np.testing.assert_allclose(fj.jw, np.moveaxis(w_num, 0, -1), atol=1e-8, err_msg=f"{name} flange rotation")


def test_jacobian_joint_columns_are_the_joint_velocity_jacobian():
    """d/dδ_i equals d/dq_i: the offset columns are the ordinary joint Jacobian."""
    model = load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml")
    chain = Chain(model)
    q = _configs(model, 3, seed=23)
    fj = chain.flange_jacobian(q)
    h = 1e-6
    for i in range(chain.n):
        dq = np.zeros(chain.n)
        dq[i] = h
        num = (chain.fk(q + dq)[:, :3, 3] - chain.fk(q - dq)[:, :3, 3]) / (2 * h)
        np.testing.assert_allclose(fj.jp[..., i], num, atol=2e-5)


# --- batched shapes ----------------------------------------------------------------------------
def test_batched_shapes_and_values_agree_with_single_calls():
    model = load_robot_model(ROBOTS / "staubli_tx60.yaml")
    chain = Chain(model)
    n, m, n_p = chain.n, chain.m, chain.n_params
    q = _configs(model, 5, seed=31)
    params = _perturbed(chain, 4, seed=32)
    assert chain.fk(q[0]).shape == (4, 4)
    assert chain.fk(q).shape == (5, 4, 4)
    assert chain.fk(q.reshape(5, 1, n)).shape == (5, 1, 4, 4)
    assert chain.fk(q, params).shape == (4, 5, 4, 4)
    assert chain.fk(q[0], params).shape == (4, 4, 4)
    assert chain.marker_positions(q, params).shape == (4, 5, m, 3)
    pos, jac = chain.marker_jacobian(q, params)
    assert pos.shape == (4, 5, m, 3) and jac.shape == (4, 5, m, 3, n_p)
    fj = chain.flange_jacobian(q, params)
    assert fj.jp.shape == fj.jw.shape == (4, 5, 3, n_p) and fj.rotation.shape == (4, 5, 3, 3)
    batch = chain.fk(q, params)
    for a in range(4):
        for b in range(5):
            # One configuration with one parameter vector takes the plain-float path.
            np.testing.assert_allclose(batch[a, b], chain.fk(q[b], params[a]), atol=1e-12)
            rot, pos1 = chain.flange_pose(q[b], params[a])
            np.testing.assert_allclose(rot, batch[a, b, :3, :3], atol=1e-12)
            np.testing.assert_allclose(pos1, batch[a, b, :3, 3], atol=1e-12)
            np.testing.assert_allclose(chain.marker_positions(q[b], params[a]),
                                       chain.marker_positions(q[b:b + 1], params[a:a + 1])[0, 0], atol=1e-12)
            np.testing.assert_allclose(jac[a, b], chain.marker_jacobian(q[b], params[a])[1], atol=1e-9)


def test_wrong_sizes_are_refused_with_what_was_given():
    chain = Chain(load_robot_model(ROBOTS / "kuka_kr6_r900_2.yaml"))
    with pytest.raises(ValueError, match="joint vectors have 7 entries, the model has 6 joints"):
        chain.fk(np.zeros(7))
    with pytest.raises(ValueError, match=f"parameter vector has 3 entries, this chain needs {chain.n_params}"):
        chain.fk(np.zeros(6), np.zeros(3))


# --- bad model files ------------------------------------------------------------------------------
KR6_TEXT = (ROBOTS / "kuka_kr6_r900_2.yaml").read_text(encoding="utf-8")


def _line_of(text: str, needle: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), start=1) if needle in line)


@pytest.mark.parametrize(
    "old, new, needle, field, why",
    [
        ("{axis: A1, theta: 0,   d: 400, a: 25,  alpha: -90, sign: -1, limits: [-170, 170], max_speed: 360, ",
         "{axis: A1, theta: 0,   d: 400, a: 25,  alpha: -90, sign: -1, limits: [-170, 170], ",
         "axis: A1", "joints.0.max_speed", "Field required"),
        ("{axis: A4, theta: 0,   d: 420,", "{axis: A4, theta: 0,   d: four-twenty,",
         "axis: A4", "joints.3.d", "valid number"),
        ("limits: [-190, 45]", "limits: [45, -190]", "axis: A2", "joints.1.limits", "lower limit 45.0 must be below upper limit -190.0"),
        ("limits: [-120, 120], max_speed: 450", "limits: [30, 30], max_speed: 450",
         "axis: A5", "joints.4.limits", "lower limit 30.0 must be below upper limit 30.0"),
        ("controller: kss", "controller: kss\ncolour: orange", "colour: orange", "colour", "Extra inputs are not permitted"),
        ("sign: 1,  limits: [-120, 156]", "sign: 2,  limits: [-120, 156]", "axis: A3", "joints.2.sign", "1 or -1"),
    ],
)
def test_bad_model_files_name_file_line_and_field(tmp_path, old, new, needle, field, why):
    assert old in KR6_TEXT
    text = KR6_TEXT.replace(old, new, 1)
    path = tmp_path / "robot.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_robot_model(path)
    msg = str(err.value)
    line = _line_of(text, needle)
    assert f"{path}:{line}:" in msg, msg
    assert f": {field}: " in msg and why in msg, msg


def test_beta_in_a_dh_model_is_refused_naming_the_file_and_the_joint(tmp_path):
    text = KR6_TEXT.replace("{axis: A3, theta: 90,", "{axis: A3, theta: 90, beta: 2,", 1)
    path = tmp_path / "robot.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_robot_model(path)
    msg = str(err.value)
    assert str(path) in msg and "beta is only allowed with convention 'mdh'" in msg and "A3" in msg


def test_beta_in_a_dh_model_points_at_the_joint_line(tmp_path):
    text = KR6_TEXT.replace("{axis: A3, theta: 90,", "{axis: A3, theta: 90, beta: 2,", 1)
    path = tmp_path / "robot.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_robot_model(path)
    assert f"{path}:{_line_of(text, 'axis: A3')}:" in str(err.value) and "joints.2.beta" in str(err.value)
