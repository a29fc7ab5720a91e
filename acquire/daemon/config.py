"""The daemon's configuration file (``/etc/remaster/daemon.yaml``), validated by pydantic.

``load_daemon_config(path)`` returns a ``DaemonConfig`` or raises ``calib.io.yamlfile.ConfigError``
whose lines read ``file:line:col: field: message (given: …)``. Relative paths in the file are
taken from the file's folder. See ``systemd/daemon.yaml.example`` for a documented example.

Sections:

- ``cell``: the cell id, ``[a-z0-9_-]+`` — key expressions are ``remaster/<cell>/…``.
- ``site`` (optional): the plant site, ``[a-z0-9_-]+``, for a cell on a plant's router — key
  expressions are then ``remaster/<site>/<cell>/…`` (``acquire.live.bus``).
- ``robot_serial`` (optional): the serial number of the cell's robot; the station files this
  cell's runs under it (default: the cell id); the station checks it against its own ``cells:``.
- ``archive_keep_days`` (optional): delete a run from ``state_dir`` this many days after the
  station confirmed it, once the station re-verified its copy (``acquire.daemon.archive``).
- ``state_dir``: where runs are written (one folder per run; the systemd unit's StateDirectory).
- ``plan_dirs``: folders a ``start`` query may name a plan from (anything else is refused);
  inline plans are written to ``<state_dir>/plans/``.
- ``fake``: ``true`` or ``{sim_config, seed, time_scale}`` — ``acquire daemon`` starts the
  simulated cell (``acquire.commands.fake.daemon_cell``) instead of real devices and hands it to
  the daemon as its cell: every plan runs against its devices, described as any cell's.
- ``robot``, ``commander``, ``sensors``: the cell's real devices ({name, driver, url, markers,
  options}, as in a plan). The daemon holds them while idle (READY only once they are up; the
  watchdog watches the commander's real-time exchange) and hands them over to a run, which
  opens the drivers its plan names at the same addresses; they come back when the run ends.
- ``zenoh``: the session. ``mode`` router (the daemon is the cell's router) or peer;
  ``listen`` endpoints (loopback by default; on a cell PC the Unix socket
  ``unixsock-stream//run/remaster/zenoh.sock``, the one endpoint a client on the cell PC sends
  credentials to, after checking that only the daemon's account can listen there:
  ``acquire.daemon.local_sockets``); ``socket_group``: the group whose members may connect to
  those Unix sockets (mode 0660; none: the daemon's user only); ``connect``; ``tls`` (server
  certificate, client CA, ``enable_mtls``); ``access_control`` (Zenoh's own ACL block: rules, subjects with
  ``cert_common_names`` or ``usernames``, policies) passed through, plus one rule the daemon
  always adds (``control_guard``): the router forwards no query on the control keys to any
  other session, so only the daemon ever sees a client's SCRAM messages. Listening on
  anything but loopback is refused unless every remote endpoint is ``tls/``/``quic/`` with
  mTLS, or access control is enabled with ``default_permission: deny``.
- ``control_socket`` (optional; the shipped example sets it): ``{path, group, allow}`` — the
  local control plane, a Unix socket (``acquire.daemon.control_socket``) of mode 0660 owned by
  ``group``: its members (and root) act with the permissions ``allow`` (default: observe, read,
  control, motion) as the kernel reports them (SO_PEERCRED), with no token at all; nobody else
  can connect. Local operators use it; ``auth`` is for clients over the network.
- ``auth``: the clients allowed to act, by name: their SCRAM-SHA-256 keys (``scram``: salt,
  iterations ≥ 4096, StoredKey, ServerKey — never the token; ``acquire token new`` prints
  them), optional TLS common names, and the permissions they hold: ``observe`` (status, runs),
  ``read`` (plan texts), ``control`` (pause, abort), ``motion`` (start, resume), ``archive``
  (list finished runs, read their files, confirm them archived: the plant's station). A query with no
  or a wrong token holds only ``anonymous`` (default: observe). A file with clients must not be
  readable by other users (``check_config_mode``): its ServerKeys let a reader impersonate the
  daemon to clients (RFC 5802 §9; ``acquire.daemon.control_auth``).
- ``health``: the watchdog's limits. ``shutdown``: what SIGTERM does to a running run.
- ``live``: ``{enabled, host, port, allow_remote}`` — serve every run live to the Foxglove app
  (``acquire.live.foxglove_server.LiveServer``, Foxglove WebSocket protocol; off by default). The server
  binds to loopback unless ``allow_remote: true`` (it has no authentication: anyone who can
  connect watches the run).
"""

