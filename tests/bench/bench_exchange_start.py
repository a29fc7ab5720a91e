"""How long the real-time exchange process takes to be ready, quiet and beside four CPU hogs.

    python tests/bench/bench_exchange_start.py [--repeat 7] [--load]

An RSI or FRI commander's ``connect`` first starts its exchange process (``drivers/exchange.py``,
multiprocessing ``spawn``) and waits for it to be ready before it can answer the controller's
first packet; a controller that is already sending counts every unanswered cycle as late (a KR C4
stops its RSI program after its late limit). So this start time is a figure a cell PC's
integrator needs: start the PC side before the robot program, or allow for it.

Each figure is the median over ``--repeat`` fresh parent processes, each timing one
``RsiCommander.bind()`` (what ``connect`` waits for) and its breakdown (``ExchangeProcess.startup``):
interpreter and imports (spawn to the child's entry point: a fresh interpreter, the loop's
module and — for a script — the parent's main script, which spawn re-runs) and warm-up (real-time
set-up, the loop's first-call costs). Two parents, interleaved so a load change hits both:

- ``console script``: a script that imports the ``acquire`` entry point's target at its top, as
  the script pip writes does (the spawned child re-runs that import); the target is read from
  ``pyproject.toml`` (``--entry acquire.cli:main`` measures the former target);
- ``python -c``: a parent whose main module spawn does not re-run (pytest, ``python -m``).

``--load`` adds a phase with four CPU-bound processes (``loadgen.Hogs``) on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "bench"))

from loadgen import Hogs, load_average, wait_for_load  # noqa: E402

MEASURE = '''
import json, time

def measure(robot):
    # (imported here: a spawned child re-runs the script's top level, as it re-runs pip's
    # console script, which holds nothing but the entry point's import)
    from calib.robot.model import load_robot_model
    from drivers.base import JointLimits
    from drivers.kuka_rsi.commander import RsiCommander

    c = RsiCommander(JointLimits.from_model(load_robot_model(robot)), host="127.0.0.1", port=0, rt_priority=0)
    t0 = time.monotonic()
    c.bind()
    total = time.monotonic() - t0
    startup = dict(c._exchange.startup)
    c.close()
    return dict(startup, bind_s=total)
'''

CONSOLE_SCRIPT = MEASURE + '''
if __name__ == "__main__":
    import sys
    print(json.dumps(measure(sys.argv[1])))
'''


def entry_point() -> str:
    """The ``acquire`` console script's target in pyproject.toml, ``module:function``."""
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]["acquire"]

BARE = MEASURE + "import sys; print(json.dumps(measure(sys.argv[1])))\n"

ROBOT = ROOT / "fixtures" / "robots" / "kuka_kr6_r900_2.yaml"


def one(cmd: list[str], env: dict) -> dict:
    proc = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}: {proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def phase(label: str, parents: dict[str, list[str]], repeat: int, env: dict) -> None:
    runs: dict[str, list[dict]] = {k: [] for k in parents}
    for _ in range(repeat):
        for name, cmd in parents.items():
            runs[name].append(one(cmd, env))
    print(f"{label} (load average {load_average()}), median of {repeat} fresh parents each:")
    for name, rs in runs.items():
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        worst = max(r["bind_s"] for r in rs)
        print(f"  {name:<15} ready {med['bind_s'] * 1000:6.0f} ms (max {worst * 1000:5.0f})"
              f" = interpreter and imports {med['interpreter_and_imports_s'] * 1000:5.0f} ms"
              f" + warm-up {med['warm_up_s'] * 1000:4.0f} ms")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7, help="fresh parent processes per figure (median taken)")
    ap.add_argument("--load", action="store_true", help="add a phase beside four CPU-bound processes")
    ap.add_argument("--entry", default=entry_point(), help="the console script's target (default: pyproject's)")
    args = ap.parse_args()
    module, func = args.entry.split(":")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    with tempfile.TemporaryDirectory(prefix="bench-exchange-") as tmp:
        script = Path(tmp) / "acquire_like.py"
        script.write_text(f"from {module} import {func}  # noqa: F401 (as pip's console script)\n" + CONSOLE_SCRIPT)
        print(f"console script: from {module} import {func}")
        parents = {
            "console script": [sys.executable, str(script), str(ROBOT)],
            "python -c": [sys.executable, "-c", BARE, str(ROBOT)],
        }
        for cmd in parents.values():  # warm the page cache and the bytecode once
            one(cmd, env)
        phase("quiet", parents, args.repeat, env)
        if args.load:
            with Hogs(4):
                wait_for_load()
                phase("four CPU hogs", parents, args.repeat, env)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
