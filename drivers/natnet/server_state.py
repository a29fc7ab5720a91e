"""What the NatNet server said and how its frames are read now: its SERVERINFO, the stream
version, the model definitions and the markers resolved from them, the transport; and how that
changes when Motive re-announces itself, switches bitstream or redefines its models."""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping

from drivers.natnet import codec
from drivers.natnet.selection import MarkerSelector, Resolved, resolve_markers
from drivers.natnet.settings import NatNetSettings


class ServerState:
    """The server as the client knows it (attributes read by ``NatNetSensor``).

    ``server_info``, ``stream_version`` (frames are decoded with it; None: drop them),
    ``model_def``, ``resolved`` (plan marker → stream ids, ``drivers.natnet.selection``),
    ``stream_group`` / ``stream_port`` (None: unicast), ``frame_rate_hz``; ``connected`` once
    the transport is chosen, ``handshake_done`` once connect() finished (a SERVERINFO after it
    is a re-announcement); ``problem``: why frames are dropped, for the silence error.
    """

    def __init__(self, settings: NatNetSettings, selectors: Mapping[str, MarkerSelector],
                 log: logging.Logger) -> None:
        self.settings = settings
        self.selectors = selectors
        self.log = log
        self.server_info: codec.ServerInfo | None = None
        self.stream_version: codec.Version | None = None
        self.model_def: codec.ModelDef | None = None
        self.resolved: dict[str, Resolved] = {}
        self.stream_group: str | None = None
        self.stream_port: int | None = None
        self.frame_rate_hz: float | None = None
        self.connected = False
        self.handshake_done = False
        self.problem: str | None = None
        self.pending_bitstream = False  # a re-announced 4.x server was asked to switch back
        self._lock = threading.Lock()  # attributes that change together change under it

    def reset(self) -> None:
        """Nothing learnt from an earlier connection carries over."""
        with self._lock:
            self.stream_version = self.stream_group = self.stream_port = None
            self.problem, self.pending_bitstream, self.handshake_done = None, False, False

    def resolve(self, md: codec.ModelDef | None) -> dict[str, Resolved]:
        """The plan's selectors against ``md`` (``selection.resolve_markers``)."""
        return resolve_markers(self.selectors, md, self.settings.name)

    def adopt(self, info: codec.ServerInfo, version: codec.Version, group: str | None,
              port: int | None) -> None:
        """The handshake chose how to read the server: frames may come from now on."""
        with self._lock:
            self.server_info = info
            self.stream_version = version
            self.stream_group, self.stream_port = group, port
            self.connected = True

    def finish(self, md: codec.ModelDef | None, resolved: dict[str, Resolved]) -> None:
        """The handshake's model definitions and markers; later SERVERINFOs re-announce."""
        with self._lock:
            self.model_def = md
            self.resolved = resolved
            self.handshake_done = True

    def on_model_def(self, md: codec.ModelDef) -> None:
        """New model definitions after the handshake (e.g. asked after a restart); kept only
        when the plan's markers still resolve, else logged and ignored."""
        try:
            resolved = self.resolve(md)
        except ValueError as exc:
            self.log.error("model definitions changed and no longer match the markers: %s", exc)
            return
        with self._lock:
            self.model_def, self.resolved = md, resolved

    def on_bitstream_reply(self, msg: codec.Response | codec.UnrecognizedRequest) -> None:
        """The answer to the bitstream switch ``on_reannounce`` asked for."""
        want = self.settings.bitstream
        with self._lock:
            self.pending_bitstream = False
            if isinstance(msg, codec.Response) and msg.code == 0:
                self.stream_version = want
                self.log.info("server switched the stream back to NatNet %d.%d", *want[:2])
            else:
                self.problem = (
                    f"Motive restarted and refused to stream NatNet {want[0]}."
                    f"{want[1]} again ({msg}); connect the sensor again")
                self.log.error("%s", self.problem)

    def on_reannounce(self, info: codec.ServerInfo) -> tuple[bool, list[codec.Message]]:
        """A SERVERINFO after the handshake: the server (re)announced itself, e.g. answering
        our CONNECT after a silence. Take its version; returns (restart ordering at its next
        frame, requests to send). A version this driver cannot read drops frames (``problem``
        says why). A changed transport (e.g. Motive switched to multicast) is logged with what
        to do: the sockets are chosen at connect(), so the sensor must be connected again."""
        want = self.settings.bitstream
        version = codec.version_tuple(info.natnet_version)
        if version[:2] < codec.MIN_VERSION[:2] or (
                version[:2] > codec.MAX_VERSION[:2] and (want is None or version[0] < 4)):
            problem = (f"Motive now announces NatNet {version[0]}.{version[1]}, which this driver "
                       f"cannot read, so its frames are dropped; set bitstream={codec.MAX_VERSION[0]}."
                       f"{codec.MAX_VERSION[1]} in the sensor URL and connect again")
            if problem != self.problem:
                self.log.error("%s", problem)
            with self._lock:
                self.server_info = info
                self.stream_version = None  # never read a newer layout as an older one
                self.problem = problem
            return False, []
        if info.multicast is not None:
            now = (info.multicast_address, info.data_port) if info.multicast else (None, None)
            if now != (self.stream_group, self.stream_port):
                self.log.error(
                    "Motive now streams %s but this sensor listens to %s; connect the sensor again "
                    "to follow it", f"multicast {now[0]}:{now[1]}" if now[0] else "unicast",
                    f"multicast {self.stream_group}:{self.stream_port}" if self.stream_group else "unicast",
                )
        self.log.info("server re-announced itself (NatNet %d.%d)", *version[:2])
        with self._lock:
            self.server_info = info
            switch = want is not None and version[0] >= 4 and want[:2] != version[:2]
            # until the server confirms the switch, frames are dropped rather than misread
            if switch:
                self.stream_version = None
            else:
                self.stream_version = want if want and version[0] >= 4 else version
            self.pending_bitstream = switch
            self.problem = None
        requests: list[codec.Message] = [codec.Request(f"Bitstream,{want[0]}.{want[1]}")] if switch else []
        return True, requests + [codec.RequestModelDef()]
