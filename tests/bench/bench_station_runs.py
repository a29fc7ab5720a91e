"""Scale of the plant station with real fake runs: cell daemons behind the site's router, each
running a short plan on its simulated cell to a fitted result, one station archiving all of them.

    nice -n 10 python tests/bench/bench_station_runs.py --cells 20 --wave 20 [--poses 8] [--time-scale 3]

The site's router (``acquire router``) and the station (``acquire station``, a client of the
router) run as processes of their own, linked by the router's Unix socket. Each cell is a real ``acquire daemon``
process (``fake:`` its simulated cell, ``site: bench``, Zenoh peer connected to the router, the
station listed with ``allow: [archive]``, ``WATCHDOG_USEC`` of the unit's ``WatchdogSec=10s``).
The bench is an operator client of the same router: it starts each daemon's run with a short
inline plan (``--poses`` generated poses: 8 → 14 configurations, enough for the ``fast`` fit and
a reference; ``--poses 1`` measures the archive alone, without a result) and follows the runs'
status keys. Cells start in waves of ``--wave`` (a wave's daemons start one after another, each
once the previous is ready — ``--no-stagger``: together —, run together, and each is stopped once
its run is confirmed); ``--wave`` = ``--cells`` runs them all at once. A daemon that does not come
up, or a run that does not start within 2 minutes, is counted and left out.

Injected mid-way (in the middle wave): the station is SIGKILLed once the first run of the wave is
confirmed and restarted; one daemon is SIGSTOPped as its run ends, for ``--freeze-s`` (past
Zenoh's 10 s lease: its link cut, its liveliness token dropped), then continued; one archived
``result.json`` gets a digit changed (the station's scrub, every ``scrub_hours`` ≈ 22 s here,
must find it, quarantine it and fetch it again from its cell, which is kept running until then).

Printed: the load average beside the run (start, highest, end); runs started vs. archived, with
a fitted result, duplicates, lost, every stored file re-verified against its manifest; seconds
from a run's end (its folder's newest file) to ``.archived`` on the cell (p50, max); when the
corrupted copy was repaired; the station's and the router's peak RSS, open descriptors and
threads; each daemon's longest gap between watchdog pings (over 10 s: systemd would restart
it); the station log's warnings by kind; the CPU seconds of all processes.
"""

from __future__ import annotations

import argparse
import json
import os
import re
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

from tests.acquire.daemon_harness import (NotifySocket, scram)  # noqa: E402
from tests.acquire.run_helpers import small_plan  # noqa: E402

SITE = "bench"
TERMINAL = ("finished", "aborted", "failed")
OPERATOR = "op-7Qm2vX9kLp4RtZ8wYc3NbF6hJd"
#: The daemon unit's WatchdogSec (systemd/remaster.service), µs.
WATCHDOG_USEC = 10_000_000
#: The station's scrub interval in the bench, hours (≈ 22 s).
SCRUB_HOURS = 0.006


