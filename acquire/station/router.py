"""``acquire router``: the site's Zenoh router, as a process of its own, for a plant without ``zenohd``.

Cells and the station are clients (or peers) of the site's router; the router carries their
liveliness tokens, control queries and announcements. Keeping it apart from the station means
restarting or upgrading the station never takes a cell's control plane down. Where Eclipse's
``zenohd`` is installed, use it instead (same endpoints, same TLS / access-control settings);
this is a Zenoh session in router mode and nothing more — no plugins, no storage.

Configuration (``/etc/remaster/router.yaml``)::

    listen: [unixsock-stream//run/remaster-router/zenoh.sock]   # the station on this host
    socket_group: remaster-router-clients   # who may connect to that socket (mode 0660): the station's account
    zenoh: {}                          # Zenoh config paths → values (transport/link/tls/…, access_control, …)
    allow_unauthenticated_listen: false

The station on the router's host connects to the Unix socket: the kernel lets only
``socket_group`` in, and the station checks that only the router's account can have made the
socket before it sends anything (``acquire.station.config.StationZenoh.connect_problems``).
Cells on other hosts reach the router over ``tls/0.0.0.0:7447`` with mutual TLS. Every listener
but a Unix socket needs mutual TLS, Zenoh access control or user-password authentication — a
loopback one too (``acquire.station.config.ZenohLinks.security_problems``).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Callable, Literal

from pydantic import Field

from acquire.live.bus import Bus, BusConfigError, is_loopback_endpoint
from acquire.station.config import ROUTER_ENDPOINT, ZenohLinks
from calib.io.yamlfile import load_validated

log = logging.getLogger(__name__)


class RouterConfig(ZenohLinks):
    """The router's endpoints and Zenoh settings (see the module docstring)."""

    mode: Literal["router"] = "router"
    listen: list[str] = Field(default_factory=lambda: [ROUTER_ENDPOINT])

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        return [(loc[1:], msg) for loc, msg in self.security_problems()]


def load_router_config(path: Path) -> RouterConfig:
    """The validated configuration (``ConfigError`` naming file, line, field)."""
    return load_validated(Path(path), RouterConfig)


def open_session(name: str, z: ZenohLinks, runtime_directory: str) -> Bus:
    """A Zenoh session on ``z``'s endpoints (closed by the caller). Its Unix-socket listeners must
    be in folders nobody else may write (``runtime_directory``: the unit's ``RuntimeDirectory=``
    that makes them) and are handed to ``z.socket_group`` (mode 0660; none: 0600) before anyone
    else could connect (Zenoh makes them with the service's umask). BusConfigError saying what
    to do when a folder or the group is wrong."""
    from acquire.daemon.local_sockets import check_socket_folder, hand_to_group, resolve_group

    try:
        gid = None if z.socket_group is None else resolve_group(z.socket_group, "socket_group")
        for path in z.socket_paths:
            check_socket_folder(path, runtime_directory)
    except (OSError, ValueError) as exc:
        raise BusConfigError(str(exc)) from exc
    # Zenoh's shared-memory transport maps a segment per local peer that sends large payloads
    # (~15 MB each, measured with 50 cells on one host); cells are remote: off unless asked.
    overrides = {"transport/shared_memory/enabled": False, **z.zenoh}
    bus = Bus(name, config={"mode": z.mode, "listen": list(z.listen), "connect": list(z.connect), "zenoh": overrides},
              listen_loopback_only=all(is_loopback_endpoint(e) for e in [*z.listen, *z.connect]))
    try:
        for path in z.socket_paths:
            hand_to_group(path, gid)
    except OSError as exc:
        bus.close()
        raise BusConfigError(str(exc)) from exc
    return bus


def open_router(cfg: RouterConfig) -> Bus:
    """The router's session (closed by the caller)."""
    bus = open_session("router", cfg, "remaster-router")
    log.info("router listening on %s", ", ".join(bus.locators))
    return bus


def serve(cfg: RouterConfig, stop: threading.Event, on_tick: Callable[[], object] | None = None,
          on_ready: Callable[[list[str]], object] | None = None) -> None:
    """Route until ``stop`` is set; ``on_tick`` each second (the systemd watchdog)."""
    with open_router(cfg) as bus:
        if on_ready is not None:
            on_ready(bus.locators)
        while not stop.wait(1.0):
            if on_tick is not None:
                on_tick()
