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
      connect: [tcp/127.0.0.1:7447]
      zenoh: {}                        # TLS / access control / user-password, Zenoh config paths → values
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

**A listener other hosts can reach is protected by Zenoh itself** (``StationZenoh.security_problems``,
reported at the endpoint's line): every non-loopback ``listen`` endpoint needs one of

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

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

import re

from acquire.daemon.archive import MAX_CHUNK_BYTES
from acquire.station.archive import Limits
from acquire.station.states import Policy
from calib.io.yamlfile import load_validated


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


_SECURE_PROTOCOLS = ("tls", "quic")
_CELL_ID = re.compile(r"^[A-Za-z0-9_.-]+$")
_TLS = "transport/link/tls/"


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


class StationZenoh(_Strict):
    mode: Literal["router", "peer", "client"] = "client"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    zenoh: dict = Field(default_factory=dict)
    allow_unauthenticated_listen: bool = Field(
        False, description="let a non-loopback listener run without mTLS, access control or user-password auth")

    def security_problems(self) -> list[tuple[tuple, str]]:
        """(field path, message) per non-loopback listen endpoint that Zenoh would serve to anyone."""
        from acquire.live.bus import is_loopback_endpoint

        if self.allow_unauthenticated_listen:
            return []
        flat = flat_paths(self.zenoh)
        mtls = all(flat.get(_TLS + k) for k in ("listen_certificate", "listen_private_key", "root_ca_certificate")) \
            and flat.get(_TLS + "enable_mtls") is True
        acl = flat.get("access_control/enabled") is True and flat.get("access_control/default_permission") == "deny"
        usrpwd = bool(flat.get("transport/auth/usrpwd/dictionary_file"))
        problems = []
        for i, ep in enumerate(self.listen):
            if not isinstance(ep, str) or "/" not in ep:
                problems.append((("zenoh", "listen", i), f"{ep!r} is not a Zenoh endpoint like 'tls/0.0.0.0:7447'"))
                continue
            if is_loopback_endpoint(ep) or acl or usrpwd or (ep.split("/", 1)[0] in _SECURE_PROTOCOLS and mtls):
                continue
            problems.append((("zenoh", "listen", i), (
                f"endpoint {ep!r} is reachable from other hosts without authentication; allowed: loopback "
                "endpoints, tls/ or quic/ endpoints with zenoh.zenoh transport/link/tls {listen_certificate, "
                "listen_private_key, root_ca_certificate, enable_mtls: true}, access_control {enabled: true, "
                "default_permission: deny}, transport/auth/usrpwd {dictionary_file}, or (knowingly) "
                "zenoh.allow_unauthenticated_listen: true")))
        return problems


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
