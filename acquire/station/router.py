"""``acquire router``: the site's Zenoh router, as a process of its own, for a plant without ``zenohd``.

Cells and the station are clients (or peers) of the site's router; the router carries their
liveliness tokens, control queries and announcements. Keeping it apart from the station means
restarting or upgrading the station never takes a cell's control plane down. Where Eclipse's
``zenohd`` is installed, use it instead (same endpoints, same TLS / access-control settings);
this is a Zenoh session in router mode and nothing more — no plugins, no storage.

Configuration (``/etc/remaster/router.yaml``)::

    listen: [tcp/127.0.0.1:7447]       # other hosts: tls/0.0.0.0:7447 with mTLS (zenoh: below)
    zenoh: {}                          # Zenoh config paths → values (transport/link/tls/…, access_control, …)
    allow_unauthenticated_listen: false

A listener other hosts can reach needs mutual TLS, Zenoh access control or user-password
authentication, under the same rule as the station's (``acquire.station.config.StationZenoh``).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Callable, Literal

from pydantic import Field

from acquire.live.bus import Bus, is_loopback_endpoint
from acquire.station.config import StationZenoh
from calib.io.yamlfile import load_validated

log = logging.getLogger(__name__)


class RouterConfig(StationZenoh):
    """The router's endpoints and Zenoh settings (see the module docstring)."""

    mode: Literal["router"] = "router"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        return [(loc[1:], msg) for loc, msg in self.security_problems()]


def load_router_config(path: Path) -> RouterConfig:
    """The validated configuration (``ConfigError`` naming file, line, field)."""
    return load_validated(Path(path), RouterConfig)


def open_router(cfg: RouterConfig) -> Bus:
    """The router's session (closed by the caller)."""
    overrides = {"transport/shared_memory/enabled": False, **cfg.zenoh}
    bus = Bus("router", config={"mode": "router", "listen": list(cfg.listen), "connect": list(cfg.connect),
                                "zenoh": overrides},
              listen_loopback_only=all(is_loopback_endpoint(e) for e in [*cfg.listen, *cfg.connect]))
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