from __future__ import annotations

import base64
import binascii
import ipaddress
import logging
import os
import stat
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from acquire.daemon.control_auth import MIN_ITERATIONS, Credentials
from acquire.daemon.local_sockets import socket_path_of
from calib.io.yamlfile import ConfigError, CrossFieldChecked, load_validated

log = logging.getLogger(__name__)

__all__ = [
    "PERMISSIONS",
    "ConfigError",
    "DaemonConfig",
    "endpoint_is_loopback",
    "load_daemon_config",
]

#: Every permission a client can hold, weakest first.
PERMISSIONS = ("observe", "read", "control", "motion", "archive")
Permission = Literal["observe", "read", "control", "motion", "archive"]

_ID = r"^[a-z0-9_-]+$"
_LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
_SECURE_PROTOCOLS = ("tls", "quic")


def endpoint_is_loopback(endpoint: str) -> bool:
    """True if a Zenoh endpoint (``proto/host:port[#config]``) only accepts local connections:
    a loopback IP, ``localhost``, or a Unix-socket protocol. Raises ValueError if malformed."""
    proto, sep, rest = endpoint.partition("/")
    if not sep or not proto or not rest:
        raise ValueError(f"Zenoh endpoint {endpoint!r} is not of the form proto/address (e.g. tcp/127.0.0.1:7447)")
    if proto in _LOCAL_PROTOCOLS:
        return True
    address = rest.split("#", 1)[0].split("?", 1)[0]
    if address.startswith("["):
        host = address[1:].split("]", 1)[0]
    else:
        host = address.rsplit(":", 1)[0]
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name other than localhost: reachable from elsewhere


#: The daemon's control keys, with and without a site (``acquire.live.bus.control_key``).
CONTROL_KEY_EXPRS = ("remaster/*/control/**", "remaster/*/*/control/**")

_GUARD_RULE = "remaster: only the daemon answers control queries"
_EVERY_SESSION = "remaster: every session"


def control_guard(acl: dict[str, Any] | None) -> dict[str, Any]:
    """Zenoh's ``access_control`` block ``acl`` (None: none configured, everything allowed) with
    one more rule for every session: no ``query`` on the control keys leaves the router
    (egress), whatever the session declared (``**`` included). The daemon's queryables are in
    the router's own process, which Zenoh's ACL does not filter: it alone receives the control
    queries — a local account or a station can neither read a client's SCRAM client-final nor
    answer in the daemon's place. (A rule denying ``declare_queryable`` would not do: Zenoh
    matches a declaration against a rule only when the rule's key expression includes it.)"""
    base = dict(acl) if acl else {"enabled": True, "default_permission": "allow"}
    if not base.get("enabled", False):
        base = {**base, "enabled": True, "default_permission": "allow", "rules": [], "subjects": [], "policies": []}
    rule = {"id": _GUARD_RULE, "permission": "deny", "flows": ["egress"], "messages": ["query"],
            "key_exprs": list(CONTROL_KEY_EXPRS)}
    return {**base,
            "rules": [*base.get("rules", []), rule],
            "subjects": [*base.get("subjects", []), {"id": _EVERY_SESSION}],  # no property: matches every session
            "policies": [*base.get("policies", []), {"rules": [_GUARD_RULE], "subjects": [_EVERY_SESSION]}]}


