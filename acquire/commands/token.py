"""``acquire token``: make a control client's token and the daemon's configuration lines for it.

Examples::

    acquire token new --client operator                  # → ~/.config/remaster/token (mode 0600)
    acquire token new --client viewer --out ./viewer.token
    acquire token new --client operator --force          # replace a token (e.g. one others could read)

``new`` writes 256 random bits (43 URL-safe characters) to the file with mode 0600 — refusing to
overwrite it without ``--force`` — and prints the ``scram:`` lines to paste under the client in
the daemon's configuration (``auth.clients``): salt, iterations, StoredKey and ServerKey, as an
RFC 5802 server stores them (acquire.daemon.control_auth). The token itself is never printed. Exit
status 0 done, 2 bad input (existing file, iterations too low).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

token_app = typer.Typer(no_args_is_help=True, add_completion=False,
                        help="Make a control client's token (mode 0600) and print the daemon's configuration lines.")


@token_app.command("new")
def new(
    client: str = typer.Option("operator", "--client", help="The client's name in the daemon's configuration."),
    out: Optional[Path] = typer.Option(None, "--out", help="Token file (default ~/.config/remaster/token)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing token file."),
    iterations: Optional[int] = typer.Option(None, "--iterations",
                                             help="PBKDF2 iterations (default 600000, at least 4096)."),
) -> None:
    """Write a new random token with mode 0600 and print the lines for the daemon's configuration."""
    import re

    from acquire.daemon.control_auth import DEFAULT_ITERATIONS, MIN_ITERATIONS, derive_credentials
    from acquire.daemon.tokens import DEFAULT_TOKEN_PATH, new_token, write_token_file

    iterations = DEFAULT_ITERATIONS if iterations is None else iterations
    if iterations < MIN_ITERATIONS:
        _fail(f"--iterations must be at least {MIN_ITERATIONS} (RFC 7677), given {iterations}")
    if not re.fullmatch(r"[a-z0-9_-]+", client):
        _fail(f"--client must match [a-z0-9_-]+ (as in the daemon's configuration), given {client!r}")
    path = (out or DEFAULT_TOKEN_PATH).expanduser()
    if path.exists() and not force:
        _fail(f"{path} exists; give --force to replace it (the old token stops working once the daemon's "
              "configuration holds the new lines)")
    token = new_token()
    creds = derive_credentials(token, iterations)
    try:
        write_token_file(path, token, force=force)
    except FileExistsError:
        _fail(f"{path} exists; give --force to replace it (the old token stops working once the daemon's "
              "configuration holds the new lines)")
    except OSError as exc:
        _fail(f"cannot write {path}: {exc.strerror or exc}")
    c = creds.config()
    typer.echo(f"# token written to {path} (mode 0600); use it with: --client {client} --token-file {path}")
    typer.echo("# paste under auth.clients in the daemon's configuration (root:remaster, mode 0640):")
    typer.echo(f"    - name: {client}\n"
               f"      scram:\n"
               f"        salt: \"{c['salt']}\"\n"
               f"        iterations: {c['iterations']}\n"
               f"        stored_key: \"{c['stored_key']}\"\n"
               f"        server_key: \"{c['server_key']}\"\n"
               f"      allow: [observe]   # add read, control, motion as this client needs")


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


def register(app: typer.Typer) -> None:
    """Add the ``token`` command group to ``app``."""
    app.add_typer(token_app, name="token")
