"""``acquire router --config FILE``: the site's Zenoh router as its own service
(``acquire.station.router``; unit ``systemd/remaster-router.service``). Exit 0 after a clean stop,
2 for a bad configuration, 1 when the session cannot be opened (e.g. the port is taken)."""

from __future__ import annotations

import signal
from pathlib import Path

import typer


def router(
    config: Path = typer.Option(..., "--config", help="The router's configuration (acquire.station.router)."),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="Debug logging."),
) -> None:
    """Route the site's Zenoh traffic (cells, station, operators): the router where no zenohd runs."""
    import logging
    import threading

    from acquire.live.bus import BusError
    from acquire.live.console import configure_logging
    from acquire.daemon.sdnotify import SdNotifier
    from acquire.station.router import load_router_config, serve
    from calib.io.yamlfile import ConfigError

    configure_logging(verbose)
    try:
        cfg = load_router_config(config)
    except (ConfigError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    notifier = SdNotifier()
    try:
        serve(cfg, stop, on_tick=notifier.watchdog,
              on_ready=lambda locators: notifier.ready(f"routing on {', '.join(locators)}"))
    except BusError as exc:
        logging.getLogger("acquire.router").error("%s", exc)
        raise typer.Exit(1)
    notifier.stopping("stopping")


def register(app: typer.Typer) -> None:
    app.command("router")(router)