def _guard_overridden(acl: dict[str, Any]) -> list[int]:
    """Indexes of the rules of an enabled ``default_permission: allow`` ACL that would override
    ``control_guard`` (Zenoh lets an allow rule win over a deny rule when the default is allow):
    allow rules for egress queries on keys that meet the control keys."""
    import zenoh

    if not acl.get("enabled") or acl.get("default_permission") != "allow":
        return []
    out = []
    for i, rule in enumerate(acl.get("rules") or []):
        if not isinstance(rule, dict) or rule.get("permission") != "allow":
            continue
        if "egress" not in (rule.get("flows") or ["ingress", "egress"]) or "query" not in (rule.get("messages") or []):
            continue
        try:
            keys = [zenoh.KeyExpr(k) for k in rule.get("key_exprs") or []]
        except Exception:  # noqa: BLE001 - zenoh reports a bad key expression when the session opens
            continue
        if any(k.intersects(zenoh.KeyExpr(c)) for k in keys for c in CONTROL_KEY_EXPRS):
            out.append(i)
    return out


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FakeCell(_Strict):
    """The simulated cell the daemon brings up instead of hardware."""

    sim_config: Path | None = Field(None, description="drivers/sim YAML; None: the packaged default cell (calib.io.resources)")
    seed: int = Field(0, ge=0)
    time_scale: float = Field(1.0, gt=0, description="simulated seconds per wall second")


class DeviceSpec(_Strict):
    """A real device of the cell (the same fields as a plan's commander / sensor), brought up
    while no run holds it and announced as ``remaster/<cell>/device/<name>``."""

    name: str = Field(pattern=_ID)
    driver: str = Field(description="a registered driver name (drivers.registry): fri, rsi, natnet, tracker, …")
    url: str
    markers: dict[str, str] = Field(default_factory=dict, description="sensors: plan marker name → driver selector")
    noise_mm: float = Field(0.0, ge=0)
    options: dict[str, Any] = Field(default_factory=dict)


class ZenohTls(_Strict):
    """TLS for the daemon's listeners (Zenoh ``transport.link.tls``); PEM files."""

    root_ca_certificate: Path = Field(description="CA that signed the clients' certificates (and the server's)")
    listen_certificate: Path
    listen_private_key: Path
    enable_mtls: bool = Field(True, description="require a client certificate signed by root_ca_certificate")


class ZenohSection(_Strict):
    """The daemon's Zenoh session."""

    mode: Literal["router", "peer"] = "router"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], description=(
        "endpoints to listen on; on a cell PC unixsock-stream//run/remaster/zenoh.sock (the one a client on the "
        "cell PC trusts with credentials: acquire.daemon.local_sockets); tcp/ on loopback only for observers "
        "without credentials"))
    socket_group: str | None = Field(None, min_length=1, description=(
        "the group (name or number) of the unixsock-stream listeners' sockets, mode 0660: its members and root "
        "may connect; none: mode 0600, the daemon's user only"))
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = Field(False, description="off by default: nothing announced on the LAN")
    tls: ZenohTls | None = None
    access_control: dict[str, Any] | None = Field(None, description="Zenoh's access_control block, as is")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for ep in value:
            endpoint_is_loopback(ep)  # raises on a malformed endpoint
        return value

    @property
    def socket_paths(self) -> list[Path]:
        """The socket files of the ``unixsock-stream`` listen endpoints."""
        return [Path(p) for p in map(socket_path_of, self.listen) if p is not None]

    @property
    def remote_endpoints(self) -> list[str]:
        """Listen endpoints reachable from other hosts."""
        return [ep for ep in self.listen if not endpoint_is_loopback(ep)]

    @property
    def acl_enforcing(self) -> bool:
        """True if the ACL block is enabled with ``default_permission: deny``."""
        acl = self.access_control or {}
        return bool(acl.get("enabled")) and acl.get("default_permission") == "deny"

    def security_problems(self) -> list[tuple[tuple, str]]:
        """(field path, message) for remote listening without authentication."""
        problems = []
        if self.access_control is not None and not isinstance(self.access_control.get("enabled", False), bool):
            problems.append((("zenoh", "access_control", "enabled"), "must be true or false"))
        for i in _guard_overridden(self.access_control or {}):
            problems.append((("zenoh", "access_control", "rules", i), (
                "with default_permission: allow, this allow rule for egress queries on the control keys would let "
                f"other sessions receive the daemon's control queries; allowed: key expressions outside "
                f"{list(CONTROL_KEY_EXPRS)}, or default_permission: deny")))
        for i, ep in enumerate(self.listen):
            path = socket_path_of(ep)
            if path is not None and not Path(path).is_absolute():
                problems.append((("zenoh", "listen", i), f"the socket of {ep!r} must be an absolute path, e.g. "
                                 "unixsock-stream//run/remaster/zenoh.sock"))
        remote = self.remote_endpoints
        if not remote or self.acl_enforcing:
            return problems
        mtls = self.tls is not None and self.tls.enable_mtls
        for i, ep in enumerate(self.listen):
            if ep not in remote:
                continue
            if ep.split("/", 1)[0] in _SECURE_PROTOCOLS and mtls:
                continue
            problems.append((
                ("zenoh", "listen", i),
                f"endpoint {ep!r} is reachable from other hosts without authentication; allowed: "
                f"loopback endpoints, tls/ or quic/ endpoints with zenoh.tls.enable_mtls: true, or "
                f"zenoh.access_control with enabled: true and default_permission: deny",
            ))
        return problems

    def zenoh_config(self) -> dict[str, Any]:
        """The Zenoh configuration as a dict of top-level keys (JSON-serialisable)."""
        cfg: dict[str, Any] = {
            "mode": self.mode,
            "listen": {"endpoints": list(self.listen)},
            "connect": {"endpoints": list(self.connect)},
            "scouting": {"multicast": {"enabled": self.multicast_scouting}, "gossip": {"enabled": False}},
        }
        if self.tls is not None:
            cfg["transport"] = {"link": {"tls": {
                "root_ca_certificate": str(self.tls.root_ca_certificate),
                "listen_certificate": str(self.tls.listen_certificate),
                "listen_private_key": str(self.tls.listen_private_key),
                "enable_mtls": self.tls.enable_mtls,
            }}}
        cfg["access_control"] = control_guard(self.access_control)
        return cfg


