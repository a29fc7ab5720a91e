"""``acquire station``: find the cells, pull every finished run, verify, store, confirm.

The station's Zenoh session is a *client* of the site's router (``zenohd``, or ``acquire router``)
— restarting the station never takes the cells' control planes down. It reaches the router over
the router's Unix socket (``unixsock-stream//run/remaster-router/zenoh.sock``) or over TLS with the
router's CA, and checks that endpoint before its session sends anything
(``acquire.station.config.StationZenoh.connect_problems``): never over plain ``tcp/``. It watches the daemons'
liveliness tokens ``remaster/<site>/<cell>/daemon`` (and ``remaster/<cell>/daemon`` of a cell
without a site) and the announcements ``…/archive/ready`` a daemon puts when a run ends. A cell is
synced (``sync_cell``) when it appears, when it announces a run, and every ``poll_s`` as a sweep:

1. ``archive-list`` — the cell's runs not yet confirmed, with each file's size and sha256; the
   serial the cell reports must be the one ``cells`` binds it to, else nothing is archived;
2. for a run not yet archived: size limits and the free-space reserve are checked against the
   announced sizes (``Archive.begin``) before any byte is fetched, then ``archive-chunk`` from each
   file's partial offset on (a station restarted or a link cut mid-way resumes where the bytes
   stop); ``Transfer.finish`` verifies sizes and sha256s and moves the run in — never over another;
3. the run enters its robot's history (``acquire.station.intake``);
4. ``archive-confirm`` with the stored files — only now does the cell stop offering the run;
5. files the scrub quarantined (``acquire.station.scrub``) are fetched again; runs the scrub
   re-verified are confirmed again with ``"verified": true`` (the cell may then delete them under
   its retention policy).

Cells are synced concurrently (``sync_workers`` threads), each operation bounded by
``cell_timeout_s``: a frozen or slow cell holds one worker and delays no other. A cell that has
just appeared is retried quickly (0.25 s, doubling up to ``poll_s``) until it first answers —
its liveliness token is declared before its control queries are.

Every operation is a SCRAM-SHA-256 exchange (``acquire.daemon.control.ControlClient``) with the cell's
own token when ``cells`` gives one: the station believes a reply only when it carries the cell's
ServerSignature and MAC for this exchange.
"""

from __future__ import annotations

import base64
import json
import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field

from acquire.live.bus import ROOT, Bus
from acquire.daemon.control import BadRequest, ControlClient, ControlError
from acquire.station.alerts import Alerter
from acquire.station.archive import Archive, ArchiveError, ArchiveFull, ArchiveRefused, RunRef, Transfer
from acquire.station.config import StationConfig
from acquire.station.history import load_history, robots
from acquire.station.intake import catch_up, record_run
from acquire.station.scrub import ScrubReport, scrub
from acquire.station.states import robot_state
from acquire.daemon.tokens import read_token_file

log = logging.getLogger(__name__)

#: Liveliness keys of every daemon, with and without a site.
DAEMON_TOKENS = (f"{ROOT}/*/daemon", f"{ROOT}/*/*/daemon")
#: What a daemon puts when one of its runs has ended (a hint: the listing is authenticated).
ANNOUNCEMENTS = (f"{ROOT}/*/archive/ready", f"{ROOT}/*/*/archive/ready")
_FIRST_RETRY_S = 0.25
#: Seconds between the robot-state checks the loop makes by itself (after each archived run too).
STATES_EVERY_S = 600.0


def parse_daemon_key(key: str) -> tuple[str, str] | None:
    """``remaster/<site>/<cell>/daemon`` → (site, cell); ``remaster/<cell>/daemon`` → ("", cell)."""
    parts = key.split("/")
    if parts[0] != ROOT or parts[-1] != "daemon" or len(parts) not in (3, 4):
        return None
    return ("", parts[1]) if len(parts) == 3 else (parts[1], parts[2])


