"""`acquire select` reads a configurations file, chooses m by IOOPS and writes them back out."""

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from acquire.cli import app
from calib.robot.model import load_robot_model
from calib.plan.poses import FILE_MAGIC, read_configurations

ROBOT = Path(__file__).resolve().parents[2] / "fixtures" / "robots" / "staubli_tx60.yaml"


def write_candidates(path: Path, n: int = 60) -> np.ndarray:
    model = load_robot_model(ROBOT)
    q = np.random.default_rng(0).uniform(model.lower_limits_rad * 0.8, model.upper_limits_rad * 0.8, (n, 6))
    lines = [FILE_MAGIC, f"# robot: {model.name}", "# seed: 0", "# sensor_origin_mm: 1500,0,500", "config,pose,branch,q1,q2,q3,q4,q5,q6"]
    lines += [f"{i},{i // 4},b{i % 4}," + ",".join(f"{v:.6f}" for v in np.degrees(row)) for i, row in enumerate(q)]
    path.write_text("\n".join(lines) + "\n")
    return q


def test_select_writes_the_chosen_configurations(tmp_path):
    cand = tmp_path / "cand.csv"
    q = write_candidates(cand)
    out = tmp_path / "chosen.csv"
    res = CliRunner().invoke(app, ["select", "--robot", str(ROBOT), "--candidates", str(cand), "-m", "20", "--index", "O6", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "IOOPS on O6" in res.output and "identifiable parameters" in res.output
    chosen = read_configurations(out, load_robot_model(ROBOT))
    assert len(chosen.configurations) == 20
    # Every chosen row is one of the candidates, unchanged.
    for c in chosen.configurations:
        assert np.allclose(c.q, q[c.config], atol=1e-7)


def test_select_rejects_an_unknown_index_and_too_many(tmp_path):
    cand = tmp_path / "cand.csv"
    write_candidates(cand, n=30)
    res = CliRunner().invoke(app, ["select", "--robot", str(ROBOT), "--candidates", str(cand), "-m", "5", "--index", "O7"])
    assert res.exit_code != 0 and "O7" in res.output
    res = CliRunner().invoke(app, ["select", "--robot", str(ROBOT), "--candidates", str(cand), "-m", "30"])
    assert res.exit_code != 0 and "cannot choose 30 of 30" in res.output
