"""How NatNet frames reach this computer: unicast on the command socket, or a multicast group on
the data port, as the server's SERVERINFO announces (``stream_route``); the socket for multicast
(``open_multicast``) and what to check when nothing arrives
(``where_frames_come``)."""

from __future__ import annotations

import logging
import socket

from drivers.errors import ConnectionLostError, ProtocolError
from drivers.natnet import codec
from drivers.natnet.settings import NatNetSettings

#: Motive's default data port (frames, multicast) and multicast group.
NATNET_DEFAULT_DATA_PORT = 1511
NATNET_DEFAULT_MULTICAST = "239.255.42.99"


def is_group(address: str | None) -> bool:
    """True for a dotted IPv4 multicast group address (224.0.0.0 – 239.255.255.255)."""
    try:
        return address is not None and 224 <= socket.inet_aton(address)[0] <= 239 and address.count(".") == 3
    except OSError:
        return False


def stream_route(
    info: codec.ServerInfo, settings: NatNetSettings, log: logging.Logger
) -> tuple[str | None, int | None]:
    """(multicast group or None for unicast, data port) from the server's announcement,
    checked against the sensor's ``multicast`` / ``data_port`` settings (used as given when
    the server announces nothing); ProtocolError saying what to change when they disagree."""
    name, multicast, data_port = settings.name, settings.multicast, settings.data_port
    where = f"{info.app_name} at {settings.server}"
    if info.multicast is None:  # short SERVERINFO: the server announces nothing
        if multicast is None:
            return None, None
        return multicast, data_port or NATNET_DEFAULT_DATA_PORT
    if not info.multicast:
        if multicast is not None:
            raise ProtocolError(
                f"{name}: {where} streams unicast (its Streaming Transmission Type is "
                f"Unicast) but the sensor URL asks for multicast={multicast}. Remove the "
                "multicast option (the driver follows what Motive announces), or set Motive's "
                "Streaming Transmission Type to Multicast"
            )
        return None, None
    group, port = info.multicast_address, info.data_port
    if not is_group(group) or not port:
        raise ProtocolError(
            f"{name}: {where} announces multicast streaming to {group}:{port}, which is "
            "not a multicast group and port; check Motive's Streaming pane (Multicast "
            "Interface, Data Port) or set its Transmission Type to Unicast"
        )
    for option, mine, theirs in (("multicast", multicast, group), ("data_port", data_port, port)):
        if mine is not None and mine != theirs:
            raise ProtocolError(
                f"{name}: {where} announces multicast {group}:{port} but the sensor URL "
                f"sets {option}={mine}. Remove the {option} option (the driver follows what "
                f"Motive announces) or set it to {theirs}"
            )
    log.info("%s streams multicast %s:%d; joining on %s", where, group, port, settings.local)
    return group, port


def open_multicast(group: str, port: int, settings: NatNetSettings) -> socket.socket:
    """A non-blocking UDP socket bound to ``group:port`` that joined ``group`` on interface
    ``settings.local``; ConnectionLostError saying what to set when this computer cannot
    receive it."""
    local, name, server = settings.local, settings.name, settings.server
    data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        data.bind((group, port))  # only datagrams to the group reach this socket
        data.setsockopt(
            socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
            socket.inet_aton(group) + socket.inet_aton(local),
        )
    except OSError as exc:
        data.close()
        raise ConnectionLostError(
            f"{name}: Motive at {server} streams multicast to {group}:{port}, but this "
            f"computer cannot receive it on interface {local}: {exc}. Either set the sensor "
            "URL option local=<this computer's IPv4 address on Motive's network>, free UDP port "
            f"{port} (another program holds it without sharing), or set Motive's Streaming "
            "Transmission Type to Unicast"
        ) from exc
    data.setblocking(False)
    return data


def where_frames_come(group: str | None, port: int | None, settings: NatNetSettings) -> str:
    """What the client listens to (``group``:``port``, or unicast when ``group`` is None) and
    what to check when nothing comes (for errors)."""
    local, server, command_port = settings.local, settings.server, settings.command_port
    if group is not None:
        return (
            f"listening to multicast {group}:{port} on interface "
            f"{local} as Motive at {server} announced. Check that Motive is streaming "
            "(Streaming pane: Enable on), that this computer's address on Motive's network is "
            f"{local} (else set the sensor URL option local=<that address>) and that the "
            f"firewall lets UDP port {port} in; or set Motive's Streaming "
            "Transmission Type to Unicast"
        )
    return (
        f"listening for unicast frames from {server}:{command_port} on "
        f"{local}. Check that Motive is running and streaming (Streaming pane: Enable on) "
        f"and that the firewall lets UDP from {server} in"
    )