class ControlSocketSection(_Strict):
    """The local control plane (``acquire.daemon.control_socket``): a Unix socket only ``group`` (and
    root) can connect to; the kernel tells the daemon who connected (SO_PEERCRED)."""

    path: Path = Field(Path("/run/remaster/control.sock"), description="the socket (systemd RuntimeDirectory=remaster)")
    group: str = Field("remaster-operators", min_length=1,
                       description="the operators' group (name or number): the socket's group, mode 0660")
    allow: list[Permission] = Field(default_factory=lambda: ["observe", "read", "control", "motion"], min_length=1,
                                    description="what a member of the group may do")


class ScramCredentials(_Strict):
    """What an RFC 5802 server stores for one client (printed by ``acquire token new``)."""

    salt: str = Field(description="base64 of the random salt (≥ 12 bytes)")
    iterations: int = Field(description=f"PBKDF2-HMAC-SHA256 iterations, ≥ {MIN_ITERATIONS}")
    stored_key: str = Field(description="base64 of StoredKey = SHA-256(ClientKey), 32 bytes")
    server_key: str = Field(description="base64 of ServerKey, 32 bytes")

    @field_validator("iterations")
    @classmethod
    def _enough_iterations(cls, value: int) -> int:
        if value < MIN_ITERATIONS:
            raise ValueError(f"must be ≥ {MIN_ITERATIONS} (RFC 7677), given {value}; make the client's lines "
                             "again with `acquire token new`")
        return value

    @field_validator("salt", "stored_key", "server_key")
    @classmethod
    def _base64(cls, value: str, info) -> str:
        try:
            raw = base64.b64decode(value, validate=True)
        except (binascii.Error, ValueError):
            raise ValueError("must be base64 (as printed by `acquire token new`)") from None
        if info.field_name == "salt" and len(raw) < 12:
            raise ValueError(f"must hold at least 12 bytes, holds {len(raw)}")
        if info.field_name != "salt" and len(raw) != 32:
            raise ValueError(f"must hold 32 bytes (SCRAM-SHA-256), holds {len(raw)}")
        return value

    def credentials(self) -> Credentials:
        return Credentials(base64.b64decode(self.salt), self.iterations, base64.b64decode(self.stored_key),
                           base64.b64decode(self.server_key))


