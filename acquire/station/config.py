"""The station's configuration file (``/etc/remaster/station.yaml``), validated by pydantic.

::

    archive: /var/lib/remaster-station/archive   # the archive root (acquire.station.archive)
    client: station                    # the name the cells know the station by (auth.clients)
    token_file: /etc/remaster/station.token   # its token (mode 0600; `acquire token new`)
    cell_tokens: {plant-a/c7: /etc/remaster/c7.token}   # optional: a token per cell (site/cell)
    sites: [plant-a]                   # optional: only these sites' cells (default: every cell)
    zenoh:
      mode: router                     # the station's session is the site's router (or peer/client
      listen: [tcp/0.0.0.0:7447]       # connecting to the site's zenohd)
      connect: []
      zenoh: {}                        # TLS / access control / user-password, Zenoh config paths → values
      allow_unauthenticated_listen: false   # see below
    poll_s: 10                         # how often each cell is asked for finished runs
    chunk_bytes: 2097152               # bytes per transfer chunk (≤ 4 MiB)
    drift: {alpha: 0.01, accuracy_limit_mm: 0.5, check_max_configurations: 12, auto_enter: true}

Each cell's daemon lists the station in ``auth.clients`` with permission ``archive``. The station
believes a cell only through the SCRAM exchange: a cell that cannot sign its replies with the
station client's keys gets nothing archived. One token for the whole plant lets every cell prove
itself as any other; ``cell_tokens`` gives each cell its own.

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

from acquire.daemon_archive import MAX_CHUNK_BYTES
from acquire.station.intake import DriftPolicy
from calib.io.yamlfile import load_validated


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


_SECURE_PROTOCOLS = ("tls", "quic")
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
    mode: Literal["router", "peer", "client"] = "router"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    zenoh: dict = Field(default_factory=dict)
    allow_unauthenticated_listen: bool = Field(
        False, description="let a non-loopback listener run without mTLS, access control or user-password auth")

    def security_problems(self) -> list[tuple[tuple, str]]:
        """(field path, message) per non-loopback listen endpoint that Zenoh would serve to anyone."""
        from acquire.bus import is_loopback_endpoint

        if self.allow_unauthenticated_listen or self.mode == "client":
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
    accuracy_limit_mm: float | None = Field(None, gt=0)
    check_max_configurations: int = Field(12, ge=0)
    auto_enter: bool = True

    def policy(self) -> DriftPolicy:
        return DriftPolicy(self.alpha, self.accuracy_limit_mm, self.check_max_configurations, self.auto_enter)


class StationConfig(_Strict):
    archive: Path
    client: str = Field("station", pattern=r"^[A-Za-z0-9_.-]+$")
    token_file: Path
    cell_tokens: dict[str, Path] = Field(default_factory=dict)
    sites: list[str] | None = None
    zenoh: StationZenoh = StationZenoh()
    poll_s: float = Field(10.0, gt=0, le=3600)
    chunk_bytes: int = Field(2 << 20, ge=1024, le=MAX_CHUNK_BYTES)
    drift: DriftSection = DriftSection()

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        """Checks between fields, reported at the right line by ``load_validated``."""
        return self.zenoh.security_problems()


def load_station_config(path: Path) -> StationConfig:
    """The validated configuration (``ConfigError`` naming file, line, field); relative paths
    are taken from the file's folder."""
    cfg = load_validated(Path(path), StationConfig)
    base = Path(path).resolve().parent
    cfg.archive = base / cfg.archive
    cfg.token_file = base / cfg.token_file
    cfg.cell_tokens = {k: base / v for k, v in cfg.cell_tokens.items()}
    return cfg
