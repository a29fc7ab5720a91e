"""The station's configuration file (``/etc/remaster/station.yaml``), validated by pydantic.

::

    archive: /var/lib/remaster-station/archive   # the archive root (acquire.station.archive)
    client: station                    # the name the cells know the station by (auth.clients)
    token_file: /etc/remaster/station.token   # its token (mode 0600; `acquire token new`)
    cells:                             # every cell the station archives, and its robot
      plant-a/c7: {robot_serial: KR6-0815, token_file: /etc/remaster/c7.token}
    sites: [plant-a]                   # optional: only these sites' cells (default: every cell)
    zenoh:
      mode: client                     # a client of the site's router (zenohd or `acquire router`)
      listen: []
      connect: [unixsock-stream//run/remaster-router/zenoh.sock]   # the router on this host
      router_user: remaster-router     # the account the router runs as (owner of that socket)
      zenoh: {}                        # TLS / access control / user-password, Zenoh config paths → values
      socket_group: null               # a station that listens on a Unix socket itself: who may connect
      allow_unauthenticated_listen: false   # see below
    poll_s: 60                         # how often each cell is asked (cells also announce their runs)
    sync_workers: 8                    # cells synced at once
    cell_timeout_s: 10                 # a cell's reply to one operation, at most
    chunk_bytes: 2097152               # bytes per transfer chunk (≤ 4 MiB)
    limits: {max_file_bytes: 17179869184, max_run_bytes: 34359738368, reserve_free_bytes: 2147483648}
    scrub_hours: 24                    # re-verify the whole archive this often (0: only on demand)
    drift: {alpha: 0.01, accuracy_limit_mm: null, accuracy_factor: 1.5, check_interval_days: 30,
            check_max_configurations: 12, auto_enter: true}
    alert: {command: [/usr/local/bin/page-maintenance], webhook: null, timeout_s: 10}

**Who a cell is.** The station believes a cell only through the SCRAM exchange, and files its
runs under the serial ``cells`` binds to it — never under the serial the cell reports (a
listing that names another serial is refused and logged). A cell missing from ``cells`` is not
archived (its state says so). A cell with its own ``token_file`` is the only holder of the keys
that answer for it; cells without one share ``token_file``, and each of them can then answer as
any other (the station warns at start).

Each cell's daemon lists the station in ``auth.clients`` with permission ``archive``.

**The station sends its SCRAM messages only to a router it has authenticated**
(``StationZenoh.connect_problems``, reported at the endpoint's line, before anything is sent):
each ``connect`` endpoint must be

- ``unixsock-stream/<absolute path>`` whose socket, folders and links only root, the station's own
  account or ``router_user`` can have made (``acquire.daemon.local_sockets.check_socket_path``:
  the router's ``/run/remaster-router``, systemd's ``RuntimeDirectory``, mode 0755) — the router
  on the station's host; or
- ``tls/`` or ``quic/`` with ``transport/link/tls/root_ca_certificate`` in ``zenoh`` (the CA that
  signed the router's certificate) — a router on another host.

Never plain ``tcp/`` (or ``udp/``, ``ws/``), loopback included: nothing tells the station who
listens there, and while the router is down any local process can, receive the station's
client-finals and answer in the router's place. A socket that does not exist yet (the router is
starting) passes the file check and is checked again when the station opens its session.

**A listener other accounts or hosts can reach is protected by Zenoh itself**
(``ZenohLinks.security_problems``, reported at the endpoint's line): a ``unixsock-stream``
listener is protected by its file's permissions (``socket_group``: its members may connect, mode
0660; none: this account only, mode 0600; its folder must not be writable by others); every
other ``listen`` endpoint — a loopback one too: any local account could join and receive the
station's queries — needs one of

- a ``tls/`` or ``quic/`` endpoint with ``transport/link/tls`` holding ``listen_certificate``,
  ``listen_private_key``, ``root_ca_certificate`` and ``enable_mtls: true`` (mutual TLS: only
  hosts with a certificate of the plant's CA join);
- ``access_control`` with ``enabled: true`` and ``default_permission: deny``;
- ``transport/auth/usrpwd`` with a ``dictionary_file`` (Zenoh's user-password authentication;
  over ``tcp/`` it authenticates but does not encrypt — prefer ``tls/``);

or ``allow_unauthenticated_listen: true``, which says in the file that anyone who can reach the
port may join the station's router (the archive itself still believes only SCRAM-signed replies).
Zenoh paths may be given nested or as ``a/b/c`` keys (``transport/link/tls: {enable_mtls: true}``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from acquire.daemon.archive import MAX_CHUNK_BYTES
from acquire.daemon.local_sockets import Listener, UNIXSOCK, credential_endpoint_problem, socket_path_of, trusted_uids
from acquire.station.archive import Limits
from acquire.station.states import Policy
from calib.io.yamlfile import load_validated


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


_SECURE_PROTOCOLS = ("tls", "quic")
_CELL_ID = re.compile(r"^[A-Za-z0-9_.-]+$")
_TLS = "transport/link/tls/"

#: Where the site's router (``acquire router``, systemd/remaster-router.service) listens for the
#: station on the station's host, and the account it runs as.
ROUTER_SOCKET = "/run/remaster-router/zenoh.sock"
ROUTER_ENDPOINT = f"{UNIXSOCK}/{ROUTER_SOCKET}"
ROUTER_USER = "remaster-router"
#: The router, as the station's checks of its ``connect`` endpoints name it.
ROUTER = Listener(
    "the router", ROUTER_SOCKET, "listen", "set zenoh.router_user (the account the router runs as)",
    f"zenoh.zenoh {_TLS}root_ca_certificate",
    f"On the router's host set zenoh.connect to [{ROUTER_ENDPOINT}]; for a router on another host "
    f"tls/HOST:7447 with zenoh.zenoh {_TLS}{{root_ca_certificate, connect_certificate, connect_private_key, "
    "enable_mtls: true}")


def flat_paths(tree: dict, prefix: str = "") -> dict[str, object]:
    """``{"transport/link/tls": {"enable_mtls": True}}`` → ``{"transport/link/tls/enable_mtls": True}``."""
    out: dict[str, object] = {}
    for k, v in tree.items():
        path = f"{prefix}{str(k).strip('/')}"
        if isinstance(v, dict) and v:
            out.update(flat_paths(v, path + "/"))
        else:
            out[path] = v
    return out


class ZenohLinks(_Strict):
    """A Zenoh session's endpoints and settings, and what protects each listener (the station's
    ``zenoh:`` section; the router's whole file, ``acquire.station.router``)."""

    mode: Literal["router", "peer", "client"] = "client"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list)
    zenoh: dict = Field(default_factory=dict)
    socket_group: str | None = Field(None, min_length=1, description=(
        "the group (name or number) of the unixsock-stream listeners' sockets, mode 0660: its members and root "
        "may connect; none: mode 0600, this service's account only"))
    allow_unauthenticated_listen: bool = Field(
        False, description="let a listener other than a Unix socket run without mTLS, access control or "
                           "user-password auth (anyone who can reach it may join: on loopback, any local account)")

    @property
    def socket_paths(self) -> list[Path]:
        """The socket files of the ``unixsock-stream`` listen endpoints."""
        return [Path(p) for p in map(socket_path_of, self.listen) if p is not None]

    def security_problems(self) -> list[tuple[tuple, str]]:
        """(field path, message) per listen endpoint that Zenoh would serve to another account or host."""
        from acquire.live.bus import is_loopback_endpoint

        flat = flat_paths(self.zenoh)
        mtls = all(flat.get(_TLS + k) for k in ("listen_certificate", "listen_private_key", "root_ca_certificate")) \
            and flat.get(_TLS + "enable_mtls") is True
        acl = flat.get("access_control/enabled") is True and flat.get("access_control/default_permission") == "deny"
        usrpwd = bool(flat.get("transport/auth/usrpwd/dictionary_file"))
        problems = []
        for i, ep in enumerate(self.listen):
            loc = ("zenoh", "listen", i)
            if not isinstance(ep, str) or "/" not in ep:
                problems.append((loc, f"{ep!r} is not a Zenoh endpoint like 'tls/0.0.0.0:7447'"))
                continue
            path = socket_path_of(ep)
            if path is not None:   # the kernel checks who connects: the file's owner, group and mode
                if not os.path.isabs(path):
                    problems.append((loc, f"the socket of {ep!r} must be an absolute path, e.g. {ROUTER_ENDPOINT}"))
                continue
            if self.allow_unauthenticated_listen or acl or usrpwd or (ep.split("/", 1)[0] in _SECURE_PROTOCOLS and mtls):
                continue
            who = "any account on this host" if is_loopback_endpoint(ep) else "other hosts"
            problems.append((loc, (
                f"endpoint {ep!r} is reachable from {who} without authentication (whoever joins receives the "
                "station's queries); allowed: unixsock-stream/<absolute path> (socket_group: who may connect), "
                "tls/ or quic/ endpoints with zenoh transport/link/tls {listen_certificate, listen_private_key, "
                "root_ca_certificate, enable_mtls: true}, access_control {enabled: true, default_permission: deny}, "
                "transport/auth/usrpwd {dictionary_file}, or (knowingly) allow_unauthenticated_listen: true")))
        return problems


