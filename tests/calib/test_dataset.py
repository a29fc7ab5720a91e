"""The measurement CSV: round trip, the example datasets, and clear errors on bad input."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from calib.measure.dataset import DatasetError, from_arrays, parse_csv, read_csv, write_csv
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import apply, pose_to_matrix

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
KR6 = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml")
BASE2SENSOR = pose_to_matrix(np.array([1800.0, -200.0, 400.0]), np.radians([175.0, 4.0, -2.0]))


def simulated(seed: int = 0, k: int = 12, scale: float = 1.0):
    """A small noise-free iiwa dataset (positions multiplied by ``scale``), in pose groups of 3."""
    rng = np.random.default_rng(seed)
    chain = Chain(IIWA)
    q = rng.uniform(IIWA.lower_limits_rad * 0.8, IIWA.upper_limits_rad * 0.8, size=(k, 7))
    xyz = apply(BASE2SENSOR, chain.marker_positions(q)[:, 0]) * scale
    return from_arrays(q, xyz, marker="smr", sensor="tracker", pose=np.repeat(np.arange(k // 3), 3).astype(str),
                       std_mm=np.full(k, 0.02), count=np.full(k, 10))


def csv_lines(tmp_path: Path, **kw) -> list[str]:
    path = tmp_path / "d.csv"
    write_csv(simulated(**kw), path, comment="test data")
    return path.read_text().splitlines()


def test_round_trip_keeps_every_column(tmp_path):
    ds = simulated()
    path = tmp_path / "d.csv"
    write_csv(ds, path, comment="two\nlines")
    back = read_csv(path, IIWA)
    np.testing.assert_allclose(back.q_rad, ds.q_rad, atol=1e-9)
    np.testing.assert_allclose(back.xyz_mm, ds.xyz_mm, atol=1e-6)
    for f in ("config", "pose", "marker", "sensor", "split"):
        assert getattr(back, f).tolist() == getattr(ds, f).tolist(), f
    np.testing.assert_allclose(back.std_mm, 0.02)
    assert back.count.tolist() == [10] * len(ds)
    assert back.source == str(path)


def test_example_datasets_read_and_split():
    cal = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", IIWA)
    val = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_val.csv", IIWA)
    assert 120 <= len(cal) <= 200 and 40 <= len(val) <= 120
    assert set(cal.split) == {"cal"} and set(val.split) == {"val"}
    assert cal.sensors == ["mocap"] and set(cal.marker) == {"sir"}
    # Every pose group holds at least two configurations (the relative metric needs pairs).
    _, counts = np.unique(cal.pose, return_counts=True)
    assert counts.min() >= 2
    joined = cal.concat(val)
    assert len(joined.calibration()) == len(cal) and len(joined.validation()) == len(val)


def test_optional_columns_default(tmp_path):
    text = "config,q1,q2,q3,q4,q5,q6,q7,x,y,z\n"
    ds0 = simulated(k=6)
    for i in range(6):
        text += ",".join([f"c{i}", *[f"{v:.6f}" for v in np.degrees(ds0.q_rad[i])], *[f"{v:.6f}" for v in ds0.xyz_mm[i]]]) + "\n"
    ds = parse_csv(text, IIWA)
    assert ds.marker.tolist() == ["smr"] * 6  # the model's first marker
    assert ds.sensor.tolist() == ["sensor"] * 6 and ds.split.tolist() == ["cal"] * 6
    assert np.isnan(ds.std_mm).all() and (ds.count == 0).all()


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda L: L[:3] + [L[3].replace(L[3].split(",")[9], "nan", 1)] + L[4:], r"d\.csv:4: column 'x': 'nan' is not a finite number"),
        (lambda L: L[:4] + [L[4].replace(L[4].split(",")[10], "abc", 1)] + L[5:], r"d\.csv:5: column 'y': 'abc' is not a number"),
        (lambda L: L[:5] + [L[5] + ",extra"] + L[6:], r"d\.csv:6: 18 columns, the header has 17"),
        (lambda L: L[:5] + [",".join(L[5].split(",")[:-2])] + L[6:], r"d\.csv:6: 15 columns, the header has 17"),
        (lambda L: [L[0], L[1].replace("x,y,z", "x,y")] + L[2:], r"missing column\(s\) \['z'\]"),
        (lambda L: [L[0], L[1].replace("split", "colour")] + L[2:], r"unknown column\(s\) \['colour'\]"),
        (lambda L: L[:3] + [L[3].replace(",smr,", ",elsewhere,")] + L[4:], r"d\.csv:4: column 'marker': 'elsewhere' is not on the tool"),
        (lambda L: L[:3] + [L[3].replace(",cal", ",train")] + L[4:], r"d\.csv:4: column 'split': 'train' is not 'cal' or 'val'"),
    ],
    ids=["nan", "not-a-number", "too-many-columns", "too-few-columns", "missing-column", "unknown-column", "unknown-marker", "bad-split"],
)
def test_bad_rows_name_file_line_and_column(tmp_path, mutate, pattern):
    lines = mutate(csv_lines(tmp_path))
    path = tmp_path / "d.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=pattern):
        read_csv(path, IIWA)


def test_joint_count_must_match_the_model(tmp_path):
    path = tmp_path / "d.csv"
    write_csv(simulated(), path)
    with pytest.raises(DatasetError, match=r"d\.csv:1: 7 joint columns \(q1…q7\) but the robot model 'KUKA KR 6 R900-2' has 6 joints"):
        read_csv(path, KR6)


def test_positions_in_metres_are_refused(tmp_path):
    path = tmp_path / "m.csv"
    write_csv(simulated(k=30, scale=0.001), path)
    with pytest.raises(DatasetError, match=r"m\.csv: .*look like metres .*millimetres"):
        read_csv(path, IIWA)


def test_positions_that_never_move_are_refused_not_a_traceback(tmp_path):
    path = tmp_path / "frozen.csv"
    write_csv(simulated(k=30, scale=0.0), path)
    with pytest.raises(DatasetError, match=r"frozen\.csv: the measured points do not move .*sensor stream"):
        read_csv(path, IIWA)


def test_joint_angles_beyond_two_turns_are_refused(tmp_path):
    lines = csv_lines(tmp_path)
    fields = lines[3].split(",")
    fields[3] = "800"
    lines[3] = ",".join(fields)
    path = tmp_path / "d.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"d\.csv:4: column 'q2': 800.0 is outside ±720; joint angles are in degrees"):
        read_csv(path, IIWA)


def test_unreadable_and_empty_files(tmp_path):
    with pytest.raises(DatasetError, match="cannot read"):
        read_csv(tmp_path / "missing.csv", IIWA)
    (tmp_path / "e.csv").write_text("# only a comment\n")
    with pytest.raises(DatasetError, match="no header and no data"):
        read_csv(tmp_path / "e.csv", IIWA)
    (tmp_path / "h.csv").write_text("config,q1,q2,q3,q4,q5,q6,q7,x,y,z\n")
    with pytest.raises(DatasetError, match="header only"):
        read_csv(tmp_path / "h.csv", IIWA)


def test_error_messages_say_what_is_allowed(tmp_path):
    lines = csv_lines(tmp_path)
    lines[1] = lines[1].replace("q3", "q9")
    path = tmp_path / "d.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as info:
        read_csv(path, IIWA)
    assert re.search(r"q1…qN without gaps", str(info.value))


def _in_radians(tmp_path: Path) -> tuple[Path, int]:
    """The simulated iiwa calibration CSV with its joint angles written in radians (positions in
    mm as measured); the line of its first measurement."""
    ds = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", IIWA)
    path = tmp_path / "radians.csv"
    write_csv(from_arrays(np.radians(ds.q_rad), ds.xyz_mm, marker=ds.marker, sensor=ds.sensor, pose=ds.pose,
                          config=ds.config), path, comment="angles in radians by mistake")
    return path, 3  # one comment line, the header, then the first row


def test_a_csv_in_radians_is_refused_up_front_naming_line_and_columns(tmp_path):
    """It used to pass check_units (radians barely move the model) and run the fit to σ = 288 mm."""
    path, first = _in_radians(tmp_path)
    with pytest.raises(DatasetError) as exc:
        read_csv(path, IIWA)
    msg = str(exc.value)
    assert msg.startswith(f"{path}:{first}: columns 'q1'…'q7': every joint angle of the ")
    assert "these look like radians (given [" in msg and "allowed degrees, e.g. [" in msg
    assert msg.endswith("this file needs degrees")
    # The same angles in degrees are read.
    assert len(read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", IIWA)) > 10


def test_the_plan_and_the_csv_share_one_radians_check():
    from acquire.plan import guards as plan_guards
    from calib.measure import units

    assert plan_guards.radians_problem is units.radians_problem
