"""``acquire fit`` on an IPA tracker series as it comes (``calib.measure.ipa_tracker``), and data that
state no spreads: their noise estimated from the data and printed (``calib.fit.noise``).

The series is simulated: a UR10 (the model's nominal arm with zero-offsets of 0.05°), its T-Mac
93 mm out on the flange (the drawing says 109) and turned on it, 0.02 mm and 0.002° of noise per axis,
written in the series' own format (';', decimal comma, joints in radians, X-Y-Z Euler degrees) —
without the ``measurement_std_*`` columns.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import typer
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from acquire.commands import fit as fit_command
from calib.measure.ipa_tracker import is_ipa_series, read_ipa_series
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from calib.robot.transforms import pose_to_matrix

ROOT = Path(__file__).resolve().parents[2]
UR10 = ROOT / "fixtures" / "robots" / "ur10.yaml"
NOISE_MM, NOISE_DEG = 0.02, 0.002
JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")


def _comma(v: float) -> str:
    return f"{v:.6f}".replace(".", ",")


def write_series(path: Path, k: int, seed: int = 0) -> np.ndarray:
    """A simulated IPA series of ``k`` rows without spreads; returns the true offsets (rad)."""
    rng = np.random.default_rng(seed)
    model = load_robot_model(UR10)
    chain = Chain(model)
    truth = chain.nominal.copy()
    offsets = np.radians(0.05 * rng.choice([-1.0, 1.0], 6))
    truth[:6] = offsets
    q = rng.uniform(-1.6, 1.6, (k, 6)) + [0.0, -1.57, 0.0, -1.57, 0.0, 0.0]
    rot, pos = chain.flange_pose(q, truth)
    tool = np.array([0.4, -0.3, 93.0])
    frame = Rotation.from_euler("xyz", [3.0, -2.0, 40.0], degrees=True).as_matrix()  # T-Mac on the flange
    b2s = np.linalg.inv(pose_to_matrix(np.array([400.0, -3200.0, 200.0]), np.radians([90.0, 1.0, -2.0])))
    xyz = np.einsum("ij,kj->ki", b2s[:3, :3], np.einsum("kij,j->ki", rot, tool) + pos) + b2s[:3, 3]
    xyz += rng.normal(0.0, NOISE_MM, xyz.shape)
    r_meas = b2s[:3, :3] @ rot @ frame
    r_meas = Rotation.from_rotvec(rng.normal(0.0, math.radians(NOISE_DEG), (k, 3))).as_matrix() @ r_meas
    euler = Rotation.from_matrix(r_meas).as_euler("XYZ", degrees=True)  # intrinsic X-Y-Z: Rx·Ry·Rz
    head = ["Timestamp", *JOINTS, "measurement_x", "measurement_y", "measurement_z", "measurement_rx", "measurement_ry",
            "measurement_rz"]
    lines = [";".join(head)]
    for i in range(k):
        lines.append(";".join(["2,02E+13", *map(_comma, q[i]), *map(_comma, xyz[i]), *map(_comma, euler[i])]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return offsets


def test_a_series_without_spreads_is_read_with_nan_spreads(tmp_path):
    path = tmp_path / "series.csv"
    write_series(path, 5)
    assert is_ipa_series(path)
    ds = read_ipa_series(path)
    assert ds.has_orientation and np.isnan(ds.std_mm).all() and np.isnan(ds.att_std_rad).all()


def test_the_noise_estimate_recovers_the_simulated_noise(tmp_path):
    from calib.fit.noise import estimate_noise

    path = tmp_path / "series.csv"
    write_series(path, 40, seed=1)
    ds = read_ipa_series(path)
    filled, doc = estimate_noise(load_robot_model(UR10), ds)
    est = doc["sensors"]["tracker"]
    assert 0.7 * NOISE_MM < est["position_mm"] < 1.5 * NOISE_MM, est
    assert 0.6 * NOISE_DEG < est["attitude_deg"] < 1.6 * NOISE_DEG, est
    assert np.all(filled.std_mm == est["position_mm"]) and np.all(filled.count == 1)
    np.testing.assert_allclose(np.degrees(filled.att_std_rad), est["attitude_deg"])
    assert estimate_noise(load_robot_model(UR10), filled) is None  # spreads stated: nothing to estimate


@pytest.mark.slow
def test_fit_reads_the_series_and_estimates_and_prints_its_noise(tmp_path):
    path, out = tmp_path / "series.csv", tmp_path / "r.json"
    write_series(path, 60)
    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        """remaster"""

    fit_command.register(app)
    res = CliRunner().invoke(app, ["fit", str(path), "--robot", str(UR10), "--method", "fast", "--draws", "150",
                                   "--random-configs", "20", "-o", str(out)])
    assert res.exit_code in (0, 1), res.output
    assert "read as an IPA tracker series" in res.output and "noise: the data state no spreads" in res.output
    doc = json.loads(out.read_text())
    est = doc["noise_estimate"]["sensors"]["tracker"]
    # The residual of the richest model has the sensor's noise in it, and no robot error here.
    assert 0.7 * NOISE_MM < est["position_mm"] < 1.5 * NOISE_MM, est
    assert 0.6 * NOISE_DEG < est["attitude_deg"] < 1.6 * NOISE_DEG, est
    weight = doc["attitude_weight"]["median_mm_per_rad"]
    assert weight == pytest.approx(est["position_mm"] / math.radians(est["attitude_deg"]), rel=0.05)
    assert "attitude rows weighted" in res.output
    # Its held-out check against the noise runs (no spread in the file is no reason to skip it).
    assert doc["diagnostics"]["error_budget"]["tracker"]["noise_mm"] == pytest.approx(est["position_mm"], rel=1e-6)
    assert doc["entered"]["heldout"]["scored_on"] == "cross-validation"
