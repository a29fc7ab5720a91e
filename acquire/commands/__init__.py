"""One module per ``acquire`` sub-command; each exposes ``register(app: typer.Typer)``."""
