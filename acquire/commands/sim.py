"""``acquire sim``: run a simulated cell — every fake device on loopback around one truth model.

Example::

    acquire sim --seed 3 --time-scale 1
    acquire sim --config fixtures/sim/default.yaml --fri-port 30200 --duration 600 --fri-version 2.7

A Sunrise cell's fake controller runs the robot application we ship: it opens the FRI session
and starts its joint-position overlay once the client answers in time, so any FRI client
(ours, KUKA's SDK examples) can be tried against it without code.

Prints where each fake listens (NatNet command port, tracker ``socket://`` URL) or sends (the
robot controller, to the commander's port), then runs until Ctrl-C or ``--duration`` wall
seconds. ``--show-truth`` also prints the hidden zero-offsets, to compare with a fit.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from calib.yamlfile import ConfigError
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH
from drivers.sim.launch import FRI_CLIENT_PORT, RSI_CLIENT_PORT, SimLaunch

#: Wall seconds between checks of the fakes (and of Ctrl-C).
POLL_S = 0.2


def sim(
    seed: Optional[int] = typer.Option(None, "--seed", min=0, help="Override the config's seed."),
    config: Path = typer.Option(DEFAULT_CONFIG_PATH, "--config",
                                help="Cell YAML (drivers/sim/config.py), or the name of a packaged cell (acquire examples)."),
    time_scale: float = typer.Option(1.0, "--time-scale", help="Simulated seconds per wall second (> 0)."),
    fri_port: int = typer.Option(FRI_CLIENT_PORT, "--fri-port", help="UDP port of the FRI client to send to."),
    rsi_port: int = typer.Option(RSI_CLIENT_PORT, "--rsi-port", help="UDP port of the RSI commander to send to."),
    rate: float = typer.Option(120.0, "--mocap-rate", help="NatNet frame rate, 120–360 Hz."),
    duration: float = typer.Option(3600.0, "--duration", help="Stop by itself after this many wall seconds."),
    show_truth: bool = typer.Option(False, "--show-truth", help="Also print the hidden zero-offsets."),
    fri_version: str = typer.Option(
        "1.15", "--fri-version", help="FRI message layout of the fake Sunrise: 1.15, 2.5 or 2.7."
    ),
) -> None:
    """Run the fake devices of a simulated cell on 127.0.0.1 until Ctrl-C."""
    if not time_scale > 0:
        raise typer.BadParameter(f"must be positive, given {time_scale}", param_hint="--time-scale")
    if not duration > 0:
        raise typer.BadParameter(f"must be positive, given {duration}", param_hint="--duration")
    try:
        if not config.exists():
            from calib.resources import find

            config = find("sim", str(config)) or config  # a packaged cell by name, e.g. "default"
        cell = SimCell.from_yaml(config, seed=seed, clock=SimClock(time_scale))
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    try:
        launch = SimLaunch(cell, fri_port=fri_port, rsi_port=rsi_port, mocap_rate_hz=rate, max_runtime_s=duration,
                           fri_version=fri_version)
        launch.start()
    except (ValueError, OSError) as exc:
        typer.echo(f"error: cannot start the simulated cell: {exc}", err=True)
        raise typer.Exit(2) from None
    try:
        for line in launch.describe():
            typer.echo(line)
        if show_truth:
            offsets = ", ".join(f"{a} {v:+.4f}" for a, v in zip(cell.truth.axis_names, cell.truth.offsets_deg))
            typer.echo(f"truth: zero-offsets (deg, controller convention): {offsets}")
        typer.echo(f"running for up to {duration:g} s; Ctrl-C to stop")
        deadline = time.monotonic() + duration
        try:
            while time.monotonic() < deadline:  # the cell's operator restarts a stopped RSI program
                time.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
        except KeyboardInterrupt:
            typer.echo("stopping")
    finally:
        launch.close()
    q = np.degrees(cell.joint_positions())
    typer.echo(f"stopped; final joints (deg) {np.round(q, 3).tolist()}")


def register(app: typer.Typer) -> None:
    """Add the ``sim`` sub-command to ``app``."""
    app.command("sim")(sim)
