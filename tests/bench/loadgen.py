"""Load that a busy cell PC puts on the real-time exchange, for the ``--load`` benches.

``Hogs``: CPU-bound processes (``while True: pass``), as other jobs on a shared machine.
``FitLoop``: the zero-offset fit of the shipped iiwa dataset, over and over, in a thread of the
calling process — the GIL, numpy and the garbage collector of the process that also talks to
the robot.

And what the real-time benches measure with: ``AnswerLog`` keeps every answer's arrival and
latency of a phase (polling the commander's ring, so a 10-minute phase loses nothing);
``StallProbe`` watches whether the machine itself stalls (a SCHED_FIFO process per CPU, above
the exchange's priority, that only sleeps 1 ms at a time): a late answer that falls in such a
stall was not the exchange's doing — no user process got that CPU then.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

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
        from calib.measure.dataset import read_csv
        from calib.fit.offsets import FitOptions
        from calib.robot.model import load_robot_model

        self.model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
        self.data = read_csv(ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv", self.model)
        self.options = FitOptions(n_draws=200)
        self.fits = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        from calib.fit.offsets import fit_offsets

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


class AnswerLog:
    """Every answer of a phase: ``poll()`` (every few seconds is enough: the ring holds 65536
    cycles) appends what the commander's ``answer_log()`` gained since the last poll.
    ``arrived``/``latency``: shape (n,), s; ``lost``: answers that left the ring unread."""

    def __init__(self, commander) -> None:
        self.commander = commander
        self.count = commander.answer_log()[0]
        self.lost = 0
        self._arrived: list[np.ndarray] = []
        self._latency: list[np.ndarray] = []

    def poll(self) -> None:
        count, arrived, latency = self.commander.answer_log()
        new = count - self.count
        if new <= 0:
            return
        kept = min(new, arrived.shape[0])
        self.lost += new - kept
        self._arrived.append(arrived[-kept:])
        self._latency.append(latency[-kept:])
        self.count = count

    @property
    def arrived(self) -> np.ndarray:
        return np.concatenate(self._arrived) if self._arrived else np.zeros(0)

    @property
    def latency(self) -> np.ndarray:
        return np.concatenate(self._latency) if self._latency else np.zeros(0)

    def figures(self, cycle_s: float) -> dict:
        """Answers, p50/p99/max latency (µs) and late answers (latency above ``cycle_s``),
        with each late answer's window ``late_windows`` (arrival, sent), shape (k, 2), s."""
        lat, arr = self.latency, self.arrived
        if lat.shape[0] == 0:
            lat = arr = np.zeros(1)
        late = lat > cycle_s
        p50, p99 = np.percentile(lat, [50, 99])
        return {
            "cycles": int(self.latency.shape[0]), "p50_us": p50 * 1e6, "p99_us": p99 * 1e6,
            "max_us": lat.max() * 1e6, "late_log": int(late.sum()), "lost": self.lost,
            "late_windows": np.stack([arr[late], arr[late] + lat[late]], axis=1),
        }


