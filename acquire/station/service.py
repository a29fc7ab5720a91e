"""``acquire station``: find the cells, pull every finished run, verify, store, confirm.

The station opens one Zenoh session (by default the site's router: cells connect to it) and
watches the daemons' liveliness tokens ``remaster/<site>/<cell>/daemon`` (and
``remaster/<cell>/daemon`` of a cell without a site). Every ``poll_s``, and as soon as a cell
appears, it syncs each live cell (``sync_cell``):

1. ``archive-list`` — the cell's runs not yet confirmed, with each file's size and sha256;
2. for a run not yet archived: ``archive-chunk`` from each file's partial offset on
   (``Archive.begin`` → ``Transfer``: a station restarted or a link cut mid-way resumes where
   the bytes stop), then ``Transfer.finish`` verifies sizes and sha256s and moves it in;
3. the run enters its robot's history with a drift verdict (``acquire.station.intake``);
4. ``archive-confirm`` with the stored files — only now does the cell stop offering the run.

Every operation is a SCRAM-SHA-256 exchange (``acquire.control.ControlClient``): the station
believes a reply only when it carries the cell's ServerSignature and MAC for this exchange, so a
process without the station client's keys (a cell without credentials, a stand-in) can neither
list runs nor send bytes into the archive. A failure with one cell is logged and retried on the
next poll; it never stops the others.
"""

from __future__ import annotations

import base64
import json
import logging
import threading
import time
from dataclasses import dataclass, field

from acquire.bus import ROOT, Bus
from acquire.control import ControlClient, ControlError
from acquire.station.archive import Archive, ArchiveError, RunRef
from acquire.station.config import StationConfig
from acquire.station.intake import record_run
from acquire.tokens import read_token_file

log = logging.getLogger(__name__)

#: Liveliness keys of every daemon, with and without a site.
DAEMON_TOKENS = (f"{ROOT}/*/daemon", f"{ROOT}/*/*/daemon")


def parse_daemon_key(key: str) -> tuple[str, str] | None:
    """``remaster/<site>/<cell>/daemon`` → (site, cell); ``remaster/<cell>/daemon`` → ("", cell)."""
    parts = key.split("/")
    if parts[0] != ROOT or parts[-1] != "daemon" or len(parts) not in (3, 4):
        return None
    return ("", parts[1]) if len(parts) == 3 else (parts[1], parts[2])


@dataclass
class CellState:
    """What the station knows of one cell (``acquire fleet`` shows it)."""

    site: str
    cell: str
    alive: bool = True
    robot_serial: str | None = None
    last_sync: float | None = None
    last_error: str | None = None
    archived: int = 0
    bytes: int = 0
    pending: int = 0
    timings_s: list[float] = field(default_factory=list)   # run listed → confirmed, per run


