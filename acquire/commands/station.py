"""``acquire station --config FILE``: the plant's station service (``acquire.station.service``).

Finds the cells through their daemons' liveliness tokens, pulls every finished run over the
SCRAM-authenticated archive operations, verifies and stores it under the archive's robot/date
tree, adds it to the robot's history with a drift verdict, and confirms it to the cell. Runs
under systemd (``systemd/remaster-station.service``, ``Type=notify``). Exit status 0 after a clean
stop, 2 for a bad configuration or token file, 1 when the session cannot be opened.
"""

from __future__ import annotations

import signal
from pathlib import Path

import typer


def station(
    config: Path = typer.Option(..., "--config", help="The station's configuration (see acquire.station.config)."),
    once: bool = typer.Option(False, "--once", help="Wait for cells for --wait seconds, sync them once, exit."),
    wait: float = typer.Option(5.0, "--wait", help="With --once: seconds to discover cells first."),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="Debug logging."),
) -> None:
    """Keep every cell's finished runs: discover, pull, verify, store, confirm; check drift."""
    import logging
    import time

    from acquire.bus import BusError
    from acquire.cli import configure_logging
    from acquire.sdnotify import SdNotifier
    from acquire.station.config import load_station_config
    from acquire.station.service import Station
    from acquire.tokens import TokenFileError, WeakToken
    from calib.io.yamlfile import ConfigError

    configure_logging(verbose)
    log = logging.getLogger("acquire.station")
    try:
        cfg = load_station_config(config)
        st = Station(cfg)
    except (ConfigError, TokenFileError, WeakToken, OSError) as exc:
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
            st.run()
            notifier.notify(STOPPING=1)
    except BusError as exc:
        log.error("%s", exc)
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.command("station")(station)
