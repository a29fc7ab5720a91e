"""The ``acquire`` console script's target, kept free of imports.

pip writes the script as ``from acquire.entry import main`` followed by ``main()`` under
``if __name__ == "__main__"``. An RSI or FRI commander's exchange process is started with
multiprocessing ``spawn``, which re-runs the parent's main script in the child before the child
can answer the robot: with the command line's own module there, every ``connect`` paid for
importing typer in the child (~60 ms quiet by ``python -X importtime``; the exchange's start as a
whole, ~0.3-0.5 s quiet and over a second beside CPU hogs, is in tests/bench/bench_exchange_start.py).
"""


def main() -> None:
    """Run the ``acquire`` command line (``acquire.cli.main``)."""
    from acquire.cli import main as cli_main

    cli_main()