def _probe(conn, cpu: int, priority: int, period_s: float, threshold_s: float) -> None:
    """Child of ``StallProbe``: pinned to ``cpu``, SCHED_FIFO ``priority``; sleeps ``period_s`` at
    a time and records (start, end) of every wake-up more than ``threshold_s`` late, on both
    clocks (monotonic, wall)."""
    import gc

    os.sched_setaffinity(0, {cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        scheduling = f"SCHED_FIFO {priority}"
    except (PermissionError, OSError) as exc:
        scheduling = f"normal priority ({exc})"
    gc.disable()
    stalls: list[tuple[float, float, float, float]] = []
    wakes = 0
    conn.send(scheduling)
    prev = time.monotonic()
    while not conn.poll():
        time.sleep(period_s)
        now = time.monotonic()
        wakes += 1
        if now - prev - period_s > threshold_s:
            wall = time.time()
            stalls.append((prev, now, wall - (now - prev), wall))
        prev = now
    conn.send((wakes, stalls))


class StallProbe:
    """Machine stalls while the context is open: one process per CPU, pinned, SCHED_FIFO at
    ``priority`` (above the exchange's 50 and the fake controller's 60, so neither can delay
    it), sleeping ``period_s`` at a time. A wake-up more than ``threshold_s`` late means that
    CPU ran nothing of ours' priority for that long: the kernel or the hypervisor (a VM's vCPU
    not scheduled) held it. ``stalls``: (cpu, start, end) on the ``clock`` asked for."""

    def __init__(self, priority: int = 70, period_s: float = 0.001, threshold_s: float = 0.002) -> None:
        self.priority, self.period_s, self.threshold_s = priority, period_s, threshold_s
        self._procs: list = []
        self.scheduling = "not started"
        self.wakes = 0
        self._stalls: list[tuple[int, float, float, float, float]] = []

    def __enter__(self) -> "StallProbe":
        ctx = mp.get_context("spawn")
        for cpu in sorted(os.sched_getaffinity(0)):
            parent, child = ctx.Pipe()
            p = ctx.Process(target=_probe, args=(child, cpu, self.priority, self.period_s, self.threshold_s), daemon=True)
            p.start()
            self._procs.append((cpu, p, parent))
        self.scheduling = ", ".join(sorted({conn.recv() for _, _, conn in self._procs}))
        return self

    def __exit__(self, *exc) -> None:
        for _, _, conn in self._procs:
            conn.send("stop")
        for cpu, p, conn in self._procs:
            if conn.poll(10):
                wakes, stalls = conn.recv()
                self.wakes += wakes
                self._stalls += [(cpu, *s) for s in stalls]
            p.join(5)

    def stalls(self, clock: str = "wall") -> np.ndarray:
        """Shape (k, 3): cpu, start, end (s) on the ``"wall"`` or ``"monotonic"`` clock."""
        col = {"monotonic": 1, "wall": 3}[clock]
        return np.array([(s[0], s[col], s[col + 1]) for s in self._stalls]).reshape(-1, 3)

    def summary(self, late_windows: np.ndarray, clock: str = "wall") -> str:
        """One line: the stalls seen and how many of the late answers (windows (arrival, sent),
        shape (k, 2), on ``clock``) fall in one (overlap, with 1 ms either side)."""
        st = self.stalls(clock)
        longest = (st[:, 2] - st[:, 1]).max() * 1e3 if st.shape[0] else 0.0
        inside = 0
        for a, b in late_windows:
            inside += bool(np.any((st[:, 1] <= b + 1e-3) & (st[:, 2] >= a - 1e-3)))
        return (f"machine stalls seen by the probe ({self.scheduling}, each CPU, {self.period_s * 1e3:g} ms sleeps, "
                f"> {self.threshold_s * 1e3:g} ms late, {self.wakes} wake-ups): {st.shape[0]}, longest "
                f"{longest:.1f} ms; late answers inside one: {inside} of {late_windows.shape[0]}")


def shuttle(commander, targets, seconds: float, answers: AnswerLog, *, speed: float, move_timeout: float,
            settle_timeout: float) -> tuple[int, str | None]:
    """Move the robot back and forth between ``targets`` (rad) for ``seconds``, as a sequencer
    would (move, then settle to 0.05° for 50 ms), polling ``answers`` after each move.
    ``(moves, fault)``: a driver error ends it and comes back as text — reported, not hidden."""
    from drivers.errors import DriverError

    t_end = time.monotonic() + seconds
    moves = 0
    try:
        while time.monotonic() < t_end:
            commander.move_to(targets[moves % len(targets)], speed=speed, timeout=move_timeout)
            commander.wait_settled(np.radians(0.05), 0.05, settle_timeout)
            moves += 1
            answers.poll()
    except DriverError as exc:
        return moves, f"{type(exc).__name__}: {exc}"
    finally:
        answers.poll()
    return moves, None