def _vm(pid: int, field: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _fds(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return 0


class Peaks:
    """Peak RSS (kB), open descriptors and threads of one process, sampled by ``sample``."""

    def __init__(self) -> None:
        self.rss = self.fds = self.threads = 0

    def sample(self, pid: int) -> None:
        self.rss = max(self.rss, _vm(pid, "VmHWM"))
        self.fds = max(self.fds, _fds(pid))
        self.threads = max(self.threads, _vm(pid, "Threads"))

    def __str__(self) -> str:
        return f"{self.rss / 1024:.0f} MB, {self.fds} fds, {self.threads} threads"


def _restore(cell: "Cell", t0: float, cut_cell: list) -> None:
    cell.proc.send_signal(signal.SIGCONT)
    cut_cell[0] = None
    print(f"cell {cell.name} continued (link restored) at {time.monotonic() - t0:.0f} s", flush=True)


def _corrupt(path: Path) -> None:
    """Change one digit of ``path`` (an archived ``result.json``) in place."""
    data = bytearray(path.read_bytes())
    i = next(i for i, b in enumerate(data) if chr(b).isdigit())
    data[i] = ord("7") if data[i] != ord("7") else ord("3")
    path.write_bytes(bytes(data))


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
        env = dict(os.environ, PYTHONPATH=str(ROOT), NOTIFY_SOCKET=self.notify.name, WATCHDOG_USEC=str(WATCHDOG_USEC))
        env.pop("JOURNAL_STREAM", None)
        self._log = open(self.folder / "daemon.log", "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "acquire", "daemon", "--config", str(path)], cwd=ROOT,
                                     env=env, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT)
        self.run_id: str | None = None
        self.frozen: tuple[float, float] | None = None   # (from, to) monotonic: pings cannot come then

    def ready(self) -> bool:
        return any(m.get("READY") == "1" for m in self.notify.all_fields())

    def runs_dir(self) -> Path:
        return self.folder / "state" / "runs"

    def longest_ping_gap(self) -> float:
        """Longest time between two watchdog pings (s), the bench's own freeze taken out."""
        with self.notify._cond:
            times = [m.t for m in self.notify.messages if m.fields.get("WATCHDOG") == "1"]
        gaps = np.diff(times) if len(times) > 1 else np.zeros(1)
        if self.frozen is not None and len(times) > 1:
            a, b = self.frozen
            gaps = np.array([g for t, g in zip(times[1:], gaps) if not (t - g <= b and t >= a)] or [0.0])
        return float(gaps.max())

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        if not self._log.closed:
            self._log.close()
            self.notify.close()


def _warnings_by_kind(log_text: str) -> dict[str, int]:
    """The station log's WARNING/ERROR lines, counted by their text with names and numbers taken out."""
    kinds: dict[str, int] = {}
    for line in log_text.splitlines():
        if " WARNING " not in line and " ERROR " not in line and not line.startswith(("WARNING", "ERROR")):
            continue
        k = re.sub(r"c\d{3}|R\d{3}|r?-?\d[\w.:-]*", "#", line.split(":", 1)[-1]).strip()[:90]
        kinds[k] = kinds.get(k, 0) + 1
    return kinds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, default=10)
    ap.add_argument("--wave", type=int, default=10, help="daemons running at once")
    ap.add_argument("--poses", type=int, default=8, help="generated candidate poses of the short plan (8: 14 "
                                                         "configurations and a fitted result; 1: no result)")
    ap.add_argument("--time-scale", type=float, default=3.0)
    ap.add_argument("--freeze-s", type=float, default=25.0, help="how long one daemon is SIGSTOPped")
    ap.add_argument("--timeout", type=float, default=1800)
    ap.add_argument("--stagger", action=argparse.BooleanOptionalAction, default=True,
                    help="start a wave's daemons one after another (each once the previous is ready)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args()

    from acquire.live.bus import Bus, BusError
    from acquire.daemon.control import BadRequest, ControlClient, ControlError, Refused
    from acquire.station.archive import Archive
    from acquire.station.history import load_history, robots
    from acquire.daemon.tokens import new_token, write_token_file

    print(f"uptime at start: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}", flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench-station-runs-"))
    token = new_token()
    write_token_file(tmp / "station.token", token)
    router = f"unixsock-stream/{tmp / 'router.sock'}"   # the station's link: never tcp/ (docs/how-to/station.md)
    (tmp / "router.yaml").write_text(f"listen: ['{router}']\n")
    cells_cfg = "".join(f"  {SITE}/c{i:03d}: {{robot_serial: R{i:03d}}}\n" for i in range(args.cells))
    (tmp / "station.yaml").write_text(
        f"archive: archive\ntoken_file: station.token\npoll_s: 30\nchunk_bytes: 1048576\nscrub_hours: {SCRUB_HOURS}\n"
        f"zenoh: {{mode: client, listen: [], connect: ['{router}']}}\ncells:\n{cells_cfg}")
    plan_text = small_plan(tmp, n=args.poses, name="short.yaml",
                           fit={"method": "fast", "compliance": False}).read_text()
    env = dict(os.environ, PYTHONPATH=str(ROOT))

    def start(what: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "acquire", what, "--config", str(tmp / f"{what}.yaml")],
                                env=env, stdout=subprocess.DEVNULL, stderr=open(tmp / f"{what}.log", "a"))

    router_proc = start("router")
    for attempt in range(60):  # the router takes seconds to listen on a loaded machine
        try:
            bus = Bus("bench", site=SITE, config={"mode": "client", "connect": [router]})
            break
        except BusError:
            if attempt == 59:
                router_proc.kill()
                raise
            time.sleep(1)
    station = start("station")
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
    station_peaks, router_peaks = [Peaks()], Peaks()
    load = [os.getloadavg()[0]]
    t0 = time.monotonic()
    cells: list[Cell] = []
    failed_start: list[str] = []
    killed_station = cut_done = False
    cut_cell: list = [None]
    victim: dict = {}   # the corrupted copy: cell, manifest, t, repaired
    archive = Archive(tmp / "archive")
    n_waves = (args.cells + args.wave - 1) // args.wave

    def poll() -> None:
        station_peaks[-1].sample(station.pid)
        router_peaks.sample(router_proc.pid)
        load.append(os.getloadavg()[0])
        for c in cells:
            folder = c.runs_dir() / c.run_id if c.run_id else None
            if folder and (c.name, c.run_id) not in confirmed and (folder / ".archived").exists():
                now = time.time()
                last = max(p.stat().st_mtime for p in folder.iterdir() if not p.name.startswith("."))
                confirmed[(c.name, c.run_id)] = now - last   # the run's last byte written → confirmed
        if "manifest" in victim and "repaired" not in victim and not archive.verify(victim["manifest"]):
            victim["repaired"] = time.monotonic() - t0
            print(f"corrupted copy of {victim['manifest']['run_id']} repaired at {victim['repaired']:.0f} s "
                  f"({victim['repaired'] - victim['t']:.0f} s after the damage)", flush=True)
        for c in cells:   # done: free the cores for the others (stop() waits for it)
            if ((c.name, c.run_id) in confirmed and c.proc.poll() is None and c is not cut_cell[0]
                    and not (victim.get("cell") is c and "repaired" not in victim)):
                c.proc.terminate()

    def corrupt(c: Cell) -> None:
        """Once ``c``'s run is archived (and the station restarted), change a digit of its result.json."""
        m = next((m for m in archive.manifests() if m["run_id"] == c.run_id), None)
        if m is None:
            return
        if not any(f["name"] == "result.json" for f in m["files"]):
            victim["no result"] = True   # nothing to corrupt: the run ended without a fit
            return
        _corrupt(archive.folder(m) / "result.json")
        victim.update(manifest=m, t=time.monotonic() - t0)
        print(f"archived result.json of {c.name}/{c.run_id} corrupted (a digit changed) at {victim['t']:.0f} s",
              flush=True)

    def start_run(c: Cell) -> str | None:
        """Start ``c``'s run (retried for 2 minutes: a starved daemon answers late, and a start it
        acted on after the client gave up shows as its current run); None when it did not start."""
        op = ControlClient(bus.session, c.name, site=SITE, client="operator", token=OPERATOR)
        text = plan_text.replace("cell: example", f"cell: {c.name}", 1)
        deadline, last = time.monotonic() + 120, None
        while time.monotonic() < deadline:
            try:
                return op.call("start", {"plan_text": text}, timeout=10)["run_id"]
            except (BadRequest, Refused) as exc:
                last = exc
                break
            except ControlError as exc:   # no reply, or none that could be attributed (an expired exchange)
                last = exc
                try:
                    run = (op.call("status", timeout=10).get("run") or {}).get("run_id")
                    if run:
                        return run
                except ControlError:
                    pass
                time.sleep(1)
        print(f"{c.name}: run not started at {time.monotonic() - t0:.0f} s: {last}", flush=True)
        failed_start.append(c.name)
        return None

    def waves() -> None:
        nonlocal station, killed_station, cut_done
        for w in range(n_waves):
            wave = []
            for i in range(w * args.wave, min(args.cells, (w + 1) * args.wave)):
                c = Cell(tmp, i, router, token, args)
                wave.append(c)
                # Cells are PCs of their own: start-up (a fresh interpreter per daemon and per real-time
                # exchange process) is not what is measured, so with --stagger the next daemon starts
                # once this one is ready; their runs then start together.
                deadline = time.monotonic() + (300 if args.stagger else 0)
                while not c.ready() and c.proc.poll() is None and time.monotonic() < deadline:
                    poll()
                    time.sleep(0.2)
            deadline = time.monotonic() + 300
            while not all(c.ready() or c.proc.poll() is not None for c in wave) and time.monotonic() < deadline:
                poll()
                time.sleep(0.2)
            for c in [c for c in wave if not c.ready()]:
                why = [ln for ln in (c.folder / "daemon.log").read_text(errors="replace").splitlines() if "ERROR" in ln]
                print(f"daemon {c.name} not ready at {time.monotonic() - t0:.0f} s: "
                      f"{why[-1] if why else 'no error logged'}", flush=True)
                failed_start.append(c.name)
                c.stop()
                wave.remove(c)
            cells.extend(wave)
            print(f"wave {w + 1}/{n_waves}: {len(wave)} daemons ready at {time.monotonic() - t0:.0f} s", flush=True)
            for c in list(wave):
                c.run_id = start_run(c)
                if c.run_id is None:
                    wave.remove(c)
                    cells.remove(c)
                    c.stop()
            print(f"wave {w + 1}/{n_waves}: runs started at {time.monotonic() - t0:.0f} s", flush=True)
            middle = w == n_waves // 2
            cut = wave[0] if middle and not cut_done else None
            cut_cell[0] = cut
            if middle and len(wave) > 1:
                victim["cell"] = wave[-1]   # kept running until its corrupted copy is repaired
            while time.monotonic() - t0 < args.timeout:
                poll()
                with lock:
                    done_runs = set(ended)
                if cut is not None and (cut.name, cut.run_id) in done_runs:
                    # The link cut: freeze the daemon past Zenoh's lease (10 s), then let it go on.
                    cut.proc.send_signal(signal.SIGSTOP)
                    now = time.monotonic()
                    cut.frozen = (now, now + args.freeze_s + 1)
                    print(f"cell {cut.name} frozen (link cut) at {now - t0:.0f} s", flush=True)
                    threading.Timer(args.freeze_s, _restore, (cut, t0, cut_cell)).start()  # the bench keeps polling
                    cut, cut_done = None, True
                in_wave = sum((c.name, c.run_id) in confirmed for c in wave)
                if not killed_station and middle and 0 < in_wave < len(wave):
                    station.kill()
                    station.wait()
                    print(f"station killed at {time.monotonic() - t0:.0f} s after {len(confirmed)} runs confirmed",
                          flush=True)
                    time.sleep(2)
                    station_peaks.append(Peaks())
                    station = start("station")
                    killed_station = True
                v = victim.get("cell")
                if (middle and killed_station and v is not None and "t" not in victim and "no result" not in victim
                        and (v.name, v.run_id) in confirmed):
                    corrupt(v)
                if all((c.name, c.run_id) in confirmed for c in wave) and (
                        victim.get("cell") not in wave or "repaired" in victim or "no result" in victim):
                    break
                time.sleep(0.2)
            for c in wave:
                c.stop()

    try:
        waves()
    finally:
        for c in cells:
            c.stop()
        if sys.exc_info()[0] is not None:
            for proc in (station, router_proc):
                if proc.poll() is None:
                    proc.kill()
            bus.close()   # an open Zenoh session would keep the interpreter from exiting
    elapsed = time.monotonic() - t0
    load_end = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    for proc in (station, router_proc):
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    bus.close()

    manifests = archive.manifests()
    ids = [(m["cell"], m["run_id"]) for m in manifests]
    with_result = sum(any(f["name"] == "result.json" for f in m["files"]) for m in manifests)
    history = sum(len(load_history(archive.root, s)) for s in robots(archive.root))
    lat = np.array(list(confirmed.values()))
    bad = sum(bool(archive.verify(m)) for m in manifests)
    total = sum(f["bytes"] for m in manifests for f in m["files"])
    started = [(c.name, c.run_id) for c in cells]
    lost = [k for k in started if k not in set(ids)]
    kinds: dict[str, int] = {}
    for s in states.values():
        kinds[s] = kinds.get(s, 0) + 1
    gaps = np.array([c.longest_ping_gap() for c in cells])
    cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"cells {args.cells} in {n_waves} wave(s) of ≤{args.wave}; daemons not ready {len(failed_start)} "
          f"{failed_start}; runs started {len(started)}, terminal "
          f"status seen on the bus {len(ended)} {kinds}, confirmed on the cell {len(confirmed)}, in the archive "
          f"{len(ids)} ({with_result} with a fitted result, {history} history entries), duplicates "
          f"{len(ids) - len(set(ids))}, lost {len(lost)}, failing re-verification {bad}")
    if len(lat):
        print(f"bytes archived {total / 1e6:.2f} MB ({total / max(1, len(ids)) / 1e3:.0f} kB per run) in {elapsed:.0f} s "
              f"wall; run's last byte → confirmed s: p50 {np.median(lat):.1f}, max {lat.max():.1f}")
    repaired = ("repaired %.0f s after the damage" % (victim["repaired"] - victim["t"]) if "repaired" in victim
                else "NOT repaired" if "t" in victim else "not injected")
    print(f"corrupted copy: {repaired}; "
          f"killed station {killed_station}, link cut {cut_done} ({args.freeze_s:.0f} s)")
    print(f"station peaks per process (restarts split it): {'; '.join(map(str, station_peaks))}; router {router_peaks}")
    print(f"daemons' longest gap between watchdog pings (WatchdogSec {WATCHDOG_USEC / 1e6:.0f} s): median "
          f"{np.median(gaps):.1f} s, max {gaps.max():.1f} s, {int((gaps > WATCHDOG_USEC / 1e6).sum())} over")
    print(f"load average (1 min): start {load[0]:.1f}, highest {max(load):.1f}; at the end: {load_end}")
    log_text = (tmp / "station.log").read_text(errors="replace")
    for k, n in sorted(_warnings_by_kind(log_text).items(), key=lambda kv: -kv[1])[:8]:
        print(f"  station log ×{n}: {k}")
    print(f"CPU of all child processes: {cpu.ru_utime + cpu.ru_stime:.0f} s")
    if args.keep:
        print(f"kept {tmp}")
    else:
        shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
