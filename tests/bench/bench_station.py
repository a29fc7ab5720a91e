"""Scale of the plant station: N cells behind the site's router, one station archiving all of them.

    python tests/bench/bench_station.py [--cells 10] [--runs 2] [--mcap-kb 512] [--iterations 4096]

The router (``acquire router``) and the station (``acquire station --config …``, a client of the
router) run as processes of their own; the cells are peer sessions of the router in this
process, each with its daemon's control queries (``acquire.daemon.service.Daemon``, not started: no
devices), liveliness token and the announcement a daemon puts when a run ends (the station's
sweep is every 30 s: runs come in by announcement). A "run" is a run folder written on the cell
(MCAP-sized random bytes, a result.json, a report) — the fit is not what is measured here.
Mid-way the station is killed (SIGKILL) and restarted, one cell's session is closed and reopened
(its link cut and restored), one archived MCAP is corrupted (the station's scrub, every ~20 s
here, must find it and fetch it again from its cell), and cell 1 freezes (its listing hangs
for 40 s). Printed: runs archived vs. written, bytes, seconds from a run written to confirmed
(median, max), duplicates in the archive, every stored file re-verified, the station's peak RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def _result(rng) -> dict:
    std = np.full(6, 0.005)
    return {"format": "remaster.fit/1", "data": {"n_configurations": 40},
            "joint_offsets": [{"joint": f"A{i + 1}", "value_deg": float(rng.normal(0, 0.005)), "std_deg": 0.005,
                               "identifiable": True, "ci95_deg": None} for i in range(6)],
            "metrics": {"absolute": {"before": {"mean": 0.4}, "after": {"mean": 0.1}}}, "std": std.tolist()}


def _frozen_daemon(seconds: float):
    """A daemon class whose listing hangs ``seconds`` once ``freeze`` is set (a frozen cell PC)."""
    import threading

    from acquire.daemon.service import Daemon

    class Frozen(Daemon):
        freeze = threading.Event()

        def archive_list(self) -> dict:
            if self.freeze.is_set():
                self.freeze.clear()
                time.sleep(seconds)
            return super().archive_list()

    return Frozen


class BenchCell:
    def __init__(self, tmp: Path, i: int, router: str, creds, daemon_cls=None) -> None:
        from acquire.daemon.service import Daemon
        from acquire.daemon.config import DaemonConfig

        self.name = f"c{i:03d}"
        self.state_dir = tmp / "cells" / self.name
        self.daemon = (daemon_cls or Daemon)(DaemonConfig(cell=self.name, site="bench", robot_serial=f"R{i:03d}",
                                                          fake=True, state_dir=self.state_dir))
        self.router, self.creds = router, creds
        self.bus = self.server = None
        self.connect()

    def connect(self) -> None:
        from acquire.live.bus import Bus
        from acquire.daemon.control import Authorizer, ControlServer
        from acquire.daemon.config import AuthSection

        self.bus = Bus(self.name, site="bench", config={"listen": [], "connect": [self.router]})
        auth = AuthSection.model_validate({"clients": [{"name": "station", "scram": self.creds.config(),
                                                        "allow": ["archive"]}]})
        self.server = ControlServer(self.bus.session, self.name, self.daemon, Authorizer(auth), site="bench")
        self.bus.liveliness_token(self.bus.key("daemon"))

    def disconnect(self) -> None:
        self.server.close()
        self.bus.close()

    def write_run(self, k: int, kb: int, rng) -> tuple[Path, float]:
        folder = self.state_dir / "runs" / f"{self.name}-run{k}"
        folder.mkdir(parents=True)
        (folder / f"{folder.name}.mcap").write_bytes(rng.bytes(kb * 1024))
        (folder / "result.json").write_text(json.dumps(_result(rng)))
        (folder / "report.html").write_text("<html>report</html>")
        if not self.bus.closed:   # a cut-off cell announces nothing: the station's sweep finds it
            self.bus.publish(self.bus.key("archive", "ready"), {"run_id": folder.name})
        return folder, time.monotonic()


def _rss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, default=10)
    ap.add_argument("--runs", type=int, default=2, help="runs per cell (half before, half after the restart)")
    ap.add_argument("--mcap-kb", type=int, default=512)
    ap.add_argument("--iterations", type=int, default=4096, help="PBKDF2 iterations of the station's token")
    ap.add_argument("--timeout", type=float, default=600)
    args = ap.parse_args()

    from acquire.daemon import control_auth
    from acquire.station.archive import Archive
    from acquire.daemon.tokens import new_token, write_token_file

    tmp = Path(tempfile.mkdtemp(prefix="bench-station-"))
    token = new_token()
    write_token_file(tmp / "station.token", token)
    creds = control_auth.derive_credentials(token, iterations=args.iterations)
    router = f"unixsock-stream/{tmp / 'router.sock'}"   # the station's link: never tcp/ (docs/how-to/station.md)
    (tmp / "router.yaml").write_text(f"listen: ['{router}']\n")
    cells_cfg = "".join(f"  bench/c{i:03d}: {{robot_serial: R{i:03d}}}\n" for i in range(args.cells))
    (tmp / "station.yaml").write_text(
        f"archive: archive\ntoken_file: station.token\npoll_s: 30\nchunk_bytes: 1048576\nscrub_hours: 0.006\n"
        f"cell_timeout_s: 60\nlimits: {{reserve_free_bytes: 0}}\n"
        f"zenoh: {{mode: client, listen: [], connect: ['{router}']}}\ncells:\n{cells_cfg}")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    router_proc = subprocess.Popen([sys.executable, "-m", "acquire", "router", "--config", str(tmp / "router.yaml")],
                                   env=env, stdout=subprocess.DEVNULL, stderr=open(tmp / "router.log", "a"))
    time.sleep(3)

    def start_station() -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "acquire", "station", "--config", str(tmp / "station.yaml")],
                                env=env, stdout=subprocess.DEVNULL, stderr=open(tmp / "station.log", "a"))

    station = start_station()
    time.sleep(2)
    rng = np.random.default_rng(1)
    frozen_cls = _frozen_daemon(40.0)
    cells = [BenchCell(tmp, i, router, creds, frozen_cls if i == 1 else None) for i in range(args.cells)]
    written: dict[Path, float] = {}
    confirmed: dict[Path, float] = {}
    peak = 0
    t_start = time.monotonic()
    half = max(1, args.runs // 2)

    def poll() -> None:
        nonlocal peak
        peak = max(peak, _rss_kb(station.pid))
        for folder, t in written.items():
            if folder not in confirmed and (folder / ".archived").exists():
                confirmed[folder] = time.monotonic() - t

    for c in cells:
        for k in range(half):
            f, t = c.write_run(k, args.mcap_kb, rng)
            written[f] = t
    # Mid-way: kill the station once some runs are archived, cut one cell's link.
    while len(confirmed) < max(1, len(written) // 3) and time.monotonic() - t_start < args.timeout:
        poll()
        time.sleep(0.2)
    station.kill()
    station.wait()
    peak_first, peak = peak, 0
    cells[0].disconnect()
    print(f"station killed after {len(confirmed)}/{len(written)} runs confirmed; cell {cells[0].name} cut off")
    archive = Archive(tmp / "archive")
    victim = archive.manifests()[0]
    mcap = next(f["name"] for f in victim["files"] if f["name"].endswith(".mcap"))
    with open(archive.folder(victim) / mcap, "r+b") as f:
        f.truncate(1000)
    print(f"archived {victim['run_id']}/{mcap} truncated to 1000 bytes; cell c001 frozen for 40 s")
    if args.cells > 1:
        frozen_cls.freeze.set()
    for c in cells:
        for k in range(half, args.runs):
            f, t = c.write_run(k, args.mcap_kb, rng)
            written[f] = t
    station = start_station()
    time.sleep(2)
    cells[0].connect()
    print(f"station restarted; cell {cells[0].name} reconnected")
    while len(confirmed) < len(written) and time.monotonic() - t_start < args.timeout:
        poll()
        time.sleep(0.2)
    while archive.verify(victim) and time.monotonic() - t_start < args.timeout:
        time.sleep(0.5)
    print(f"corrupted copy {'repaired' if not archive.verify(victim) else 'NOT repaired'} at "
          f"{time.monotonic() - t_start:.1f} s")
    elapsed = time.monotonic() - t_start
    station.terminate()
    station.wait(timeout=30)
    for c in cells:
        c.disconnect()
    router_proc.terminate()
    router_proc.wait(timeout=30)

    manifests = archive.manifests()
    ids = [m["run_id"] for m in manifests]
    lat = np.array(sorted(confirmed.values()))
    bad = sum(bool(archive.verify(m)) for m in manifests)
    total = sum(f["bytes"] for m in manifests for f in m["files"])
    print(f"cells {args.cells}, runs written {len(written)}, confirmed {len(confirmed)}, archived {len(ids)}, "
          f"duplicates {len(ids) - len(set(ids))}, failing verification {bad}")
    print(f"bytes archived {total / 1e6:.1f} MB in {elapsed:.1f} s wall; written→confirmed s: median "
          f"{np.median(lat):.1f}, max {lat.max():.1f} (includes the restart)")
    print(f"station peak RSS: first process {peak_first / 1024:.0f} MB, second {peak / 1024:.0f} MB")
    shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