class Client(_Strict):
    """One named client and what it may do."""

    name: str = Field(pattern=_ID)
    scram: ScramCredentials = Field(description="the client's SCRAM-SHA-256 keys (never its token)")
    allow: list[Permission] = Field(min_length=1)
    cert_common_names: list[str] = Field(
        default_factory=list,
        description="if given, the query must also come over a TLS link whose certificate CN is one of these",
    )

    @model_validator(mode="before")
    @classmethod
    def _no_token_hash(cls, data: Any) -> Any:
        if isinstance(data, dict) and "token_sha256" in data:
            raise ValueError(
                "token_sha256 is no longer accepted (control protocol v3 authenticates with SCRAM-SHA-256): "
                "make a new token with `acquire token new --client NAME` and paste the `scram:` lines it prints")
        return data


class AuthSection(_Strict):
    """Who may do what; see the module docstring."""

    clients: list[Client] = Field(default_factory=list)
    anonymous: list[Permission] = Field(default_factory=lambda: ["observe"])

    @field_validator("anonymous")
    @classmethod
    def _anonymous_never_moves(cls, value: list[str]) -> list[str]:
        if "motion" in value or "read" in value or "archive" in value:
            raise ValueError(
                f"anonymous clients may not hold 'motion', 'read' or 'archive' (given {value}); allowed: observe, control"
            )
        return value

    @model_validator(mode="after")
    def _unique_names(self) -> "AuthSection":
        names = [c.name for c in self.clients]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"client names must be unique; repeated: {dup}")
        return self


class HealthSection(_Strict):
    """Limits of the watchdog: pings stop while any is exceeded."""

    max_state_age_s: float = Field(0.5, gt=0, description="the commander's measured state must be this fresh")
    max_late_answers_per_check: int = Field(
        0, ge=0, description="late real-time answers allowed to appear between two health checks"
    )
    recorder_max_silence_s: float = Field(
        120.0, gt=0, description="a running run's log must have been written within this (when reported)"
    )


class ShutdownSection(_Strict):
    """What SIGTERM does to a running run."""

    on_sigterm: Literal["pause", "abort"] = Field(
        "pause", description="pause: finish the current configuration, then stop; abort: stop now, safely"
    )
    timeout_s: float = Field(60.0, gt=0, description="after this the run is aborted anyway")


class LiveSection(_Strict):
    """The live view for the Foxglove app (one server for all the daemon's runs)."""

    enabled: bool = False
    host: str = Field("127.0.0.1", min_length=1, description="interface to bind; loopback unless allow_remote")
    port: int = Field(8765, ge=1, le=65535)
    allow_remote: bool = Field(False, description="allow a non-loopback host (the live view has no authentication)")

    @model_validator(mode="after")
    def _loopback_unless_allowed(self) -> "LiveSection":
        if self.enabled and not self.allow_remote and not _host_is_loopback(self.host):
            raise ValueError(f"host {self.host!r} is not loopback: the live view has no authentication; "
                             "set allow_remote: true to serve it to the network anyway")
        return self


