"""Scale of the plant station with real fake runs: cell daemons behind one router, each running
a short plan on its simulated cell, one station archiving all of them.

    python tests/bench/bench_station_runs.py [--cells 50] [--wave 10] [--poses 1] [--time-scale 3]

The station runs as its own process (``acquire station``, the router, on a loopback port). Each
cell is a real ``acquire daemon`` process (``fake:`` its simulated cell, ``site: bench``, Zenoh
peer connected to the station's router, the station listed with ``allow: [archive]``). The bench
is an operator client on the same router: it starts each daemon's run with a short inline plan
(``--poses`` generated poses → a few configurations; too few for a fit, so a run ends without a
result — what is measured is the archive, not the fit) and follows the runs' status keys.
2 cores cannot run 50 daemons and their real-time runs at once: cells start in waves of
``--wave`` (a wave's daemons start together, run together, and are stopped once their runs are
confirmed). Mid-way the station is SIGKILLed and restarted, and one daemon is SIGSTOPped for
longer than Zenoh's lease (its link cut: its liveliness token drops) while its run is pending,
then continued. A daemon is stopped once its run is confirmed. Printed: runs started vs.
archived, bytes, seconds from a run's end (its folder's newest file) to ``.archived`` on the
cell (median, max), duplicates, every stored file
re-verified against its manifest, the station's peak RSS, the bench's CPU seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.acquire.daemon_harness import (NotifySocket, free_port, scram)  # noqa: E402
from tests.acquire.run_helpers import small_plan  # noqa: E402

SITE = "bench"
TERMINAL = ("finished", "aborted", "failed")
OPERATOR = "op-7Qm2vX9kLp4RtZ8wYc3NbF6hJd"


def _vm(pid: int, field: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _restore(cell: "Cell", t0: float, cut_cell: list) -> None:
    cell.proc.send_signal(signal.SIGCONT)
    cut_cell[0] = None
    print(f"cell {cell.name} continued (link restored) at {time.monotonic() - t0:.0f} s", flush=True)


class Cell:
    """One ``acquire daemon`` process with its simulated cell."""

    def __init__(self, tmp: Path, i: int, router: str, station_token: str, args) -> None:
        self.name = f"c{i:03d}"
        self.folder = tmp / "cells" / self.name
        self.folder.mkdir(parents=True)
        cfg = {
            "cell": self.name, "site": SITE, "robot_serial": f"R{i:03d}",
            "state_dir": str(self.folder / "state"),
            "fake": {"time_scale": args.time_scale, "seed": i},
            "allow_inline_plans": True,
            "zenoh": {"mode": "peer", "listen": [], "connect": [router]},
            "auth": {"clients": [
                {"name": "operator", "scram": scram(OPERATOR), "allow": ["observe", "read", "control", "motion"]},
                {"name": "station", "scram": scram(station_token), "allow": ["archive"]}]},
        }
        path = self.folder / "daemon.yaml"
        path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        path.chmod(0o600)
        self.notify = NotifySocket()
        env = dict(os.environ, PYTHONPATH=str(ROOT), NOTIFY_SOCKET=self.notify.name, WATCHDOG_USEC="5000000")
        env.pop("JOURNAL_STREAM", None)
        self._log = open(self.folder / "daemon.log", "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "acquire", "daemon", "--config", str(path)], cwd=ROOT,
                                     env=env, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT)
        self.run_id: str | None = None

    def ready(self) -> bool:
        return any(m.get("READY") == "1" for m in self.notify.all_fields())

    def runs_dir(self) -> Path:
        return self.folder / "state" / "runs"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()
        self.notify.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, default=10)
    ap.add_argument("--wave", type=int, default=10, help="daemons running at once")
    ap.add_argument("--poses", type=int, default=1, help="generated candidate poses of the short plan")
    ap.add_argument("--time-scale", type=float, default=3.0)
    ap.add_argument("--timeout", type=float, default=900)
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args()

    from acquire.live.bus import Bus, BusError
    from acquire.daemon.control import BadRequest, ControlClient, ControlError, Refused
    from acquire.station.archive import Archive
    from acquire.daemon.tokens import new_token, write_token_file

    tmp = Path(tempfile.mkdtemp(prefix="bench-station-runs-"))
    token = new_token()
    write_token_file(tmp / "station.token", token)
    router = f"tcp/127.0.0.1:{free_port()}"
    cells_cfg = "".join(f"  {SITE}/c{i:03d}: {{robot_serial: R{i:03d}}}\n" for i in range(args.cells))
    (tmp / "station.yaml").write_text(
        f"archive: archive\ntoken_file: station.token\npoll_s: 1\nchunk_bytes: 1048576\n"
        f"zenoh: {{mode: router, listen: ['{router}'], connect: []}}\ncells:\n{cells_cfg}")
    plan_text = small_plan(tmp, n=args.poses, name="short.yaml").read_text()
    env = dict(os.environ, PYTHONPATH=str(ROOT))

    def start_station() -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "acquire", "station", "--config", str(tmp / "station.yaml")],
                                env=env, stdout=subprocess.DEVNULL, stderr=open(tmp / "station.log", "a"))

    station = start_station()
    for attempt in range(60):  # the station's router takes seconds to listen on a loaded machine
        try:
            bus = Bus("bench", site=SITE, config={"mode": "client", "connect": [router]})
            break
        except BusError:
            if attempt == 59:
                station.kill()
                raise
            time.sleep(1)
    ended: dict[tuple[str, str], float] = {}
    states: dict[tuple[str, str], str] = {}
    lock = threading.Lock()

    def on_status(key: str, payload: bytes) -> None:
        parts = key.split("/")  # remaster/bench/<cell>/run/<run-id>/status
        try:
            state = json.loads(payload).get("state")
        except ValueError:
            return
        with lock:
            if state in TERMINAL and (parts[2], parts[4]) not in ended:
                ended[(parts[2], parts[4])] = time.monotonic()
                states[(parts[2], parts[4])] = state

    bus.subscribe(f"remaster/{SITE}/*/run/*/status", on_status)
    confirmed: dict[tuple[str, str], float] = {}
    peaks = [0]
    t0 = time.monotonic()
    cells: list[Cell] = []
    killed_station = cut_done = False
    cut_cell: list = [None]
    n_waves = (args.cells + args.wave - 1) // args.wave

    def poll(active: list[Cell]) -> None:
        peaks[-1] = max(peaks[-1], _vm(station.pid, "VmHWM"))
        for c in cells:
            folder = c.runs_dir() / c.run_id if c.run_id else None
            if folder and (c.name, c.run_id) not in confirmed and (folder / ".archived").exists():
                now = time.time()
                last = max(p.stat().st_mtime for p in folder.iterdir() if not p.name.startswith("."))
                confirmed[(c.name, c.run_id)] = now - last   # the run's last byte written → confirmed
                if c.proc.poll() is None and c is not cut_cell[0]:
                    c.proc.terminate()   # done: free the cores for the others (stop() waits for it)

    def waves() -> None:
        nonlocal station, killed_station, cut_done
        for w in range(n_waves):
            wave = [Cell(tmp, i, router, token, args) for i in range(w * args.wave, min(args.cells, (w + 1) * args.wave))]
            cells.extend(wave)
            deadline = time.monotonic() + 180
            while not all(c.ready() for c in wave) and time.monotonic() < deadline:
                if any(c.proc.poll() is not None for c in wave):
                    bad = next(c for c in wave if c.proc.poll() is not None)
                    raise SystemExit(f"daemon {bad.name} exited: {(bad.folder / 'daemon.log').read_text()[-2000:]}")
                time.sleep(0.2)
            for c in wave:
                op = ControlClient(bus.session, c.name, site=SITE, client="operator", token=OPERATOR)
                text = plan_text.replace("cell: example", f"cell: {c.name}", 1)
                for attempt in range(10):
                    try:
                        c.run_id = op.call("start", {"plan_text": text}, timeout=10)["run_id"]
                        break
                    except (BadRequest, Refused) as exc:
                        raise SystemExit(f"{c.name}: could not start a run: {exc}") from None
                    except ControlError as exc:
                        last = exc
                        time.sleep(1)
                else:
                    raise SystemExit(f"{c.name}: could not start a run: {last}")
            print(f"wave {w + 1}/{n_waves}: {len(wave)} daemons ready, runs started at {time.monotonic() - t0:.0f} s",
                  flush=True)
            cut = wave[0] if w == n_waves // 2 and not cut_done else None
            cut_cell[0] = cut
            while time.monotonic() - t0 < args.timeout:
                poll(wave)
                with lock:
                    done_runs = {k for k in ended}
                if cut is not None and (cut.name, cut.run_id) in done_runs:
                    # The link cut: freeze the daemon past Zenoh's lease (10 s), then let it go on.
                    cut.proc.send_signal(signal.SIGSTOP)
                    print(f"cell {cut.name} frozen (link cut) at {time.monotonic() - t0:.0f} s", flush=True)
                    threading.Timer(15, _restore, (cut, t0, cut_cell)).start()  # the bench keeps polling meanwhile
                    cut, cut_done = None, True
                in_wave = sum((c.name, c.run_id) in confirmed for c in wave)
                if not killed_station and w == n_waves // 2 and 0 < in_wave < len(wave):
                    station.kill()
                    station.wait()
                    print(f"station killed at {time.monotonic() - t0:.0f} s after {len(confirmed)} runs confirmed",
                          flush=True)
                    time.sleep(2)
                    peaks.append(0)
                    station = start_station()
                    killed_station = True
                if all((c.name, c.run_id) in confirmed for c in wave):
                    break
                time.sleep(0.2)
            for c in wave:
                c.stop()

    try:
        waves()
    finally:
        for c in cells:
            c.stop()
        if sys.exc_info()[0] is not None and station.poll() is None:
            station.kill()
    elapsed = time.monotonic() - t0
    station.terminate()
    try:
        station.wait(timeout=30)
    except subprocess.TimeoutExpired:
        station.kill()
    bus.close()

    archive = Archive(tmp / "archive")
    manifests = archive.manifests()
    ids = [(m["cell"], m["run_id"]) for m in manifests]
    lat = np.array(list(confirmed.values()))
    bad = sum(bool(archive.verify(m)) for m in manifests)
    total = sum(f["bytes"] for m in manifests for f in m["files"])
    started = [(c.name, c.run_id) for c in cells]
    lost = [k for k in started if k not in set(ids)]
    kinds: dict[str, int] = {}
    for s in states.values():
        kinds[s] = kinds.get(s, 0) + 1
    cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"cells {args.cells} in {n_waves} waves of ≤{args.wave}; runs started {len(started)}, terminal "
          f"status seen on the bus {len(ended)} {kinds}, confirmed on the cell {len(confirmed)}, in the archive {len(ids)}, duplicates "
          f"{len(ids) - len(set(ids))}, lost {len(lost)}, failing re-verification {bad}")
    if len(lat):
        print(f"bytes archived {total / 1e6:.2f} MB ({total / max(1, len(ids)) / 1e3:.0f} kB per run) in {elapsed:.0f} s "
              f"wall; run's last byte → confirmed s: median {np.median(lat):.1f}, max {lat.max():.1f}")
    print(f"station peak RSS per process (restarts split it): {', '.join(f'{p / 1024:.0f} MB' for p in peaks)}")
    print(f"CPU of all child processes: {cpu.ru_utime + cpu.ru_stime:.0f} s; killed station {killed_station}, "
          f"link cut {cut_done}")
    if args.keep:
        print(f"kept {tmp}")
    else:
        shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
