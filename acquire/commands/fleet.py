"""``acquire fleet --archive DIR [--json] [--html OUT]``: the plant's robots, their cells, and each
robot's state — calibrated, drifted, out of tolerance, never calibrated, check due
(``acquire.station.states``); ``--html`` writes ``index.html`` and a page per robot. ``enter SERIAL
RUN`` marks a run's offsets as entered into the controller (the reference for later drift checks;
refused for a run that cannot be one). Exit 0; 2 for a missing archive, an unknown robot/run or a
refused reference; 3 when any robot is drifted or out of tolerance (for a cron job or a monitoring
check)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

fleet_app = typer.Typer(add_completion=False, invoke_without_command=True,
                        help="Show every robot of the archive and its state; write the fleet's pages.")

_ARCHIVE = typer.Option(..., "--archive", help="The station's archive folder.")


@fleet_app.callback()
def fleet(
    ctx: typer.Context,
    archive: Optional[Path] = typer.Option(None, "--archive", help="The station's archive folder."),
    as_json: bool = typer.Option(False, "--json", help="The rows as JSON."),
    html: Optional[Path] = typer.Option(None, "--html", help="Write <serial>.html per robot into this folder."),
) -> None:
    """Show every robot of the archive and its state; write the fleet's pages."""
    if ctx.invoked_subcommand is not None:
        return
    from acquire.station.fleet import fleet_rows, needs_action, render_table, write_pages

    if archive is None or not archive.is_dir():
        typer.echo(f"error: --archive {archive}: no such folder (the station's `archive:` setting)", err=True)
        raise typer.Exit(2)
    rows = fleet_rows(archive)
    typer.echo(json.dumps(rows, indent=1) if as_json else render_table(rows))
    if html is not None:
        for p in write_pages(archive, html):
            typer.echo(f"wrote {p}", err=True)
    if needs_action(rows):
        raise typer.Exit(3)


@fleet_app.command("enter")
def enter(
    serial: str = typer.Argument(..., help="The robot's serial."),
    run_id: str = typer.Argument(..., help="The run whose offsets were entered into the controller."),
    archive: Path = _ARCHIVE,
    undo: bool = typer.Option(False, "--undo", help="Mark it as not entered."),
) -> None:
    """Mark a run's offsets as entered into the controller: the reference for later drift checks."""
    from acquire.station.fleet import read_policy
    from acquire.station.history import mark_entered

    try:
        mark_entered(archive, serial, run_id, not undo, read_policy(archive))
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2)
    typer.echo(f"{serial}: run {run_id} {'not ' if undo else ''}entered")


def register(app: typer.Typer) -> None:
    app.add_typer(fleet_app, name="fleet")
