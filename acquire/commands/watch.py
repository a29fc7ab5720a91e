"""``acquire watch``: print a live run's events and samples (or any bus stream) as they arrive.

Example::

    acquire watch --cell cell1                       # everything of cell1: remaster/cell1/**
    acquire watch --cell cell1 'remaster/cell1/run/*/event'
    acquire watch --cell cell1 --connect tcp/127.0.0.1:7448 --count 10

Subscribes over Zenoh (loopback only) to the process that runs the cell — by default the one
listening on tcp/127.0.0.1:7447 — and prints one line per message: the key, then the JSON
payload (other payloads as their size and hex). It may be started before the run: it connects
when the run starts. Stops after ``--count`` messages, after ``--duration`` seconds, or on Ctrl-C.
"""

from __future__ import annotations

import json
import logging
import queue
import time
from typing import Optional

import typer

from acquire.bus import DEFAULT_ENDPOINT, Bus, BusConfigError, BusError, check_key_expr, key
from acquire.jsonpayload import PayloadError, decode_json

log = logging.getLogger(__name__)


def format_line(key_str: str, payload: bytes) -> str:
    """``<key> <compact JSON>``, or ``<key> <n> bytes: <hex…>`` for a non-JSON payload."""
    try:
        obj = decode_json(payload)
    except PayloadError:
        head = payload[:32].hex()
        return f"{key_str} {len(payload)} bytes: {head}{'…' if len(payload) > 32 else ''}"
    return f"{key_str} {json.dumps(obj, separators=(',', ':'), ensure_ascii=False)}"


def watch(
    key_expr: Optional[str] = typer.Argument(None, metavar="[KEYEXPR]", help="Key expression (default remaster/<cell>/**)."),
    cell: str = typer.Option("default", "--cell", help="Cell id ([a-z0-9_-]+)."),
    connect: list[str] = typer.Option([DEFAULT_ENDPOINT], "--connect", help="Endpoint of the run or daemon (repeatable)."),
    count: int = typer.Option(0, "--count", help="Exit after this many messages (0: no limit)."),
    duration: float = typer.Option(0.0, "--duration", help="Exit after this many seconds (0: no limit)."),
) -> None:
    """Print a live run's events and samples (any bus stream) by subscribing to it."""
    if count < 0:
        raise typer.BadParameter(f"must be >= 0, given {count}", param_hint="--count")
    if duration < 0:
        raise typer.BadParameter(f"must be >= 0 s, given {duration}", param_hint="--duration")
    try:
        cell_root = key(cell, "x")[: -len("/x")]  # validates the cell id
        expr = check_key_expr(key_expr) if key_expr else f"{cell_root}/**"
    except BusConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="KEYEXPR" if key_expr else "--cell") from exc
    inbox: "queue.Queue[tuple[str, bytes]]" = queue.Queue()
    try:
        bus = Bus(cell, config={"listen": [], "connect": list(connect)})
    except BusConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--connect / --cell") from exc
    except BusError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    received = 0
    t_end = time.monotonic() + duration if duration > 0 else None
    warned = False
    t_start = time.monotonic()
    with bus:
        bus.subscribe(expr, lambda k, p: inbox.put((k, p)))
        typer.echo(f"watching {expr} via {', '.join(connect)}", err=True)
        try:
            while count == 0 or received < count:
                if t_end is not None and time.monotonic() >= t_end:
                    break
                try:
                    k, payload = inbox.get(timeout=0.1)
                except queue.Empty:
                    if not warned and time.monotonic() - t_start > 2.0 and not bus.session.info.peers_zid():
                        typer.echo(f"not connected to {', '.join(connect)} yet; waiting for the run…", err=True)
                        warned = True
                    continue
                typer.echo(format_line(k, payload))
                received += 1
        except KeyboardInterrupt:
            typer.echo("", err=True)


def register(app: typer.Typer) -> None:
    """Add the ``watch`` sub-command to ``app``."""
    app.command("watch")(watch)