class StationZenoh(ZenohLinks):
    """The station's session: by default a client of the router on its host, over its Unix socket."""

    connect: list[str] = Field(default_factory=lambda: [ROUTER_ENDPOINT])
    router_user: str = Field(ROUTER_USER, min_length=1, description=(
        "the account the router runs as: a unixsock-stream connect endpoint's socket and folders must belong to "
        "it, to root or to the station's own account"))

    def connect_problems(self, *, socket_up: bool) -> list[tuple[tuple, str]]:
        """(field path, message) per ``connect`` endpoint the station must not send a SCRAM message
        to (``acquire.daemon.local_sockets.credential_endpoint_problem``). ``socket_up``: a Unix
        socket must exist (when opening the session); else a missing one passes (the router may be
        starting) and is checked then."""
        ca = flat_paths(self.zenoh).get(_TLS + "root_ca_certificate")
        trusted = trusted_uids(self.router_user)
        problems = []
        for i, ep in enumerate(self.connect):
            path = socket_path_of(ep)
            if path is not None and not os.path.isabs(path):
                problem = f"the socket must be an absolute path, e.g. {ROUTER_ENDPOINT}"
            elif path is not None and not socket_up and not os.path.lexists(path):
                continue
            else:
                problem = credential_endpoint_problem(ep, tls_ca=ca, trusted=trusted, listener=ROUTER)
            if problem:
                problems.append((("zenoh", "connect", i), f"the station sends no credentials to {ep!r}: {problem}"))
        return problems

    def security_problems(self, *, socket_up: bool = False) -> list[tuple[tuple, str]]:
        """The listeners' problems (``ZenohLinks.security_problems``) and the ``connect`` endpoints'."""
        return super().security_problems() + self.connect_problems(socket_up=socket_up)


