"""``acquire watch``: show a live run or daemon — found on the bus by itself — as a status view.

Examples::

    acquire watch                                    # the cell behind tcp/127.0.0.1:7447, whatever its name
    acquire watch --until-done                       # ... and exit when its run ends
    acquire watch --raw                              # every message as one JSON line
    acquire watch --raw 'remaster/cell1/run/*/event' # any key expression, raw
    acquire watch --connect tcp/127.0.0.1:7448       # a run started with --listen tcp/127.0.0.1:7448
    acquire watch --site plant-a --cell c7 --connect tls/router:7447   # a cell of a plant (daemon `site:`)

Subscribes over Zenoh (loopback only) to the process that runs the cell — the daemon, or an
``acquire run`` — by default the one listening on tcp/127.0.0.1:7447 and, when it is there and
only the daemon's account can have made it, the daemon's ``/run/remaster/zenoh.sock``. Without ``--cell`` the cell
is the first one seen there: the daemon's liveliness token ``remaster/<cell>/daemon`` or any
message under ``remaster/<cell>/``. On a terminal it shows a live panel: daemon and devices,
the run's progress (state, done/total, measured, skipped, failed, ETA), the configuration being
measured, the last sample, the joints, the last warnings. Piped (or in a journal) it prints one
plain line per status change, sample and warning. ``--raw`` prints every message as
``<key> <compact JSON>`` (other payloads as their size and hex). It may be started before the
run: it connects when the run starts. Stops after ``--count`` messages, after ``--duration``
seconds, with ``--until-done`` when the run ends, or on Ctrl-C.

A cell whose daemon has ``site:`` publishes under ``remaster/<site>/<cell>/…``: give ``--site``
(or ``$REMASTER_SITE``); the view then reads the keys below ``remaster/<site>/`` and, without
``--cell``, takes the first cell of that site it sees.
"""

from __future__ import annotations

import json
import logging
import queue
import sys
import time
from typing import Optional

import typer

log = logging.getLogger(__name__)

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"  # acquire.live.bus.DEFAULT_ENDPOINT (zenoh is loaded on use)
#: Seconds without any connection before saying so (once).
NOT_CONNECTED_AFTER_S = 2.0
#: Seconds connected without seeing a cell before saying so (once).
NO_CELL_AFTER_S = 5.0


def format_line(key_str: str, payload: bytes) -> str:
    """``<key> <compact JSON>``, or ``<key> <n> bytes: <hex…>`` for a non-JSON payload."""
    from acquire.record.jsonpayload import PayloadError, decode_json

    try:
        obj = decode_json(payload)
    except PayloadError:
        head = payload[:32].hex()
        return f"{key_str} {len(payload)} bytes: {head}{'…' if len(payload) > 32 else ''}"
    return f"{key_str} {json.dumps(obj, separators=(',', ':'), ensure_ascii=False)}"


def _connected(bus) -> bool:
    """Whether the session has any peer or router: a daemon is a Zenoh router, a run a peer."""
    info = bus.session.info
    return bool(info.peers_zid()) or bool(info.routers_zid())


def _default_connect() -> list[str]:
    """``acquire run``'s endpoint, plus the daemon's Unix socket when it passes the client's check
    (``acquire.daemon.local_sockets``): the shipped daemon listens there only."""
    from acquire.daemon.local_sockets import DEFAULT_LOCAL_ENDPOINT, credential_endpoint_problem, trusted_uids

    local = credential_endpoint_problem(DEFAULT_LOCAL_ENDPOINT, tls_ca=None, trusted=trusted_uids()) is None
    return [DEFAULT_CONNECT, *([DEFAULT_LOCAL_ENDPOINT] if local else [])]


def watch(
    key_expr: Optional[str] = typer.Argument(None, metavar="[KEYEXPR]",
                                             help="Key expression (default: everything of the cell)."),
    cell: Optional[str] = typer.Option(None, "--cell",
                                       help="Cell id ([a-z0-9_-]+); default: the one found on the bus."),
    site: Optional[str] = typer.Option(None, "--site", envvar="REMASTER_SITE",
                                       help="The cell's plant site (a daemon with `site:`: keys remaster/<site>/<cell>/…)."),
    connect: Optional[list[str]] = typer.Option(None, "--connect", help=(
        "Endpoint of the run or daemon (repeatable; default: tcp/127.0.0.1:7447, and the daemon's "
        "unixsock-stream//run/remaster/zenoh.sock when only its account can have made it).")),
    raw: bool = typer.Option(False, "--raw", help="Print every message as '<key> <JSON>' instead of the status view."),
    until_done: bool = typer.Option(False, "--until-done", help="Exit when the watched run has finished, aborted or failed."),
    count: int = typer.Option(0, "--count", help="Exit after this many messages (0: no limit)."),
    duration: float = typer.Option(0.0, "--duration", help="Exit after this many seconds (0: no limit)."),
) -> None:
    """Show a live run or daemon (found on the bus by itself): progress, last sample, warnings."""
    from acquire.live.bus import ROOT, Bus, BusConfigError, BusError, check_key_expr, key

    if count < 0:
        raise typer.BadParameter(f"must be >= 0, given {count}", param_hint="--count")
    if duration < 0:
        raise typer.BadParameter(f"must be >= 0 s, given {duration}", param_hint="--duration")
    try:
        if cell is not None or site is not None:
            key(cell or "x", "x", site=site)  # validates the cell and site ids
        prefix = f"{ROOT}/{site}" if site else ROOT
        if key_expr:
            expr = check_key_expr(key_expr)
        else:
            expr = f"{prefix}/{cell}/**" if cell else f"{prefix}/**"
    except BusConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="KEYEXPR" if key_expr else "--cell / --site") from exc
    if key_expr and not raw:
        raw = True  # an explicit key expression is a raw stream: the view needs the cell's own keys
    connect = list(connect or _default_connect())
    inbox: "queue.Queue[tuple[str, str, object]]" = queue.Queue()
    try:
        bus = Bus(cell or "watch", config={"listen": [], "connect": connect})
    except BusConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--connect / --cell") from exc
    except BusError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    with bus:
        bus.subscribe(expr, lambda k, p: inbox.put(("msg", k, p)))
        if not key_expr:  # the view's daemon and devices; a raw key expression gets only its own stream
            bus.watch_liveliness(f"{prefix}/{cell or '*'}/daemon", lambda k, a: inbox.put(("alive", k, a)))
            bus.watch_liveliness(f"{prefix}/{cell or '*'}/device/*", lambda k, a: inbox.put(("alive", k, a)))
        typer.echo(f"watching {expr} via {', '.join(connect)}", err=True)
        session = _Session(bus, cell, site=site, raw=raw, until_done=until_done, count=count, duration=duration,
                           connect=connect, explicit_expr=bool(key_expr))
        try:
            session.loop(inbox)
        except KeyboardInterrupt:
            typer.echo("", err=True)
        finally:
            session.close()


