"""Between the last measurement and the result only the fit runs: its imports are made while the
robot moves (``acquire.run.fitting.preload_fit``), and ``acquire run --fake`` stops the simulated
cell as soon as the run measures no more (``wait_for_end``'s ``on_measured``)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from acquire.commands.run import wait_for_end

ROOT = Path(__file__).resolve().parents[2]

# A fresh interpreter (pytest has every module imported already): the example plan's fit (its
# robot has dynamics, so the compliance candidates; attitude rows, as its motion-capture rigid
# body gives) on 12 simulated configurations, after ``preload_fit``.
SCRIPT = r"""
import json, sys
import numpy as np
from acquire.plan.schema import load_plan
from acquire.run.fitting import _fit_run_auto, preload_fit
from calib.robot.kinematics import Chain
from tests.calib.pose_sim import BASE2SENSOR, PoseCell, measure_poses, perturb
lp = load_plan(sys.argv[1])
preload_fit(lp).join()
before = set(sys.modules)
from calib.fit.offsets import FitOptions
model = lp.model
chain = Chain(model)
rng = np.random.default_rng(3)
lo, hi = model.lower_limits_rad, model.upper_limits_rad
q = lo + (hi - lo) * rng.uniform(0.15, 0.85, (12, chain.n))
truth = perturb(chain, [f"{a}.offset" for a in model.axis_names], rng, 0.0, 0.1)
cal = measure_poses(chain, q, PoseCell(truth, np.eye(3), BASE2SENSOR, 0.03, 0.01), rng, sensor="mocap")
doc, _, _ = _fit_run_auto(__import__("pathlib").Path(sys.argv[2]) / "run.mcap", model, cal, None,
                          FitOptions(n_draws=200), lp.plan.fit, 20)
print(json.dumps({"chosen": doc["model_choice"]["chosen"], "new": sorted(set(sys.modules) - before)}))
"""


@pytest.mark.slow  # a guard of the main job's fit share (a fresh interpreter and a whole fit): tests/bench/README.md
def test_after_the_preload_the_end_of_run_fit_imports_nothing(tmp_path):
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(ROOT / "fixtures/plans/example.yaml"), str(tmp_path)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert "compliance" in got["chosen"]  # the path the example's run takes (fit.compliance)
    fit_modules = [m for m in got["new"] if m.split(".")[0] in ("calib", "acquire", "scipy")]
    assert fit_modules == [], f"the fit imported these after preload_fit: add them to FIT_MODULES: {fit_modules}"


class _Run:
    """A run's control surface as ``wait_for_end`` sees it: it measures no more after two waits
    and ends after four."""

    def __init__(self) -> None:
        self.measurements_over = threading.Event()
        self.waits = 0

    def wait(self, timeout: float):
        self.waits += 1
        if self.waits == 2:
            self.measurements_over.set()
        if self.waits < 4:
            raise TimeoutError
        return "summary"


def test_the_simulation_ends_once_as_soon_as_the_run_measures_no_more():
    run, calls = _Run(), []
    assert wait_for_end(run, on_measured=lambda: calls.append(run.waits)) == "summary"
    assert calls == [2]  # at the first look after the measurements, while the run still fitted; once
    assert wait_for_end(_Run()) == "summary"  # (nothing to stop: acquire verify)
