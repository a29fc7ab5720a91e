"""``acquire daemon`` (the service) and its thin clients ``acquire status|start|pause|resume|abort|runs``.

Examples::

    acquire daemon --config /etc/remaster/daemon.yaml
    acquire status --cell lab1
    acquire start fixtures/plans/example.yaml --cell lab1 --client operator --token-file ~/.config/remaster/token
    acquire start --inline my-plan.yaml --cell lab1 --client operator --token-file …
    acquire pause|resume|abort --cell lab1 --client operator --token-file …
    acquire runs --cell lab1
    acquire status --site plant-a --cell c7 --connect tls/router.plant-a:7447 --tls-ca …   # a cell with `site:`

On the cell PC, without ``--client`` or ``--connect``, a client talks to the daemon's control
socket (``--socket``, default ``$REMASTER_CONTROL_SOCKET`` or ``/run/remaster/control.sock``;
``acquire.daemon.control_socket``): the OS lets only the operators' group in and tells the daemon who
asks, so no token is needed (``acquire abort`` is all it takes); the client checks first that the
daemon's account is listening there (``SO_PEERCRED``). Otherwise they connect to the daemon's Zenoh
router (``--connect``, default with ``--client``: ``unixsock-stream//run/remaster/zenoh.sock``); a
remote daemon needs ``tls/host:7447`` with ``--tls-ca``, ``--tls-cert`` and ``--tls-key`` (mTLS).
A client sends credentials, and any operation beyond ``status`` and ``runs``, only to a listener
it has authenticated (``acquire.daemon.local_sockets.credential_endpoint_problem``): a Unix socket
that only root or the daemon's account (``REMASTER_DAEMON_USER``, default ``remaster``) can have
made, or TLS with the CA that signed the daemon's certificate — never plain ``tcp/``, where any
local process can listen while the daemon is down. Credentials:
``--client NAME`` and the token from
``--token-file`` (made by ``acquire token new``; refused when the group or others may read it, as
ssh refuses an unprotected key) or the environment (``REMASTER_CLIENT``, ``REMASTER_TOKEN``); a
weak token is refused. Each operation is a SCRAM-SHA-256 exchange (``acquire.daemon.control_auth``) in
which the daemon proves itself before its reply is believed. Replies are printed
as JSON with ``--json``, otherwise as a few readable lines. Exit status: 0 done, 2 bad usage or
bad request, 3 refused, 4 no daemon answered, 1 other failures.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Optional

import typer

log = logging.getLogger(__name__)

#: syslog priorities for the ``<N>`` prefix journald understands (sd-daemon(3)).
_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}


class JournalFormatter(logging.Formatter):
    """``<N>level name: message`` — journald reads the ``<N>`` prefix as the line's priority;
    every line of a multi-line message (tracebacks) carries it. The journal is the daemon's text
    log: it keeps the traceback of a foreseen failure too (a terminal shows it in one line)."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        prio = _PRIORITY.get(record.levelno, 6 if record.levelno < logging.WARNING else 3)
        return "\n".join(f"<{prio}>{line}" for line in text.splitlines())


def configure_daemon_logging(verbose: bool) -> None:
    """The CLI's logging (acquire.live.console.configure_logging) plus journald priorities when stderr
    is connected to the journal (``JOURNAL_STREAM`` set). ``REMASTER_LOG_LEVEL`` overrides."""
    from acquire.live.console import configure_logging

    configure_logging(verbose)
    level = os.environ.get("REMASTER_LOG_LEVEL")
    if level:
        if level.upper() not in ("DEBUG", "INFO", "WARNING", "ERROR"):
            raise typer.BadParameter(f"REMASTER_LOG_LEVEL must be DEBUG, INFO, WARNING or ERROR, given {level!r}")
        logging.getLogger().setLevel(level.upper())
    if os.environ.get("JOURNAL_STREAM"):
        for handler in logging.getLogger().handlers:
            handler.setFormatter(JournalFormatter("%(levelname)s %(name)s: %(message)s"))