class _Session:
    """The receive loop of one ``acquire watch``: discovery, raw lines, plain lines or the live view."""

    def __init__(self, bus, cell: Optional[str], *, site: Optional[str] = None, raw: bool, until_done: bool, count: int, duration: float,
                 connect: list[str], explicit_expr: bool) -> None:
        from acquire.live.status import CellView

        self.bus = bus
        self.site_prefix = f"remaster/{site}/" if site else None
        self.raw = raw
        self.until_done = until_done
        self.count = count
        self.connect = connect
        self.explicit_expr = explicit_expr
        self.t_start = time.monotonic()
        self.t_end = self.t_start + duration if duration > 0 else None
        self.received = 0
        self.heard = False  # anything (message or token) arrived: we are connected, whatever zenoh says
        self.warned_connect = self.warned_cell = False
        self.view: Optional[CellView] = CellView(cell) if cell else None
        self.live = None

    # -------------------------------------------------------------------- discovery
    def _choose(self, cell: str) -> None:
        from acquire.live.status import CellView

        self.view = CellView(cell)
        typer.echo(f"found cell {cell} via {', '.join(self.connect)}", err=True)
        if not self.raw and sys.stdout.isatty():
            from rich.console import Console
            from rich.live import Live

            self.live = Live(self.view.renderable(self._footer()), console=Console(), refresh_per_second=4,
                             transient=False)
            self.live.start()

    def _footer(self) -> str:
        return "Ctrl-C to quit" + ("; exits when the run ends" if self.until_done else "")

    # -------------------------------------------------------------------- loop
    def loop(self, inbox: "queue.Queue") -> None:
        from acquire.live.status import cell_of

        while self.count == 0 or self.received < self.count:
            now = time.monotonic()
            if self.t_end is not None and now >= self.t_end:
                return
            try:
                kind, k, value = inbox.get(timeout=0.1)
            except queue.Empty:
                self._idle(now)
                continue
            self.heard = True
            k_full, k = k, self._local(k)
            if k is None:
                continue
            if self.view is None and not self.explicit_expr:
                c = cell_of(k)
                if c is None:
                    continue
                if kind == "alive" and not value:
                    continue
                self._choose(c)
            if kind == "alive":
                lines = self.view.alive(k, bool(value)) if self.view is not None else []
                if not self.raw:
                    self._show(lines)
                continue
            if self.raw:
                if self.view is not None and not self.explicit_expr and cell_of(k) != self.view.cell:
                    continue
                typer.echo(format_line(k_full, value))  # type: ignore[arg-type]
                self.received += 1
                if self.view is not None:
                    self.view.feed(k, value)  # type: ignore[arg-type]
            else:
                lines = self.view.feed(k, value) if self.view is not None else []  # type: ignore[arg-type]
                if self.view is not None and cell_of(k) == self.view.cell:
                    self.received += 1
                self._show(lines)
            if self.until_done and self.view is not None and self.view.run_done:
                return

    def _local(self, k: str) -> Optional[str]:
        """A key as the cell view reads it: ``remaster/<site>/<cell>/…`` → ``remaster/<cell>/…``
        when watching a site (None: another site's key; the explicit raw stream keeps every key)."""
        if self.site_prefix is None:
            return k
        if k.startswith(self.site_prefix):
            return "remaster/" + k[len(self.site_prefix):]
        return k if self.explicit_expr else None

    def _show(self, lines: list[str]) -> None:
        if self.live is not None:
            self.live.update(self.view.renderable(self._footer()))
        else:
            for line in lines:
                typer.echo(line)

    def _idle(self, now: float) -> None:
        if self.live is not None:
            self.live.update(self.view.renderable(self._footer()))  # ages tick on
        if self.heard:
            return
        waited = now - self.t_start
        if not self.warned_connect and waited > NOT_CONNECTED_AFTER_S and not _connected(self.bus):
            typer.echo(f"not connected to {', '.join(self.connect)} yet; waiting for the run or the daemon…", err=True)
            self.warned_connect = True
        elif not self.warned_cell and waited > NO_CELL_AFTER_S and _connected(self.bus):
            typer.echo(f"connected to {', '.join(self.connect)}; nothing published yet — waiting for a run", err=True)
            self.warned_cell = True

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()


def register(app: typer.Typer) -> None:
    """Add the ``watch`` sub-command to ``app``."""
    app.command("watch")(watch)