class Station:
    """The service (see the module docstring). ``run()`` blocks until ``request_stop()``."""

    def __init__(self, cfg: StationConfig, *, token: str | None = None) -> None:
        self.cfg = cfg
        self.archive = Archive(cfg.archive)
        self._token = token if token is not None else read_token_file(cfg.token_file)
        self._cell_tokens = {k: read_token_file(p) for k, p in cfg.cell_tokens.items()}
        self.cells: dict[tuple[str, str], CellState] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.bus: Bus | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "Station":
        z = self.cfg.zenoh
        problems = z.security_problems()
        if problems:
            from acquire.bus import BusConfigError

            raise BusConfigError("; ".join(f"zenoh.{'.'.join(map(str, loc[1:]))}: {msg}" for loc, msg in problems))
        # Zenoh's shared-memory transport maps a segment per local peer that sends large payloads
        # (~15 MB each, measured with 50 cells on one host); cells are remote: off unless asked.
        overrides = {"transport/shared_memory/enabled": False, **z.zenoh}
        self.bus = Bus("station", config={"mode": z.mode, "listen": list(z.listen), "connect": list(z.connect),
                                          "zenoh": overrides},
                       listen_loopback_only=all(_loopback(e) for e in [*z.listen, *z.connect]))
        for expr in DAEMON_TOKENS:
            self.bus.watch_liveliness(expr, self._on_liveliness)
        log.info("station: archive %s, Zenoh %s on %s", self.cfg.archive, z.mode, ", ".join(self.bus.locators))
        return self

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()

    def __enter__(self) -> "Station":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request_stop(self, *_args) -> None:
        self._stop.set()
        self._wake.set()

    def run(self) -> int:
        """Sync every live cell every ``poll_s`` (or when one appears) until stopped."""
        while not self._stop.is_set():
            self.sync_all()
            self._wake.wait(self.cfg.poll_s)
            self._wake.clear()
        return 0

    def _on_liveliness(self, key: str, alive: bool) -> None:
        ident = parse_daemon_key(key)
        if ident is None or (self.cfg.sites is not None and ident[0] not in self.cfg.sites):
            return
        with self._lock:
            state = self.cells.setdefault(ident, CellState(*ident))
            state.alive = alive
        log.info("cell %s %s", "/".join(p for p in ident if p), "joined" if alive else "left")
        if alive:
            self._wake.set()

    # ------------------------------------------------------------------ syncing
    def sync_all(self) -> int:
        """Sync every live cell once; returns how many runs were archived."""
        with self._lock:
            live = [c for c in self.cells.values() if c.alive]
        done = sum(self.sync_cell(c.site, c.cell) for c in live)
        self.write_cells()
        return done

    def write_cells(self) -> None:
        """The cells as the station sees them, for ``acquire fleet``: ``<archive>/.station/cells.json``."""
        folder = self.archive.root / ".station"
        folder.mkdir(exist_ok=True)
        rows = [{k: v for k, v in vars(c).items() if k != "timings_s"} for c in self.cell_states()]
        tmp = folder / "cells.tmp"
        tmp.write_text(json.dumps({"written": time.time(), "cells": rows}, indent=1))
        tmp.replace(folder / "cells.json")

    def _client(self, site: str, cell: str) -> ControlClient:
        token = self._cell_tokens.get(f"{site}/{cell}" if site else cell, self._token)
        return ControlClient(self.bus.session, cell, site=site or None, client=self.cfg.client, token=token)

    def sync_cell(self, site: str, cell: str) -> int:
        """Pull, verify, store and confirm every pending run of one cell; returns how many were
        archived (a failure is logged, kept in the cell's state, and retried next time)."""
        with self._lock:
            state = self.cells.setdefault((site, cell), CellState(site, cell))
        client = self._client(site, cell)
        done = 0
        try:
            listing = client.call("archive-list", timeout=15.0)
            state.robot_serial = listing.get("robot_serial")
            state.pending = len(listing.get("runs", []))
            for run in listing.get("runs", []):
                t0 = time.monotonic()
                ref = RunRef(site, cell, run["run_id"], state.robot_serial or cell)
                if not self.archive.is_complete(ref, run["files"]):
                    manifest = self._pull(client, ref, run)
                    record_run(self.archive, manifest, self.cfg.drift.policy())
                    state.archived += 1
                    state.bytes += sum(f["bytes"] for f in manifest["files"])
                    done += 1
                stored = self.archive.manifest(ref)["files"]
                client.call("archive-confirm", {"run_id": ref.run_id, "files": stored}, timeout=15.0)
                state.pending -= 1
                state.timings_s.append(time.monotonic() - t0)
            state.last_error = None
        except (ControlError, ArchiveError, ValueError, KeyError, TypeError, OSError, RuntimeError) as exc:
            state.last_error = f"{type(exc).__name__}: {exc}"
            log.warning("cell %s: %s", "/".join(p for p in (site, cell) if p), state.last_error)
        state.last_sync = time.time()
        return done

    def _pull(self, client: ControlClient, ref: RunRef, run: dict) -> dict:
        transfer = self.archive.begin(ref, run["files"], run["finished"])
        for name, offset in transfer.missing().items():
            size = next(f["bytes"] for f in run["files"] if f["name"] == name)
            while offset < size:
                reply = client.call("archive-chunk", {"run_id": ref.run_id, "name": name, "offset": offset,
                                                      "size": self.cfg.chunk_bytes}, timeout=30.0)
                data = base64.b64decode(reply["data"], validate=True)
                if not data:
                    raise ArchiveError(f"{ref.run_id}/{name}: the cell sent no bytes at offset {offset} of {size}")
                offset = transfer.write(name, offset, data)
        return transfer.finish()

    def cell_states(self) -> list[CellState]:
        with self._lock:
            return sorted(self.cells.values(), key=lambda c: (c.site, c.cell))


def _loopback(endpoint: str) -> bool:
    from acquire.bus import is_loopback_endpoint

    return is_loopback_endpoint(endpoint)
