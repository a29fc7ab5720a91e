"""6-DoF rows in the measurement CSV: orientation columns (unit quaternion, scalar first), their
round trip and clear errors. Vectors are built by hand here, not by our quaternion code."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib.measure.dataset import DatasetError, from_arrays, parse_csv, read_csv, write_csv
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import apply, exp_so3, pose_to_matrix

ROOT = Path(__file__).resolve().parents[2]
TX60 = load_robot_model(ROOT / "fixtures" / "robots" / "staubli_tx60.yaml")
B2S = pose_to_matrix(np.array([1500.0, 200.0, -300.0]), np.radians([150.0, 3.0, -2.0]))


def pose_rows(k: int = 8, seed: int = 0):
    rng = np.random.default_rng(seed)
    chain = Chain(TX60)
    q = rng.uniform(TX60.lower_limits_rad * 0.6, TX60.upper_limits_rad * 0.6, (k, 6))
    xyz = apply(B2S, chain.marker_positions(q)[:, 0])
    rot = exp_so3(rng.normal(0, 1.0, (k, 3)))
    rot[2] = np.nan  # one position-only row
    return from_arrays(q, xyz, marker="smr", sensor="tracker", rot=rot, att_std_rad=np.radians(0.01),
                       std_mm=np.full(k, 0.02))


def header(extra: str = "qw,qx,qy,qz,std_deg") -> str:
    return "config,q1,q2,q3,q4,q5,q6,x,y,z," + extra


ROW = "c1,10,20,30,40,50,60,800,100,200,"


def test_orientation_round_trips_through_the_csv(tmp_path):
    ds = pose_rows()
    path = tmp_path / "p.csv"
    write_csv(ds, path)
    back = read_csv(path, TX60)
    assert back.has_orientation
    np.testing.assert_array_equal(back.oriented, ds.oriented)
    np.testing.assert_allclose(back.rot[ds.oriented], ds.rot[ds.oriented], atol=1e-11)
    np.testing.assert_allclose(back.att_std_rad[ds.oriented], np.radians(0.01))
    assert "qw,qx,qy,qz,std_deg" in path.read_text().splitlines()[0]


def test_quaternion_convention_scalar_first_hamilton():
    # 90° about z: (w, x, y, z) = (cos 45°, 0, 0, sin 45°) takes the target's x axis to the sensor's y.
    c = math.cos(math.pi / 4)
    text = header() + f"\n{ROW}{c},0,0,{c},0.02\n"
    ds = parse_csv(text, TX60)
    np.testing.assert_allclose(ds.rot[0] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert ds.att_std_rad[0] == pytest.approx(math.radians(0.02))


def test_semicolon_decimal_comma_orientation():
    text = "config;q1;q2;q3;q4;q5;q6;x;y;z;qw;qx;qy;qz\nc1;10;20;30;40;50;60;800,5;100;200;0,5;0,5;0,5;0,5\n"
    ds = parse_csv(text, TX60)
    np.testing.assert_allclose(ds.rot[0] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # 120° about (1,1,1)


@pytest.mark.parametrize("text, match", [
    (header("qw,qx,qy") + f"\n{ROW}1,0,0\n", "without \\['qz'\\]"),
    (header() + f"\n{ROW}1,0,0,0.2,0.01\n", "norm 1.0198"),
    (header() + f"\n{ROW}1,,0,0,0.01\n", "partly empty"),
    (header() + f"\n{ROW}1,0,0,0,-1\n", "'std_deg'"),
    (header("std_deg") + f"\n{ROW}0.1\n", "without orientation columns"),
])
def test_bad_orientation_is_refused_by_line_and_column(text, match):
    with pytest.raises(DatasetError, match=match) as err:
        parse_csv(text, TX60, source="pose.csv")
    assert str(err.value).startswith("pose.csv:")


def test_subset_and_concat_keep_orientation():
    ds = pose_rows()
    sub = ds.subset(np.arange(len(ds)) < 4)
    assert sub.rot.shape == (4, 3, 3)
    joined = sub.concat(ds.without_orientation())
    assert joined.rot.shape == (4 + len(ds), 3, 3) and joined.oriented.sum() == sub.oriented.sum()
