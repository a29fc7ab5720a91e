"""``acquire station --config FILE``: the plant's station service (``acquire.station.service``);
``acquire station verify --config FILE``: read the whole archive back now (``acquire.station.scrub``).

The service finds the cells through their daemons' liveliness tokens and announcements, pulls
every finished run over the SCRAM-authenticated archive operations, verifies and stores it under
the serial the configuration binds to the cell, adds it to the robot's history, confirms it to
the cell, and re-verifies the archive every ``scrub_hours``. Runs under systemd
(``systemd/remaster-station.service``, ``Type=notify`` with a watchdog). Exit status 0 after a
clean stop, 2 for a bad configuration or token file, 1 when the session cannot be opened;
``verify`` exits 3 when anything is damaged or still awaits its copy from the cell.
"""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Optional

import typer

station_app = typer.Typer(add_completion=False, invoke_without_command=True,
                          help="Keep every cell's finished runs: pull, verify, store, confirm; scrub the archive; robot states.")


def _config(config: Optional[Path]):
    from acquire.station.config import load_station_config
    from calib.io.yamlfile import ConfigError

    if config is None:
        typer.echo("error: --config FILE is required (the station's configuration, e.g. /etc/remaster/station.yaml)",
                   err=True)
        raise typer.Exit(2)
    try:
        return load_station_config(config)
    except (ConfigError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2)


@station_app.callback()
def station(
    ctx: typer.Context,
    config: Optional[Path] = typer.Option(None, "--config", help="The station's configuration (acquire.station.config)."),
    once: bool = typer.Option(False, "--once", help="Wait for cells for --wait seconds, sync them once, exit."),
    wait: float = typer.Option(5.0, "--wait", help="With --once: seconds to discover cells first."),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="Debug logging."),
) -> None:
    """Keep every cell's finished runs: pull, verify, store, confirm; scrub the archive; robot states."""
    if ctx.invoked_subcommand is not None:
        return
    import logging
    import time

    from acquire.live.bus import BusError
    from acquire.live.console import configure_logging
    from acquire.daemon.sdnotify import SdNotifier
    from acquire.station.service import Station
    from acquire.daemon.tokens import TokenFileError, WeakToken

    configure_logging(verbose)
    log = logging.getLogger("acquire.station")
    cfg = _config(config)
    try:
        st = Station(cfg)
    except (TokenFileError, WeakToken, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2)
    notifier = SdNotifier()
    try:
        with st:
            if once:
                time.sleep(wait)
                n = st.sync_all()
                typer.echo(f"{n} run(s) archived from {len(st.cell_states())} cell(s)")
                return
            signal.signal(signal.SIGTERM, st.request_stop)
            signal.signal(signal.SIGINT, st.request_stop)
            notifier.ready(f"archive {cfg.archive}")
            st.run(on_tick=notifier.watchdog)
            notifier.stopping("stopping")
    except BusError as exc:
        log.error("%s", exc)
        raise typer.Exit(1)


@station_app.command("verify")
def verify(
    config: Optional[Path] = typer.Option(None, "--config", help="The station's configuration."),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="Debug logging."),
) -> None:
    """Read every archived file back against its sha256; quarantine what differs (the running
    station fetches it again from its cell). Exit 3 when anything is damaged or awaits repair."""
    from acquire.live.console import configure_logging
    from acquire.station.archive import Archive
    from acquire.station.scrub import scrub

    configure_logging(verbose)
    cfg = _config(config)
    report = scrub(Archive(cfg.archive, cfg.limits.limits()))
    typer.echo("\n".join(report.lines()))
    if not report.ok:
        raise typer.Exit(3)


def register(app: typer.Typer) -> None:
    app.add_typer(station_app, name="station")
