"""The ``acquire`` command line. Only this entry point configures logging.

Start-up is kept short: a sub-command's module (``acquire/commands/<name>.py``) is imported only
when that sub-command runs (or shows its own ``--help``). ``acquire --help`` lists the commands
from the :data:`COMMANDS` table without importing any of them, so it never pays for numpy,
scipy or Zenoh. A module listed here must expose ``register(app)`` adding exactly
the commands the table names for it, with the table's help as their first docstring line
(tests/acquire/test_cli_startup.py checks both).
"""

from __future__ import annotations

import importlib
from typing import Any, NamedTuple

import typer
from typer.core import TyperCommand, TyperGroup, TyperOption

from acquire.live.console import configure_logging


class CommandSpec(NamedTuple):
    """Where a sub-command lives and the one line ``acquire --help`` shows for it."""

    module: str
    help: str


#: Sub-commands in ``--help`` order: name → module with ``register(app)`` and its short help.
COMMANDS: dict[str, CommandSpec] = {
    "run": CommandSpec("acquire.commands.run", "Run the measurement plan: move, settle, measure every configuration; log; fit."),
    "poses": CommandSpec("acquire.commands.poses", "Plan the paper's poses: Latin hypercube aimed at the sensor, every IK solution of each."),
    "fit": CommandSpec("acquire.commands.fit", "Fit the joint zero-offsets (and the sensor registration and σ) to measured marker positions."),
    "select": CommandSpec("acquire.commands.select", "Choose m configurations from a candidate set with the IOOPS exchange algorithm."),
    "sim": CommandSpec("acquire.commands.sim", "Run the fake devices of a simulated cell on 127.0.0.1 until Ctrl-C; inject faults on demand."),
    "verify": CommandSpec("acquire.commands.verify", "Measure fresh configurations after the offsets were entered; compare with the prediction."),
    "move": CommandSpec("acquire.commands.move", "Move the robot to one joint target, safely, and print where it settled."),
    "daemon": CommandSpec("acquire.commands.daemon", "Run the cell's service: Zenoh router, devices, control queries, systemd notification."),
    "status": CommandSpec("acquire.commands.daemon", "Show the daemon's and the current run's state."),
    "start": CommandSpec("acquire.commands.daemon", "Start a run on the daemon (the robot will move)."),
    "pause": CommandSpec("acquire.commands.daemon", "Pause the run after its current configuration."),
    "resume": CommandSpec("acquire.commands.daemon", "Resume a paused run (the robot will move)."),
    "abort": CommandSpec("acquire.commands.daemon", "Stop the run safely now; its log is closed."),
    "confirm": CommandSpec("acquire.commands.daemon", "Socket calibration: the ball sits in the socket, record now (the robot will move on)."),
    "runs": CommandSpec("acquire.commands.daemon", "List the runs in the daemon's state folder."),
    "station": CommandSpec("acquire.commands.station", "Keep every cell's finished runs: pull, verify, store, confirm; scrub the archive; robot states."),
    "fleet": CommandSpec("acquire.commands.fleet", "Show every robot of the archive and its state; write the fleet's pages."),
    "router": CommandSpec("acquire.commands.router", "Route the site's Zenoh traffic (cells, station, operators): the router where no zenohd runs."),
    "token": CommandSpec("acquire.commands.token", "Make a control client's token (mode 0600) and print the daemon's configuration lines."),
    "watch": CommandSpec("acquire.commands.watch", "Show a live run or daemon (found on the bus by itself): progress, last sample, warnings."),
    "examples": CommandSpec("acquire.commands.examples", "List the packaged example plans, robot models, simulated cells and Foxglove layout (or copy a plan)."),
    "compensate": CommandSpec("acquire.commands.compensate", "Pre-correct Cartesian targets so the controller's nominal arm lands where the calibrated model says."),
    "model": CommandSpec("acquire.commands.model", "Robot models in and out of URDF (import a vendor URDF, export a calibrated model)."),
}

#: The command modules, in table order (each once).
COMMAND_MODULES = list(dict.fromkeys(spec.module for spec in COMMANDS.values()))


def plain_switches(command: Any, ctx: Any) -> None:
    """Show on/off switches as ``--fake``, not ``--fake <bool>``: a flag takes no value, so its
    help row gets no type column (the help option's included); a counter (``-v``, ``-vv``) neither
    a type nor its default 0."""
    params = list(getattr(command, "params", []))
    help_option = command.get_help_option(ctx) if hasattr(command, "get_help_option") else None
    if help_option is not None:
        params.append(help_option)
    for param in params:
        if not isinstance(param, TyperOption):
            continue
        if getattr(param, "count", False):  # -v, -vv: repeated, no value, no default worth showing
            param.metavar = ""
            param.show_default = False
        elif getattr(param, "is_flag", False):
            param.metavar = ""


def load_command(name: str, ctx: Any = None) -> Any:
    """Import the module of sub-command ``name`` and return its command object."""
    spec = COMMANDS[name]
    module = importlib.import_module(spec.module)
    sub = typer.Typer(add_completion=False)
    module.register(sub)
    group = typer.main.get_group(sub)
    command = group.commands.get(name)
    if command is None:
        raise RuntimeError(f"{spec.module}.register() added {sorted(group.commands)}, not {name!r}: fix "
                           "acquire.cli.COMMANDS")
    if ctx is not None:
        plain_switches(command, ctx)
    return command


class _Listed(TyperCommand):
    """A placeholder that carries a sub-command's name and short help for ``acquire --help``."""


class LazyGroup(TyperGroup):
    """The root command: lists :data:`COMMANDS` from the table; loads one when it is invoked."""

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        for name, spec in COMMANDS.items():
            self.commands.setdefault(name, _Listed(name=name, help=spec.help, short_help=spec.help))

    def list_commands(self, ctx: Any) -> list[str]:
        return list(self.commands)

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Any, list[str]]:
        name, command, rest = super().resolve_command(ctx, args)
        if isinstance(command, _Listed):
            command = self.commands[name] = load_command(name, ctx)
        return name, command, rest

    def get_help_option(self, ctx: Any) -> Any:
        option = super().get_help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option


app = typer.Typer(
    cls=LazyGroup,
    no_args_is_help=True,
    add_completion=False,
    help="remaster: in-situ robot remastering — plan, measure, fit, prove.",
)


@app.callback()
def _root() -> None:
    """remaster: in-situ robot remastering — plan, measure, fit, prove."""


def main() -> None:
    configure_logging()
    app()


if __name__ == "__main__":
    main()
