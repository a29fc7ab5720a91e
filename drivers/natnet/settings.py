"""A NatNet sensor's settings (``NatNetSettings``), checked once, and the ``natnet://`` URL they
come from (``url_options``). Every option is described on ``drivers.natnet.client.NatNetSensor``."""

from __future__ import annotations

import math
import socket
from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

from drivers.natnet import codec

#: Query options a ``natnet://`` URL may carry.
URL_OPTIONS = (
    "command_port", "data_port", "multicast", "local", "bitstream", "silence_timeout", "units", "name",
)


def route_source(server: str, port: int) -> str:
    """This host's IPv4 address on the route to ``server`` (no packet is sent); "0.0.0.0"
    (any interface) when there is no route yet."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((server, port))
            return probe.getsockname()[0]
        except OSError:
            return "0.0.0.0"


@dataclass(frozen=True)
class NatNetSettings:
    """Where Motive is and how to talk to it; ValueError naming the setting and what is allowed.

    name: the sensor's name (starts its error messages). server, command_port: Motive's IPv4
    address and command port. data_port, multicast: only for a server that announces nothing.
    local: this computer's IPv4 address on Motive's network (None: the address the route to
    the server leaves from). bitstream: the NatNet version to
    ask a 4.x server for, or None. silence_timeout_s, handshake_timeout_s, keepalive_interval_s:
    seconds. units: "m" or "mm", the unit positions arrive in. reorder_window, restart_run:
    frames (see NatNetSensor's "Ordering").
    """

    name: str
    server: str
    command_port: int
    data_port: int | None
    multicast: str | None
    local: str | None
    bitstream: codec.Version | None
    silence_timeout_s: float
    handshake_timeout_s: float
    keepalive_interval_s: float
    units: str
    reorder_window: int
    restart_run: int

    def __post_init__(self) -> None:
        for label, value in (("command_port", self.command_port), ("data_port", self.data_port)):
            if value is not None and not (isinstance(value, int) and 0 < value < 65536):
                raise ValueError(f"{label} must be a port 1..65535, got {value!r}")
        for label, value in (
            ("silence_timeout_s", self.silence_timeout_s), ("handshake_timeout_s", self.handshake_timeout_s),
            ("keepalive_interval_s", self.keepalive_interval_s),
        ):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a positive number of seconds, got {value!r}")
        if self.units not in ("m", "mm"):
            raise ValueError(f"units must be 'm' or 'mm' (the unit Motive streams), got {self.units!r}")
        if self.multicast is not None:
            try:
                first = int(self.multicast.split(".")[0])
                socket.inet_aton(self.multicast)
            except (ValueError, OSError) as exc:
                raise ValueError(f"multicast must be an IPv4 group address, got {self.multicast!r}") from exc
            if not 224 <= first <= 239:
                raise ValueError(
                    f"multicast must be a group address 224.0.0.0–239.255.255.255, got {self.multicast!r}"
                )
        if self.reorder_window < 1 or self.restart_run < 2:
            raise ValueError(
                f"reorder_window must be ≥ 1 and restart_run ≥ 2, got {self.reorder_window}, {self.restart_run}"
            )
        set_ = object.__setattr__  # frozen: normalise once
        set_(self, "local", self.local or route_source(self.server, self.command_port))
        if self.bitstream is not None:
            set_(self, "bitstream", codec.check_supported(self.bitstream))
        for label in ("silence_timeout_s", "handshake_timeout_s", "keepalive_interval_s"):
            set_(self, label, float(getattr(self, label)))
        set_(self, "reorder_window", int(self.reorder_window))
        set_(self, "restart_run", int(self.restart_run))

    @property
    def scale_mm(self) -> float:
        """Millimetres per streamed position unit."""
        return 1000.0 if self.units == "m" else 1.0

    @property
    def bitstream_or_any(self) -> codec.Version:
        """The version CONNECT asks for: ``bitstream``, else (0, 0, 0, 0) (whatever streams)."""
        return self.bitstream or (0, 0, 0, 0)


def url_options(url: str) -> dict:
    """``natnet://host[:port]?options`` → NatNetSensor keyword arguments (``name`` included
    when given); ValueError naming the bad part and what is allowed."""
    parts = urlsplit(url)
    if parts.scheme != "natnet" or not parts.hostname:
        raise ValueError(f"NatNet URL must look like 'natnet://<server ip>[:port]?…', got {url!r}")
    opts: dict = {"server": parts.hostname}
    try:
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"bad port in NatNet URL {url!r}") from exc
    if port is not None:
        opts["command_port"] = port
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key not in URL_OPTIONS:
            raise ValueError(f"unknown NatNet URL option {key!r}; allowed: {', '.join(URL_OPTIONS)}")
        try:
            if key in ("command_port", "data_port"):
                opts[key] = int(value)
            elif key == "silence_timeout":
                opts["silence_timeout_s"] = float(value)
            elif key == "multicast":
                opts[key] = value or None
            else:
                opts[key] = value
        except ValueError as exc:
            raise ValueError(f"NatNet URL option {key}={value!r} is not a number") from exc
    return opts