def parse_announcement(key: str) -> tuple[str, str] | None:
    """``remaster/<site>/<cell>/archive/ready`` → (site, cell); without a site ("", cell)."""
    parts = key.split("/")
    if parts[0] != ROOT or parts[-2:] != ["archive", "ready"] or len(parts) not in (4, 5):
        return None
    return ("", parts[1]) if len(parts) == 4 else (parts[1], parts[2])


def _name(site: str, cell: str) -> str:
    return f"{site}/{cell}" if site else cell


@dataclass
class CellState:
    """What the station knows of one cell (``acquire fleet`` shows it)."""

    site: str
    cell: str
    alive: bool = True
    answered: bool = False                 # it has answered the station at least once
    robot_serial: str | None = None        # as bound in the station's configuration
    last_sync: float | None = None
    last_error: str | None = None
    archived: int = 0
    repaired: int = 0
    bytes: int = 0
    pending: int = 0
    due: float = 0.0                       # time.monotonic() of its next sync
    again: bool = False                    # announced a run while being synced: sync once more
    retry_s: float = _FIRST_RETRY_S
    timings_s: list[float] = field(default_factory=list)   # run listed → confirmed, per run


class Station:
    """The service (see the module docstring). ``run()`` blocks until ``request_stop()``."""

    def __init__(self, cfg: StationConfig, *, token: str | None = None) -> None:
        self.cfg = cfg
        self.archive = Archive(cfg.archive, cfg.limits.limits())
        self.policy = cfg.drift.policy()
        self.alerts = Alerter(cfg.alert.command, cfg.alert.webhook, cfg.alert.timeout_s)
        self._token = token if token is not None else read_token_file(cfg.token_file)
        self._cell_tokens = {name: read_token_file(c.token_file) for name, c in cfg.cells.items()
                             if c.token_file is not None}
        shared = sorted(name for name, c in cfg.cells.items() if c.token_file is None)
        if len(shared) > 1:
            log.warning("cells %s share the station's token: each can answer as the others; give each its own "
                        "token_file (cells: in the station's configuration)", ", ".join(shared))
        self.cells: dict[tuple[str, str], CellState] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._pool = ThreadPoolExecutor(cfg.sync_workers, thread_name_prefix="station-sync")
        self._running: dict[tuple[str, str], Future] = {}
        self._states: dict[str, str] = {}
        self._states_lock = threading.Lock()
        self.bus: Bus | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "Station":
        """Check every endpoint (``StationZenoh.security_problems``: the router's socket must exist
        and only its account can have made it, or TLS with its CA) before the session sends anything,
        then join the router and watch the cells."""
        from acquire.live.bus import BusConfigError
        from acquire.station.router import open_session

        z = self.cfg.zenoh
        problems = z.security_problems(socket_up=True)
        if problems:
            raise BusConfigError("; ".join(f"zenoh.{'.'.join(map(str, loc[1:]))}: {msg}" for loc, msg in problems))
        self.bus = open_session("station", z, "remaster-station")
        self._states = self._read_states()
        self._write_station_file("policy.json", self.policy.to_dict())
        catch_up(self.archive, self.policy)   # runs stored just before a stop, not yet in their history
        for expr in DAEMON_TOKENS:
            self.bus.watch_liveliness(expr, self._on_liveliness)
        for expr in ANNOUNCEMENTS:
            self.bus.subscribe(expr, self._on_announcement)
        log.info("station: archive %s, Zenoh %s %s", self.cfg.archive, z.mode,
                 ", ".join(self.bus.locators) or ", ".join(z.connect))
        return self

    def close(self) -> None:
        self._stop.set()
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self.bus is not None:
            self.bus.close()

    def __enter__(self) -> "Station":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request_stop(self, *_args) -> None:
        self._stop.set()
        self._wake.set()

    def run(self, on_tick=None) -> int:
        """Sync cells when due (appeared, announced a run, or every ``poll_s``) and scrub the
        archive every ``scrub_hours`` until stopped. ``on_tick()``: called each loop (watchdog)."""
        next_scrub = time.monotonic() + 3600.0 * self.cfg.scrub_hours if self.cfg.scrub_hours else None
        scrubber: threading.Thread | None = None
        last_write, last_states = 0.0, float("-inf")
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                due = [c for c in self.cells.values() if c.alive and c.due <= now]
            for c in due:
                self.schedule(c.site, c.cell)
            if next_scrub is not None and now >= next_scrub and (scrubber is None or not scrubber.is_alive()):
                scrubber = threading.Thread(target=self.scrub, name="station-scrub", daemon=True)
                scrubber.start()
                next_scrub = now + 3600.0 * self.cfg.scrub_hours
            if now - last_write > 1.0:
                self.write_cells()
                last_write = now
            if now - last_states > STATES_EVERY_S:   # "check due" comes with time alone
                self.check_states()
                last_states = now
            if on_tick is not None:
                on_tick()
            self._wake.wait(0.5)
            self._wake.clear()
        return 0

    def _cell(self, ident: tuple[str, str]) -> CellState:
        with self._lock:
            return self.cells.setdefault(ident, CellState(*ident))

    def _on_liveliness(self, key: str, alive: bool) -> None:
        ident = parse_daemon_key(key)
        if ident is None or (self.cfg.sites is not None and ident[0] not in self.cfg.sites):
            return
        state = self._cell(ident)
        with self._lock:
            state.alive = alive
            if alive:
                state.answered, state.retry_s, state.due = False, _FIRST_RETRY_S, 0.0
        log.info("cell %s %s", _name(*ident), "joined" if alive else "left")
        if alive:
            self._wake.set()

    def _on_announcement(self, key: str, _payload) -> None:
        ident = parse_announcement(key)
        if ident is None or (self.cfg.sites is not None and ident[0] not in self.cfg.sites):
            return
        state = self._cell(ident)
        with self._lock:
            state.due, state.again = 0.0, True
        log.debug("cell %s announced a finished run", _name(*ident))
        self._wake.set()

    # ------------------------------------------------------------------ syncing
    def schedule(self, site: str, cell: str) -> Future | None:
        """Sync one cell on a worker unless it is being synced already; its future."""
        ident = (site, cell)
        with self._lock:
            running = self._running.get(ident)
            if running is not None and not running.done():
                return running
            state = self.cells.setdefault(ident, CellState(site, cell))
            state.due = float("inf")   # set again when the sync ends
            fut = self._pool.submit(self._sync_job, state)
            self._running[ident] = fut
            return fut

    def _sync_job(self, state: CellState) -> int:
        """``sync_cell`` on a worker: whatever happens, the cell is due again after ``poll_s``."""
        try:
            return self.sync_cell(state.site, state.cell)
        except Exception:  # noqa: BLE001 - a defect, not the cell's fault: logged with its traceback, retried
            log.exception("cell %s: sync failed", _name(state.site, state.cell))
            with self._lock:
                state.due = time.monotonic() + self.cfg.poll_s
            return 0

    def sync_all(self) -> int:
        """Sync every live cell once, concurrently, and wait; returns how many runs were archived."""
        with self._lock:
            live = [(c.site, c.cell) for c in self.cells.values() if c.alive]
        futures = [f for f in (self.schedule(*ident) for ident in live) if f is not None]
        wait(futures)
        self.write_cells()
        return sum(f.result() for f in futures if f.exception() is None)

    def sync_cell(self, site: str, cell: str) -> int:
        """Pull, verify, store and confirm every pending run of one cell, repair what the scrub
        quarantined, tell it what was re-verified; returns how many runs were archived (a failure
        is logged, kept in the cell's state, and retried on the cell's next sync)."""
        state = self._cell((site, cell))
        done, errors = 0, []
        try:
            entry = self.cfg.cell(site, cell)
            if entry is None:
                raise ArchiveRefused(f"cell {_name(site, cell)} is not in the station's configuration (cells:); "
                                     "add it with its robot's serial to archive its runs")
            state.robot_serial = entry.robot_serial
            client = self._client(site, cell)
            listing = client.call("archive-list", timeout=self.cfg.cell_timeout_s)
            state.answered = True
            if listing.get("robot_serial") != entry.robot_serial:
                raise ArchiveRefused(f"cell {_name(site, cell)} reports robot {listing.get('robot_serial')!r}, but the "
                                     f"station's configuration binds it to {entry.robot_serial!r}; nothing archived "
                                     "(fix the daemon's robot_serial or the station's cells:)")
            runs = listing.get("runs", [])
            state.pending = len(runs)
            for run in runs:
                try:
                    done += self._archive_run(client, state, RunRef(site, cell, run["run_id"], entry.robot_serial), run)
                    state.pending -= 1
                except (ArchiveFull, ArchiveRefused) as exc:
                    errors.append(str(exc))
                    self._refused(site, cell, exc)
            self._repair(client, state)
            self._tell_verified(client, site, cell)
        except ArchiveRefused as exc:
            errors.append(str(exc))
            self._refused(site, cell, exc)
        except (ControlError, ArchiveError, ValueError, KeyError, TypeError, OSError, RuntimeError) as exc:
            errors.append(f"{type(exc).__name__}: {exc}")
        self._finished_sync(state, errors)
        if done:
            self.check_states()
        return done

    def _finished_sync(self, state: CellState, errors: list[str]) -> None:
        now = time.monotonic()
        with self._lock:
            state.last_sync = time.time()
            if errors and not state.answered:
                # Just appeared and not answering yet (its queries come after its token): soon again.
                log.debug("cell %s not answering yet: %s", _name(state.site, state.cell), errors[-1])
                state.due = now + state.retry_s
                state.retry_s = min(2 * state.retry_s, self.cfg.poll_s)
                state.last_error = errors[-1]
                return
            if errors:
                if errors[-1] != state.last_error:
                    log.warning("cell %s: %s", _name(state.site, state.cell), "; ".join(errors))
                state.last_error = errors[-1]
            else:
                state.last_error = None
            # A run announced while this sync was under way may have missed its listing: once more.
            state.due = now if state.again else now + self.cfg.poll_s
            state.again = False

    def _refused(self, site: str, cell: str, exc: Exception) -> None:
        state = self._cell((site, cell))
        if str(exc) != state.last_error:
            self.alerts.send("refused", str(exc), site=site, cell=cell, problem=str(exc))

    def _client(self, site: str, cell: str) -> ControlClient:
        token = self._cell_tokens.get(_name(site, cell), self._token)
        return ControlClient(self.bus.session, cell, site=site or None, client=self.cfg.client, token=token)

    def _archive_run(self, client: ControlClient, state: CellState, ref: RunRef, run: dict) -> int:
        t0 = time.monotonic()
        done = 0
        if not self.archive.is_complete(ref, run["files"]):
            manifest = self._fetch(client, self.archive.begin(ref, run["files"], run["finished"]))
            record_run(self.archive, manifest, self.policy)
            state.archived += 1
            state.bytes += sum(f["bytes"] for f in manifest["files"])
            done = 1
        stored = self.archive.manifest(ref)["files"]
        client.call("archive-confirm", {"run_id": ref.run_id, "files": stored}, timeout=self.cfg.cell_timeout_s)
        state.timings_s.append(time.monotonic() - t0)
        return done

    def _fetch(self, client: ControlClient, transfer: Transfer) -> dict:
        """Every missing byte of a transfer, chunk by chunk; then ``finish``."""
        try:
            for name, offset in transfer.missing().items():
                size = transfer.files[name]["bytes"]
                while offset < size:
                    reply = client.call("archive-chunk", {"run_id": transfer.ref.run_id, "name": name,
                                                          "offset": offset, "size": self.cfg.chunk_bytes},
                                        timeout=self.cfg.cell_timeout_s)
                    data = base64.b64decode(reply["data"], validate=True)
                    if not data:
                        raise ArchiveError(f"{transfer.ref.run_id}/{name}: the cell sent no bytes at offset "
                                           f"{offset} of {size}")
                    offset = transfer.write(name, offset, data)
            return transfer.finish()
        finally:
            transfer.close()

    def _runs_of(self, site: str, cell: str) -> list[tuple[RunRef, dict]]:
        """(ref, index entry) of every archived run of one cell."""
        prefix = f"{site or '-'}~{cell}~"
        out = []
        for idx in sorted((self.archive.root / ".index").glob(f"{prefix}*.json")):
            entry = json.loads(idx.read_text())
            manifest = json.loads((self.archive.root / entry["folder"] / "manifest.json").read_text())
            out.append((RunRef.of(manifest), entry))
        return out

    def _repair(self, client: ControlClient, state: CellState) -> None:
        for ref, entry in self._runs_of(state.site, state.cell):
            if not entry.get("damaged"):
                continue
            manifest = self.archive.manifest(ref)
            transfer = self.archive.begin_repair(manifest)
            if transfer is None:
                continue
            try:
                self._fetch(client, transfer)
                state.repaired += 1
            except BadRequest as exc:
                log.error("run %s (robot %s) cannot be repaired: cell %s answers %s; the quarantined copy stays",
                          ref.run_id, ref.robot_serial, _name(state.site, state.cell), exc)
                self.archive.update_index(ref, repair_error=str(exc))

    def _tell_verified(self, client: ControlClient, site: str, cell: str) -> None:
        for ref, entry in self._runs_of(site, cell):
            if not entry.get("verified_at") or entry.get("told_verified") == entry["verified_at"]:
                continue
            files = self.archive.manifest(ref)["files"]
            try:
                client.call("archive-confirm", {"run_id": ref.run_id, "files": files, "verified": True},
                            timeout=self.cfg.cell_timeout_s)
            except BadRequest as exc:   # the cell has deleted it, or it changed since: nothing to tell
                log.debug("run %s: not told verified: %s", ref.run_id, exc)
            self.archive.update_index(ref, told_verified=entry["verified_at"])

    # ------------------------------------------------------------------ archive checks and states
    def scrub(self) -> ScrubReport:
        """Read the whole archive back (``acquire.station.scrub``); alerts for what is damaged."""
        report = scrub(self.archive)
        for tag, name, why in report.damaged:
            self.alerts.send("damaged", f"archive: {tag}: {name} {why}; quarantined, fetched again from the cell",
                             run=tag, file=name, problem=why)
        with self._lock:
            for c in self.cells.values():
                c.due = 0.0   # repair and confirm soon
        self._wake.set()
        log.info("scrub: %s", report.lines()[0])
        return report

    def check_states(self) -> dict[str, dict]:
        """Every robot's state now; alerts for each change since the last check."""
        out, changes = {}, []
        with self._states_lock:
            for serial in robots(self.archive.root):
                entries = load_history(self.archive.root, serial)
                st = out[serial] = robot_state(entries, self.policy)
                before = self._states.get(serial)
                if before != st["state"]:
                    changes.append((serial, before, st, entries[-1] if entries else {}))
                    self._states[serial] = st["state"]
            self._write_station_file("states.json", self._states)
        for serial, before, st, last in changes:
            self.alerts.send("state", f"robot {serial}: {before or 'new'} → {st['state']}: " + "; ".join(st["reasons"]),
                             robot_serial=serial, site=last.get("site"), cell=last.get("cell"), reasons=st["reasons"],
                             **{"from": before, "to": st["state"]})
        return out

    def _read_states(self) -> dict[str, str]:
        try:
            return json.loads((self.archive.root / ".station" / "states.json").read_text())
        except (OSError, ValueError):
            return {}

    def _write_station_file(self, name: str, body: dict) -> None:
        folder = self.archive.root / ".station"
        folder.mkdir(exist_ok=True)
        tmp = folder / f"{name}.tmp"
        tmp.write_text(json.dumps(body, indent=1))
        tmp.replace(folder / name)

    def write_cells(self) -> None:
        """The cells as the station sees them, for ``acquire fleet``: ``<archive>/.station/cells.json``."""
        rows = [{k: v for k, v in vars(c).items() if k not in ("timings_s", "due", "retry_s")}
                for c in self.cell_states()]
        self._write_station_file("cells.json", {"written": time.time(), "cells": rows})

    def cell_states(self) -> list[CellState]:
        with self._lock:
            return sorted(self.cells.values(), key=lambda c: (c.site, c.cell))

