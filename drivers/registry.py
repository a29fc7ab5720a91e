"""Driver registry: names map to ``"module:Class"`` strings imported on use (python-can style),
merged with the entry-point group ``remaster.drivers`` so a third party can add a driver."""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from drivers.errors import DriverUnavailableError

#: Built-in drivers. Sensors and commanders share one namespace.
BUILTIN: dict[str, str] = {
    "natnet": "drivers.natnet.client:NatNetSensor",
    "tracker": "drivers.tracker.client:TrackerSensor",
    "emscon": "drivers.emscon.client:EmsconSensor",
    "rsi": "drivers.kuka_rsi.commander:RsiCommander",
    "fri": "drivers.kuka_fri.commander:FriCommander",
    "socket": "drivers.socket.sensor:SocketSensor",
}

ENTRY_POINT_GROUP = "remaster.drivers"


def known_drivers() -> dict[str, str]:
    """Every driver name with its ``module:Class`` target, built-ins first."""
    found = dict(BUILTIN)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep.value)
    return found


def load_driver(name: str) -> type:
    """Import and return the driver class registered as ``name``.

    Raises ValueError for an unknown name (listing the valid ones) and DriverUnavailableError,
    chained to the cause, when the import fails.
    """
    drivers = known_drivers()
    if name not in drivers:
        raise ValueError(f"unknown driver {name!r}; known drivers: {', '.join(sorted(drivers))}")
    target = drivers[name]
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
        return getattr(module, attr)
    except (ImportError, AttributeError) as exc:
        raise DriverUnavailableError(f"driver {name!r} ({target}) could not be loaded: {exc}") from exc