def _host_is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class DaemonConfig(_Strict, CrossFieldChecked):
    """The whole daemon configuration (see the module docstring)."""

    cell: str = Field(pattern=_ID)
    site: str | None = Field(None, pattern=_ID, description="plant site: keys remaster/<site>/<cell>/…")
    robot_serial: str | None = Field(None, pattern=r"^[A-Za-z0-9_.-]+$", max_length=64,
                                     description="the robot's serial number (archive folder); default: the cell id")
    state_dir: Path = Path("/var/lib/remaster")
    plan_dirs: list[Path] = Field(default_factory=list)
    allow_inline_plans: bool = True
    fake: bool | FakeCell = False
    robot: Path | None = Field(None, description="robot model YAML: the commander's joint limits")
    commander: DeviceSpec | None = None
    sensors: list[DeviceSpec] = Field(default_factory=list)
    zenoh: ZenohSection = ZenohSection()
    control_socket: ControlSocketSection | None = None
    auth: AuthSection = AuthSection()
    health: HealthSection = HealthSection()
    shutdown: ShutdownSection = ShutdownSection()
    live: LiveSection = LiveSection()
    status_interval_s: float = Field(1.0, gt=0, le=60, description="health check / STATUS period without a watchdog")
    archive_keep_days: float | None = Field(None, ge=0, description=(
        "delete a run this many days after the station confirmed it, once the station re-verified its copy "
        "(acquire.daemon.archive); default: keep every run"))

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        """Checks between fields, reported at the right line by ``load_validated``."""
        problems = list(self.zenoh.security_problems())
        names = [d.name for d in self.sensors] + ([self.commander.name] if self.commander else [])
        for i, d in enumerate(self.sensors):
            if names.count(d.name) > 1:
                problems.append((("sensors", i, "name"), f"device names must be unique; {d.name!r} repeats"))
        if self.fake_cell is None and self.commander is not None and self.robot is None:
            problems.append((("commander",), "a real commander needs 'robot' (the model whose joint limits it enforces)"))
        if self.fake_cell is None and self.commander is None and not self.sensors:
            problems.append(((), "no devices: give 'commander' and/or 'sensors', or 'fake: true' for the simulated cell"))
        return problems

    @property
    def fake_cell(self) -> FakeCell | None:
        """The simulated cell to bring up, or None for real devices."""
        if self.fake is True:
            return FakeCell()
        return self.fake or None

    def resolved(self, base: Path) -> "DaemonConfig":
        """A copy with every relative path taken from ``base`` (the config file's folder)."""

        def fix(p: Path | None) -> Path | None:
            return None if p is None else (p if p.is_absolute() else (base / p).resolve())

        update: dict[str, Any] = {
            "state_dir": fix(self.state_dir),
            "robot": fix(self.robot),
            "plan_dirs": [fix(p) for p in self.plan_dirs],
        }
        fc = self.fake_cell
        if fc is not None and fc.sim_config is not None:
            update["fake"] = fc.model_copy(update={"sim_config": fix(fc.sim_config)})
        if self.zenoh.tls is not None:
            t = self.zenoh.tls
            tls = t.model_copy(update={
                "root_ca_certificate": fix(t.root_ca_certificate),
                "listen_certificate": fix(t.listen_certificate),
                "listen_private_key": fix(t.listen_private_key),
            })
            update["zenoh"] = self.zenoh.model_copy(update={"tls": tls})
        if self.control_socket is not None:
            update["control_socket"] = self.control_socket.model_copy(update={"path": fix(self.control_socket.path)})
        return self.model_copy(update=update)

    def client(self, name: str) -> Client | None:
        """The configured client called ``name``, or None."""
        for c in self.auth.clients:
            if c.name == name:
                return c
        return None


def load_daemon_config(path: str | Path) -> DaemonConfig:
    """Read and validate the daemon configuration; relative paths resolved from its folder.

    Raises ConfigError (a ValueError) with ``file:line:col: field: message`` lines, and when
    the file holds client keys but other users may read it, or anyone but its owner and group
    may write it (see ``check_config_mode``).
    """
    path = Path(path)
    cfg = load_validated(path, DaemonConfig)
    if cfg.auth.clients:
        check_config_mode(path)
    return cfg.resolved(path.resolve().parent)


def check_config_mode(path: Path) -> None:
    """ConfigError unless ``path`` is unreadable to others and unwritable to group and others
    (its ServerKey lets a reader impersonate the daemon to clients; see acquire.daemon.control_auth).
    Group read is allowed: ``root:remaster 0640`` is the documented installation."""
    mode = stat.S_IMODE(os.stat(path).st_mode)
    if mode & (stat.S_IRWXO | stat.S_IWGRP):
        raise ConfigError(
            f"{path}: UNPROTECTED CONFIGURATION: mode {mode:04o}, but it holds client keys (auth.clients), with "
            "which a reader can impersonate this daemon to its clients. Allowed: readable by its owner and group "
            f"only, writable by its owner only. Run: chmod 0640 {path} (owner root, group of the daemon's user)")