class DriftSection(_Strict):
    alpha: float = Field(0.01, gt=0, lt=0.5, description="false-alarm rate of the offset test")
    accuracy_limit_mm: float | None = Field(None, gt=0,
                                             description="absolute limit of the error as the robot runs (mm, held out)")
    accuracy_factor: float = Field(1.5, ge=1.0, description="else: limit = factor × what the robot runs with its reference entered")
    check_interval_days: float | None = Field(30.0, gt=0)
    check_max_configurations: int = Field(12, ge=0)
    auto_enter: bool = True

    def policy(self) -> Policy:
        return Policy(alpha=self.alpha, accuracy_limit_mm=self.accuracy_limit_mm, accuracy_factor=self.accuracy_factor,
                      check_interval_days=self.check_interval_days,
                      check_max_configurations=self.check_max_configurations, auto_enter=self.auto_enter)


class CellEntry(_Strict):
    robot_serial: str = Field(..., pattern=r"^[A-Za-z0-9_.-]+$", max_length=64)
    token_file: Path | None = None


class LimitsSection(_Strict):
    max_file_bytes: int = Field(Limits.max_file_bytes, ge=0)
    max_run_bytes: int = Field(Limits.max_run_bytes, ge=0)
    reserve_free_bytes: int = Field(Limits.reserve_free_bytes, ge=0)

    def limits(self) -> Limits:
        return Limits(self.max_file_bytes, self.max_run_bytes, self.reserve_free_bytes)


class AlertSection(_Strict):
    command: list[str] | None = Field(None, min_length=1, description="argv; the event as JSON on stdin")
    webhook: str | None = Field(None, pattern=r"^https?://", description="POSTed the event as JSON")
    timeout_s: float = Field(10.0, gt=0, le=300)


class StationConfig(_Strict):
    archive: Path
    client: str = Field("station", pattern=r"^[A-Za-z0-9_.-]+$")
    token_file: Path
    cells: dict[str, CellEntry] = Field(default_factory=dict)
    sites: list[str] | None = None
    zenoh: StationZenoh = StationZenoh()
    poll_s: float = Field(60.0, gt=0, le=3600)
    sync_workers: int = Field(8, ge=1, le=256)
    cell_timeout_s: float = Field(10.0, gt=0, le=600)
    chunk_bytes: int = Field(2 << 20, ge=1024, le=MAX_CHUNK_BYTES)
    limits: LimitsSection = LimitsSection()
    scrub_hours: float = Field(24.0, ge=0)
    drift: DriftSection = DriftSection()
    alert: AlertSection = AlertSection()

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        """Checks between fields, reported at the right line by ``load_validated``."""
        problems = self.zenoh.security_problems()
        for name in self.cells:
            parts = name.split("/")
            if len(parts) > 2 or not all(_CELL_ID.match(p) for p in parts):
                problems.append((("cells", name), f"{name!r} is not a cell: 'site/cell' or 'cell' "
                                 "(letters, digits, '_', '.', '-')"))
        return problems

    def cell(self, site: str, cell: str) -> CellEntry | None:
        """The configured entry of a cell (``site/cell``, or ``cell`` without a site)."""
        return self.cells.get(f"{site}/{cell}" if site else cell)


def load_station_config(path: Path) -> StationConfig:
    """The validated configuration (``ConfigError`` naming file, line, field); relative paths
    are taken from the file's folder."""
    cfg = load_validated(Path(path), StationConfig)
    base = Path(path).resolve().parent
    cfg.archive = base / cfg.archive
    cfg.token_file = base / cfg.token_file
    for entry in cfg.cells.values():
        if entry.token_file is not None:
            entry.token_file = base / entry.token_file
    return cfg
