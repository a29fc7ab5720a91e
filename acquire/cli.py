"""The ``acquire`` command line. Only this entry point configures logging."""

from __future__ import annotations

import importlib
import logging
import sys

import typer

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="remaster: in-situ robot remastering — plan, measure, fit, prove.",
)

#: Sub-command modules, each with ``register(app)``. Order is the order of ``--help``.
COMMAND_MODULES = [
    "acquire.commands.run",
    "acquire.commands.poses",
    "acquire.commands.fit",
    "acquire.commands.select",
    "acquire.commands.sim",
    "acquire.commands.move",
    "acquire.commands.daemon",
    "acquire.commands.watch",
    "acquire.commands.examples",
]


def configure_logging(verbose: bool = False) -> None:
    """One line per event; colour-free when not on a terminal (journald friendly)."""
    level = logging.DEBUG if verbose else logging.INFO
    fmt = "%(levelname)s %(name)s: %(message)s"
    if sys.stderr.isatty():
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level, format=fmt, stream=sys.stderr, force=True)


@app.callback()
def _root() -> None:
    """remaster: in-situ robot remastering — plan, measure, fit, prove."""


for _name in COMMAND_MODULES:
    importlib.import_module(_name).register(app)


def main() -> None:
    configure_logging()
    app()


if __name__ == "__main__":
    main()
