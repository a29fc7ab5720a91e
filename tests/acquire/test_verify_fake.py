"""Prove it in the cell: calibrate against the simulated cell, enter the result into its
controller as an operator does (``acquire sim``: ``enter``, ``save``), run ``acquire verify`` on
fresh configurations, and find the predicted improvement within its interval. The robot left as
found fails the same verification. Real sockets, real protocols, two whole fake runs (~2 min)."""

from __future__ import annotations

import json
import os
import queue
import socket
import subprocess
import threading
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.cli import app
from acquire.plan.schema import load_plan
from acquire.record.recorder import read_run

from run_helpers import ROOT, acquire_cmd, simulated_run, small_plan, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(400)]
ROBOT = ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def enter_in_the_simulated_controller(result, cell_file, saved) -> list[str]:
    """``acquire sim`` as the operator runs it: ``enter`` the result, ``save`` the cell; its answers."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(acquire_cmd("sim", "--config", str(cell_file), "--fri-port", str(free_udp_port()),
                                        "--duration", "120"), cwd=ROOT, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x.rstrip("\n")) for x in proc.stdout], daemon=True).start()
    seen: list[str] = []
    try:
        def wait_for(prefix: str) -> None:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    seen.append(lines.get(timeout=0.2))
                except queue.Empty:
                    continue
                if seen[-1].startswith(prefix):
                    return
            raise AssertionError("acquire sim printed:\n" + "\n".join(seen))

        wait_for("running for up to")
        proc.stdin.write(f"enter {result}\nsave {saved}\n")
        proc.stdin.flush()
        wait_for("saved ")
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        proc.stdin.close()
        proc.stdout.close()
    return seen


def test_entered_offsets_improve_the_simulated_robot_as_predicted(tmp_path):
    plan = small_plan(tmp_path, n=10, fit={"method": "fast", "compliance": False})
    lp = load_plan(plan)
    with simulated_run(lp, fit=False) as (rc, sim):  # the calibration run
        rc.start()
        cal = wait_for_run(rc)
    assert cal.state == "finished" and cal.measured >= 12, cal.reason
    result = cal.log_path.with_name("result.json")
    fit = CliRunner().invoke(app, ["fit", str(cal.log_path), "--robot", str(ROBOT), "--method", "fast",
                                   "--link-tolerance", "none", "-o", str(result)])
    assert fit.exit_code == 0, fit.output

    cell = tmp_path / "cell-entered.yaml"
    said = enter_in_the_simulated_controller(result, ROOT / "fixtures" / "sim" / "default.yaml", cell)
    assert any(line.startswith(f"entered from {result}") for line in said), said

    res = CliRunner().invoke(app, ["verify", str(plan), "--result", str(result), "--fake", "--cell", str(cell),
                                   "--poses", "10"])
    assert res.exit_code == 0, res.output
    assert "verdict: as predicted" in res.output
    (out,) = [p for p in (tmp_path / "runs").rglob("verify.json")]
    doc = json.loads(out.read_text())
    measured, lo_hi = doc["measured"]["improvement_mm"]["value"], doc["predicted"]["interval_for_this_run"]
    assert lo_hi[0] <= measured <= lo_hi[1] and measured > 1.0  # millimetres better, as predicted
    assert doc["entry_matches_result"]
    assert doc["after"]["mean_mm"] < 0.4 * doc["before"]["calibration"]["mean_mm"]
    assert out.with_name("verify.html").stat().st_size > 2000
    # fresh configurations: the region's, none of the calibration's
    fresh = {s["config_id"] for s in read_run(doc["log"]).samples}
    assert fresh and all(c.startswith("v") for c in fresh)
    cal_q = np.array([s["q_target_deg"] for s in read_run(cal.log_path).samples])
    new_q = np.array([s["q_target_deg"] for s in read_run(doc["log"]).samples])
    assert np.min(np.abs(new_q[:, None, :] - cal_q[None, :, :]).max(axis=-1)) > 1e-3

    # the robot as found (the calibration's own log, nothing entered) fails the same verification
    res = CliRunner().invoke(app, ["verify", str(plan), "--result", str(result), "--log", str(cal.log_path)])
    assert res.exit_code == 3, res.output
    assert "verdict: worse than predicted" in res.output
