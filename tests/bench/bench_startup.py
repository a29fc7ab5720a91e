"""Start-up time of the command line against ``python -c "import numpy"``, measured in the same run.

    python tests/bench/bench_startup.py [--repeat 7]

Target (issue 15): ``acquire --help`` and ``acquire status`` each within 3x the time of a fresh
interpreter importing numpy. Each figure is the median wall time of ``--repeat`` fresh processes,
run interleaved (numpy, help, status, numpy, …) so a load change hits all three alike.
``acquire status`` asks a real daemon: ``acquire daemon`` on the simulated cell (fake devices),
started here on a free loopback port and stopped at the end, so the figure includes the Zenoh
connection and the query round trip.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "acquire"))

from daemon_harness import CELL, DaemonProcess, NotifySocket, free_port, write_config  # noqa: E402

TARGET = 3.0


def wall(cmd: list[str], env: dict) -> float:
    """Seconds from spawn to exit of ``cmd`` (output discarded); raises if it fails."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          stdin=subprocess.DEVNULL, text=True)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}: {proc.stderr}")
    return dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7, help="fresh processes per command (median taken)")
    args = ap.parse_args()
    env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS="100")
    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        port = free_port()
        notify = NotifySocket()
        daemon = DaemonProcess(write_config(Path(tmp), port), notify)
        try:
            daemon.wait_ready(60)
            cmds = {
                'python -c "import numpy"': [py, "-c", "import numpy"],
                "acquire --help": [py, "-m", "acquire", "--help"],
                "acquire status": [py, "-m", "acquire", "status", "--cell", CELL, "--connect",
                                   f"tcp/127.0.0.1:{port}"],
            }
            for cmd in cmds.values():  # warm the page cache and the bytecode once
                wall(cmd, env)
            times: dict[str, list[float]] = {k: [] for k in cmds}
            for _ in range(args.repeat):
                for name, cmd in cmds.items():
                    times[name].append(wall(cmd, env))
        finally:
            daemon.stop()
            notify.close()
    med = {k: statistics.median(v) for k, v in times.items()}
    base = med['python -c "import numpy"']
    print(f"median of {args.repeat} fresh processes each, interleaved; load average {os.getloadavg()[0]:.2f}")
    ok = True
    for name, t in med.items():
        ratio = t / base
        line = f"{name:<28} {t * 1000:7.0f} ms  {ratio:5.2f}x import numpy"
        if name != 'python -c "import numpy"':
            verdict = ratio <= TARGET
            ok &= verdict
            line += f"  (target <= {TARGET:g}x: {'met' if verdict else 'MISSED'})"
        print(line)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
