"""The NatNet session handshake run by ``NatNetSensor.connect()``: CONNECT → SERVERINFO, the
version checks, the bitstream negotiation with a 4.x server, the transport, FrameRate and the
model definitions (order and messages as in NatNetSensor's "Handshake")."""

from __future__ import annotations

import math

from drivers.errors import ProtocolError
from drivers.natnet import codec
from drivers.natnet.command import connect_message
from drivers.natnet.receiver import Receiver
from drivers.natnet.settings import NatNetSettings
from drivers.natnet.transport import open_multicast, stream_route


def too_new(settings: NatNetSettings, version: codec.Version, app: str) -> ProtocolError:
    """The error for a server streaming a NatNet layout newer than this driver reads."""
    mx, s = codec.MAX_VERSION, settings
    return ProtocolError(
        f"{s.name}: {app} at {s.server} streams NatNet {version[0]}.{version[1]}, newer "
        f"than the newest layout this driver reads ({mx[0]}.{mx[1]}). Add bitstream={mx[0]}.{mx[1]} "
        f"to the sensor URL (natnet://{s.server}:{s.command_port}?bitstream={mx[0]}.{mx[1]}) "
        f"so the driver asks Motive to stream NatNet {mx[0]}.{mx[1]} (a NatNet 4.x server "
        "switches its stream for all its clients), or use a driver that reads "
        f"NatNet {version[0]}.{version[1]}"
    )


class Handshake:
    """One connect()'s handshake over a running ``Receiver`` (it delivers the replies) and
    the parts it feeds; ``run()`` leaves the server state connected and ``handshake_done``
    (a multicast socket joined and handed to the receiver) or raises (ProtocolError,
    DeviceTimeoutError, ConnectionLostError) saying what to do.
    """

    def __init__(self, receiver: Receiver) -> None:
        self.receiver = receiver
        self.settings, self.channel = receiver.settings, receiver.channel
        self.state, self.frames = receiver.state, receiver.frames
        self.clock, self.log = receiver.clock, receiver.log

    def run(self) -> None:
        s = self.settings
        info = self.channel.wait_for(codec.ServerInfo, connect_message(s), "SERVERINFO")
        announced = codec.version_tuple(info.natnet_version)
        if announced[:2] < codec.MIN_VERSION[:2]:
            raise ProtocolError(
                f"{s.name}: {info.app_name} at {s.server} speaks NatNet "
                f"{announced[0]}.{announced[1]}; this driver reads NatNet 3.0 to 4.1 (Motive 2.0 "
                "and later): update Motive"
            )
        if announced[:2] > codec.MAX_VERSION[:2] and (announced[0] < 4 or s.bitstream is None):
            raise too_new(s, announced, info.app_name)
        version = announced
        self.log.info(
            "connected to %s %s (NatNet %s) at %s:%d",
            info.app_name, ".".join(map(str, info.app_version)), ".".join(map(str, version)),
            s.server, s.command_port,
        )
        group, port = stream_route(info, s, self.log)
        if version[0] >= 4:
            version = self._negotiate_bitstream(version, info.app_name)
        elif s.bitstream is not None and s.bitstream[:2] != version[:2]:
            self.log.warning("NatNet %d.%d server cannot change its bitstream; decoding %d.%d",
                             *version[:2], *version[:2])
        self.frames.heard(self.clock())  # before adopt(): the receiver's silence check starts now
        self.state.adopt(info, version, group, port)
        if group is not None:
            self.receiver.listen(open_multicast(group, port, s))
            self.log.info("joined multicast %s:%d on %s", group, port, s.local)
        self.state.frame_rate_hz = self._ask_frame_rate()
        md = self._model_def()
        self.state.finish(md, self.state.resolve(md))
        self.frames.heard(self.clock())

    def _model_def(self) -> codec.ModelDef | None:
        """REQUEST_MODELDEF → MODELDEF; None when it cannot be decoded and no marker is
        selected by name (else ProtocolError saying to select by id)."""
        try:
            return self.channel.wait_for(codec.ModelDef, codec.RequestModelDef(), "MODELDEF")
        except ProtocolError as exc:
            by_name = [k for k, v in self.state.selectors.items() if v.needs_names]
            if by_name:
                raise ProtocolError(
                    f"{self.settings.name}: cannot read Motive's model definitions ({exc}), so markers "
                    f"{by_name} cannot be found by name; select them by id "
                    "('lm:<model id>:<marker id>', 'rb:<body id>' or 'sk:<skeleton id>:<bone id>')"
                ) from exc
            self.log.warning("cannot read Motive's model definitions (%s); markers are selected by id", exc)
            return None

    def _ask_frame_rate(self) -> float | None:
        """REQUEST "FrameRate": Motive answers a float32 in frames per second
        (NatNet SDK NatNetRequests.h); None when it does not answer or makes no sense."""
        reply = self.channel.wait_for((codec.Response, codec.UnrecognizedRequest), codec.Request("FrameRate"),
                                      "reply to the frame-rate request", required=False)
        if not isinstance(reply, codec.Response) or reply.code is None:
            self.log.info("server gave no frame rate (%s)", reply)
            return None
        rate = reply.float32
        if not (math.isfinite(rate) and 0.0 < rate <= 10_000.0):
            self.log.warning("server's frame rate %r Hz makes no sense; ignored", rate)
            return None
        self.log.info("Motive tracks at %.3f Hz", rate)
        return rate

    def _negotiate_bitstream(self, announced: codec.Version, app: str) -> codec.Version:
        """With a 4.x server: ask for ``bitstream`` if set, else ask which version it streams
        now (the setting is global: another client may have changed it). Returns a version
        this codec reads or raises ProtocolError."""
        s, replies = self.settings, (codec.Response, codec.UnrecognizedRequest)
        if s.bitstream is not None:
            want = f"{s.bitstream[0]}.{s.bitstream[1]}"
            reply = self.channel.wait_for(replies, codec.Request(f"Bitstream,{want}"),
                                          "reply to the bitstream request")
            if isinstance(reply, codec.Response) and reply.code == 0:
                self.log.info("server switched the stream to NatNet %s", want)
                return s.bitstream
            if announced[:2] > codec.MAX_VERSION[:2]:
                raise ProtocolError(
                    f"{s.name}: {app} at {s.server} streams NatNet {announced[0]}.{announced[1]} "
                    f"and refused 'Bitstream,{want}' ({reply}); this driver reads NatNet 3.0 to "
                    f"{codec.MAX_VERSION[0]}.{codec.MAX_VERSION[1]}, so it cannot read this server"
                )
            self.log.warning("server refused bitstream %s (%s); asking what it streams", want, reply)
        reply = self.channel.wait_for(replies, codec.Request("Bitstream"), "reply to the bitstream query",
                                      required=False)
        text = reply.text if isinstance(reply, codec.Response) else None
        if text and text.startswith("Bitstream,"):
            try:
                now = codec.version_tuple(text.split(",", 1)[1])
            except ValueError as exc:
                raise ProtocolError(f"{s.name}: server streams {text!r}: {exc}") from exc
            if now[:2] > codec.MAX_VERSION[:2]:
                raise too_new(s, now, app)
            try:
                return codec.check_supported(now)
            except ValueError as exc:
                raise ProtocolError(f"{s.name}: server streams {text!r}: {exc}") from exc
        return announced
