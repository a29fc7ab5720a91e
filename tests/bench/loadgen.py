"""Load that a busy cell PC puts on the real-time exchange, for the ``--load`` benches.

``Hogs``: CPU-bound processes (``while True: pass``), as other jobs on a shared machine.
``FitLoop``: the zero-offset fit of the shipped iiwa dataset, over and over, in a thread of the
calling process — the GIL, numpy and the garbage collector of the process that also talks to
the robot.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class Hogs:
    """``n`` CPU-bound child processes while the context is open."""

    def __init__(self, n: int = 4) -> None:
        self.n = n
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> "Hogs":
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(self.n)]
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait(5)


class FitLoop:
    """Fits the shipped iiwa calibration dataset in a loop in a daemon thread; counts fits."""

    def __init__(self) -> None:
        from calib.dataset import read_csv
        from calib.fit import FitOptions
        from calib.model import load_robot_model

        self.model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
        self.data = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", self.model)
        self.options = FitOptions(n_draws=200)
        self.fits = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        from calib.fit import fit_offsets

        while not self._stop.is_set():
            fit_offsets(self.model, self.data, self.options)
            self.fits += 1

    def __enter__(self) -> "FitLoop":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(120)


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def wait_for_load(target: float = 3.0, timeout: float = 20.0) -> None:
    """Give the hogs time to raise the load average toward ``target`` (it lags by design)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if float(Path("/proc/loadavg").read_text().split()[0]) >= target:
                return
        except (OSError, ValueError):
            return
        time.sleep(1.0)