def daemon(
    config: Path = typer.Option(..., "--config", help="Daemon configuration YAML (see systemd/daemon.yaml.example)."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
) -> None:
    """Run the cell's service: Zenoh router, devices, control queries, systemd notification."""
    from acquire.daemon.service import run_daemon
    from acquire.daemon.config import ConfigError, load_daemon_config

    configure_daemon_logging(verbose)
    try:
        cfg = load_daemon_config(config)
    except ConfigError as exc:
        log.error("configuration not valid:\n%s", exc)
        raise typer.Exit(2) from None
    sim = None
    if cfg.fake_cell is not None:  # the simulated cell, started here and handed over as any cell
        from acquire.commands.fake import daemon_cell

        try:
            sim = daemon_cell(cfg.fake_cell).start()
        except (ConfigError, ValueError, OSError) as exc:
            log.error("the simulated cell did not start: %s", exc)
            raise typer.Exit(1) from None
    try:
        status = run_daemon(cfg, cell=sim)
    finally:
        if sim is not None:
            sim.close()
    raise typer.Exit(status)


# ---------------------------------------------------------------------------------- clients
_CONNECT = typer.Option(None, "--connect", help="The daemon's Zenoh endpoint (default with --client: "
                        "unixsock-stream//run/remaster/zenoh.sock; without --client and --connect: the control "
                        "socket). Plain tcp/ is for status and runs without credentials only.")
_SOCKET = typer.Option(None, "--socket", help="The daemon's control socket (default: $REMASTER_CONTROL_SOCKET, "
                       "else /run/remaster/control.sock); used unless --client or --connect is given.")
DEFAULT_SOCKET = "/run/remaster/control.sock"
_CELL = typer.Option(None, "--cell", help="Cell id (default: $REMASTER_CELL).")
_SITE = typer.Option(None, "--site", help="The cell's plant site, for a daemon with `site:` (keys "
                     "remaster/<site>/<cell>/…; default: $REMASTER_SITE, else none).")
_CLIENT = typer.Option(None, "--client", help="Client name (default: $REMASTER_CLIENT).")
_TOKEN_FILE = typer.Option(None, "--token-file", help="File holding the client's token (else $REMASTER_TOKEN).")
_CA = typer.Option(None, "--tls-ca", help="CA certificate (PEM) that signed the daemon's certificate.")
_CERT = typer.Option(None, "--tls-cert", help="This client's certificate (PEM), for mTLS.")
_KEY = typer.Option(None, "--tls-key", help="This client's private key (PEM), for mTLS.")
_TIMEOUT = typer.Option(10.0, "--timeout", help="Seconds to wait for the daemon's reply (per round trip; two with credentials).")
_JSON = typer.Option(False, "--json", help="Print the reply as JSON.")


def _fail(message: str, code: int) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _call(op: str, request: dict | None, *, connect: Optional[str], cell: Optional[str], site: Optional[str],
          client: Optional[str],
          token_file: Optional[Path], tls_ca: Optional[Path], tls_cert: Optional[Path], tls_key: Optional[Path],
          timeout: float, as_json: bool, socket: Optional[Path] = None) -> dict:
    client = client or os.environ.get("REMASTER_CLIENT")
    if connect is None and client is None and token_file is None:
        reply = _call_socket(op, request, socket or Path(os.environ.get("REMASTER_CONTROL_SOCKET") or DEFAULT_SOCKET),
                             timeout)
    else:
        from acquire.daemon.local_sockets import DEFAULT_LOCAL_ENDPOINT

        reply = _call_zenoh(op, request, connect=connect or DEFAULT_LOCAL_ENDPOINT, cell=cell, site=site,
                            client=client, token_file=token_file, tls_ca=tls_ca, tls_cert=tls_cert,
                            tls_key=tls_key, timeout=timeout)
    if as_json:
        typer.echo(json.dumps(reply, indent=2, sort_keys=True))
    else:
        _print_reply(op, reply)
    return reply


def _call_socket(op: str, request: dict | None, path: Path, timeout: float) -> dict:
    from acquire.daemon.control import BadRequest, Conflict, ControlError, NoReply, Refused, Unverified
    from acquire.daemon.control_socket import SocketClient

    try:
        return SocketClient(path).call(op, request, timeout=timeout)
    except (Refused, Unverified) as exc:
        _fail(str(exc), 3)
    except NoReply as exc:
        _fail(f"{exc} (or give --connect / --client to use Zenoh)", 4)
    except (BadRequest, Conflict) as exc:
        _fail(str(exc), 2)
    except (ControlError, OSError) as exc:
        _fail(str(exc), 1)
    raise AssertionError("unreachable")


def _call_zenoh(op: str, request: dict | None, *, connect: str, cell: Optional[str], site: Optional[str],
                client: Optional[str], token_file: Optional[Path], tls_ca: Optional[Path],
                tls_cert: Optional[Path], tls_key: Optional[Path], timeout: float) -> dict:
    from acquire.live.bus import Bus, BusError, is_loopback_endpoint
    from acquire.daemon.control import BadRequest, Conflict, ControlClient, ControlError, NoReply, Refused, Unverified

    cell = cell or os.environ.get("REMASTER_CELL")
    if not cell:
        _fail("give --cell (or set REMASTER_CELL)", 2)
    site = site or os.environ.get("REMASTER_SITE") or None
    from acquire.live.bus import BusConfigError, key

    try:
        key(cell, "x", site=site)  # validates the cell and site ids
    except BusConfigError as exc:
        _fail(f"--cell/--site: {exc}", 2)
    from acquire.daemon.tokens import TokenFileError, WeakToken, check_token, read_token_file

    token, source = None, "REMASTER_TOKEN"
    if token_file is not None:
        source = "--token-file"
        try:
            token = read_token_file(token_file)
        except TokenFileError as exc:
            _fail(f"--token-file: {exc}", 2)
    else:
        token = os.environ.get("REMASTER_TOKEN")
    if token:
        try:
            check_token(token, (client or "", cell))  # the client's name and the cell are known words too
        except WeakToken as exc:
            _fail(f"{source}: {exc}", 2)
    if client and not token:
        _fail(f"client {client!r} needs a token (--token-file or REMASTER_TOKEN; make one with "
              "`acquire token new`)", 2)
    if token and not client:
        _fail("a token needs --client (or REMASTER_CLIENT)", 2)
    from acquire.daemon.control import OPERATIONS
    from acquire.daemon.local_sockets import credential_endpoint_problem, socket_path_of, trusted_uids

    problem = credential_endpoint_problem(connect, tls_ca=tls_ca, trusted=trusted_uids())
    if problem and (token or OPERATIONS[op] != "observe"):  # before a byte is sent
        what = "credentials" if token else f"{op} (its reply could come from anyone)"
        path = socket_path_of(connect)
        _fail(f"--connect {connect}: not sending {what}: {problem}; nothing was sent",
              4 if path and not os.path.lexists(path) else 2)
    tls = {}
    if tls_ca is not None:
        tls = {"root_ca_certificate": str(tls_ca), "verify_name_on_connect": True}  # the daemon's name, too
        if (tls_cert is None) != (tls_key is None):
            _fail("give both --tls-cert and --tls-key, or neither", 2)
        if tls_cert is not None:
            tls.update(connect_certificate=str(tls_cert), connect_private_key=str(tls_key), enable_mtls=True)
    config = {"mode": "client", "connect": [connect], "zenoh": {"transport/link/tls": tls} if tls else {}}
    try:
        with Bus(cell, config=config, listen_loopback_only=is_loopback_endpoint(connect), site=site) as bus:
            cc = ControlClient(bus.session, cell, client=client, token=token, site=site)
            reply = cc.call(op, request, timeout=timeout)
    except Unverified as exc:
        _fail(str(exc), 3)
    except Refused as exc:
        _fail(str(exc), 3)
    except NoReply as exc:
        _fail(str(exc) + ("" if site else "; a daemon with `site:` answers only under remaster/<site>/<cell>/…: "
                          "give --site"), 4)
    except (BadRequest, Conflict) as exc:
        _fail(str(exc), 2)
    except (ControlError, BusError) as exc:
        _fail(str(exc), 1)
    if not cc.last_reply_verified:
        typer.echo("note: reply not authenticated (no credentials given): it may not come from the daemon",
                   err=True)
    return reply


def _print_reply(op: str, reply: dict) -> None:
    if op == "status":
        typer.echo(f"cell {reply['cell']}: daemon {reply['daemon']}, "
                   f"{'healthy' if reply['healthy'] else 'UNHEALTHY: ' + reply['health']}, "
                   f"devices {', '.join(reply['devices']) or 'none'}{' (fake)' if reply.get('fake') else ''}")
        rss = (reply.get("memory") or {}).get("rss_kb")
        if rss is not None:
            typer.echo(f"up {reply['uptime_s']:.0f} s, resident memory {rss / 1024:.0f} MiB")
        run = reply.get("run")
        if run:
            eta = run.get("eta_s")
            typer.echo(f"run {run['run_id']}: {run['state']} {run['done']}/{run['total']} "
                       f"(failed {run['failed']}, skipped {run['skipped']}"
                       f"{f', eta {eta:.0f} s' if isinstance(eta, (int, float)) else ''}); log {run.get('log')}")
        else:
            typer.echo("no run")
    elif op == "runs":
        for r in reply["runs"]:
            typer.echo(f"{r['run_id']}  {r['modified']}  {r['bytes']:>10} B"
                       f"{'  (current)' if r['current'] else ''}{'  result' if r['result'] else ''}")
        if not reply["runs"]:
            typer.echo("no runs")
    else:
        typer.echo(" ".join(f"{k} {v}" for k, v in reply.items() if k != "ok"))


def status(connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
           token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
           tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON) -> None:
    """Show the daemon's and the current run's state."""
    _call("status", None, **locals())


def runs(connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
         token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
         tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON) -> None:
    """List the runs in the daemon's state folder."""
    _call("runs", None, **locals())


def start(
    plan: Optional[str] = typer.Argument(None, help="Plan path ON THE CELL PC (inside the daemon's plan_dirs)."),
    inline: Optional[Path] = typer.Option(None, "--inline", help="Send this local plan file's text instead."),
    resume: Optional[str] = typer.Option(None, "--resume", help="Run id to resume (its log in the state folder)."),
    connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
    token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
    tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON,
) -> None:
    """Start a run on the daemon (the robot will move)."""
    if (plan is None) == (inline is None):
        _fail("give a plan path on the cell PC, or --inline FILE", 2)
    request: dict = {"plan": plan} if plan is not None else {}
    if inline is not None:
        try:
            request["plan_text"] = inline.read_text(encoding="utf-8")
        except OSError as exc:
            _fail(f"cannot read --inline {inline}: {exc.strerror or exc}", 2)
    if resume:
        request["resume"] = resume
    _call("start", request, connect=connect, socket=socket, cell=cell, site=site, client=client, token_file=token_file, tls_ca=tls_ca,
          tls_cert=tls_cert, tls_key=tls_key, timeout=timeout, as_json=as_json)


def pause(connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
          token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
          tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON) -> None:
    """Pause the run after its current configuration."""
    _call("pause", None, **locals())


def resume(connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
           token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
           tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON) -> None:
    """Resume a paused run (the robot will move)."""
    _call("resume", None, **locals())


def abort(reason: str = typer.Option("aborted by operator", "--reason", help="Why (goes into the log)."),
          connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
          token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
          tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON) -> None:
    """Stop the run safely now; its log is closed."""
    _call("abort", {"reason": reason}, connect=connect, socket=socket, cell=cell, site=site, client=client, token_file=token_file,
          tls_ca=tls_ca, tls_cert=tls_cert, tls_key=tls_key, timeout=timeout, as_json=as_json)


def confirm(connect: Optional[str] = _CONNECT, socket: Optional[Path] = _SOCKET, cell: Optional[str] = _CELL, site: Optional[str] = _SITE,
           client: Optional[str] = _CLIENT,
            token_file: Optional[Path] = _TOKEN_FILE, tls_ca: Optional[Path] = _CA, tls_cert: Optional[Path] = _CERT,
            tls_key: Optional[Path] = _KEY, timeout: float = _TIMEOUT, as_json: bool = _JSON) -> None:
    """Socket calibration: the ball sits in the socket, record now (the robot will move on)."""
    _call("confirm", None, **locals())


def register(app: typer.Typer) -> None:
    """Add ``daemon`` and its clients to ``app``."""
    app.command("daemon")(daemon)
    for fn in (status, start, pause, resume, abort, confirm, runs):
        app.command(fn.__name__)(fn)
