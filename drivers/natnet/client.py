"""``NatNetSensor``: marker positions from OptiTrack Motive over NatNet, as a PositionSensor.

The sensor composes the parts in this package: ``settings`` (options, URL), ``command`` (the
command socket and replies), ``handshake`` (connect()'s exchange), ``receiver`` (the thread
reading datagrams), ``server_state`` (what Motive announced), ``newest_frame`` (ordering and
silence), ``transport`` (unicast or multicast), ``selection`` and ``samples`` (plan markers in a
frame).
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from drivers.base import Clock, SensorBase
from drivers.errors import ConnectionLostError
from drivers.natnet import codec
from drivers.natnet.command import CommandChannel
from drivers.natnet.handshake import Handshake
from drivers.natnet.newest_frame import NewestFrame
from drivers.natnet.receiver import Receiver
from drivers.natnet.samples import body_rotation, frame_samples
from drivers.natnet.selection import MarkerSelector
from drivers.natnet.server_state import ServerState
from drivers.natnet.settings import NatNetSettings, url_options
from drivers.natnet.transport import where_frames_come
from drivers.protocols import MarkerSample

__all__ = ["MarkerSelector", "NatNetSensor", "body_rotation"]


def _from(part: str, attr: str, doc: str) -> property:
    """A read-only sensor attribute that one of its parts holds."""
    return property(lambda self: getattr(getattr(self, part), attr), doc=doc)


class NatNetSensor(SensorBase):
    """Marker positions (mm, Motive's frame) from an OptiTrack Motive server over NatNet.

    URL (``from_url``)::

        natnet://<server ip>[:<command port>]?<option>=<value>&...

    options: ``command_port`` (default 1510), ``multicast`` and ``data_port`` (only for a
    server that does not announce how it streams; see Transport), ``local`` (this computer's
    IPv4 address on Motive's network; default: the address the route to the server leaves
    from), ``bitstream`` (e.g. ``4.1``: ask a NatNet 4.x server for that stream version),
    ``silence_timeout`` (s), ``units`` (``m``, Motive's default, or ``mm``: the unit positions
    arrive in), ``name``. Example: ``natnet://192.168.1.20?local=192.168.1.31``.

    markers: plan marker name → selector:

    - ``"rb:<body id or name>"``: a rigid body's pivot reported as a marker, visible while
      Motive tracks it;
    - ``"lm:<model id>:<marker id>"``: a labeled marker;
    - ``"ms:<asset>:<marker name>"``: a marker of an asset named in the model definitions. For
      a rigid body or skeleton of that name it is the labeled marker (asset id, index of the
      name in the asset's marker set + 1), Motive's asset-id/member-id labelling (real Motive
      2.1 capture: rigid body 2 "RaceQuad", markers 2:1 … 2:5); for a NatNet 4.1 trained
      markerset it is the asset marker with that name (its description's id; an id below
      65536 is taken as the member id under the asset id — *unverified* against Motive 3.1);
    - ``"sk:<skeleton id or name>:<bone id or name>"``: a skeleton bone's position (a bone of a
      NatNet 4.1 trained markerset the same way), visible while its tracking-valid bit is set.
      Bones are matched on the low 16 bits of their frame id (frame data packs
      skeleton id << 16 | bone id; definitions give the bone id alone).

    Transport: Motive streams frames either multicast (its default: group 239.255.42.99, data
    port 1511) or unicast to each client that sent CONNECT; a NatNet ≥ 3.0 SERVERINFO says which
    (``ServerInfo.multicast``, ``multicast_address``, ``data_port``). The client follows that
    announcement: it joins the announced group on the announced port on interface ``local``, or
    receives unicast frames on its command socket and sends KEEPALIVE every
    ``keepalive_interval_s``. ``multicast``/``data_port`` options are for servers that announce
    nothing; given with a server that announces, they must agree with it (else connect()
    fails saying what to change). ``stream_group`` / ``stream_port`` say what was used.

    Handshake on ``connect()``: CONNECT → SERVERINFO (retried, ``handshake_timeout_s``), then
    (4.x server) REQUEST ``Bitstream,X.Y`` (``bitstream`` set) or ``Bitstream`` (which version
    streams now), then REQUEST ``FrameRate`` (float32 frames per second → ``frame_rate_hz``,
    None if the server does not answer) and REQUEST_MODELDEF → MODELDEF. A server announcing a
    NatNet version above 4.1 (the newest layout this driver reads) is refused unless
    ``bitstream`` (≤ 4.1) is set and the server accepts the switch.

    Ordering: the client keeps only the newest frame. A frame whose number is not above the
    newest one is a duplicate or arrived late and is dropped. A server restart is recognised
    when the counter jumps back by more than ``reorder_window`` frames, when ``restart_run``
    consecutive older frames arrive in increasing order, or when a new SERVERINFO arrives;
    then ordering restarts, model definitions are requested again and ``restarts`` counts it.

    Silence: ``read()`` raises DeviceTimeoutError as soon as no frame has arrived for
    ``silence_timeout_s`` (default 0.5 s), even when the caller's timeout is longer; so a
    server that stops sending is reported at most ``silence_timeout_s`` after its last frame.
    While silent, a unicast client re-sends CONNECT every ``silence_timeout_s`` to rejoin a
    restarted server.

    Samples: ``device_time`` is the frame's timestamp (s, Motive's clock), ``host_time`` is
    ``clock()`` (``time.monotonic``) when the datagram arrived. A marker that is occluded
    (params bit 0x01), missing from the frame, or a rigid body Motive does not track comes
    back with ``visible=False`` (occluded: Motive's predicted position; missing: NaN).
    """

    # settings (validated once, see drivers.natnet.settings)
    server = _from("settings", "server", "Motive's IPv4 address.")
    command_port = _from("settings", "command_port", "Motive's command port.")
    data_port = _from("settings", "data_port", "The data_port option (None: as announced).")
    multicast = _from("settings", "multicast", "The multicast option (None: as announced).")
    local = _from("settings", "local", "This computer's IPv4 address on Motive's network.")
    bitstream = _from("settings", "bitstream", "The NatNet version asked of a 4.x server, or None.")
    silence_timeout_s = _from("settings", "silence_timeout_s", "Silence limit (s).")
    handshake_timeout_s = _from("settings", "handshake_timeout_s", "Handshake reply limit (s).")
    keepalive_interval_s = _from("settings", "keepalive_interval_s", "Unicast KEEPALIVE period (s).")
    scale_mm = _from("settings", "scale_mm", "Millimetres per streamed position unit.")
    reorder_window = _from("settings", "reorder_window", "Frames a late frame may lag (see Ordering).")
    restart_run = _from("settings", "restart_run", "Older frames in a row that mean a restart.")
    # what the server said
    server_info = _from("_state", "server_info", "Motive's SERVERINFO (codec.ServerInfo), or None.")
    stream_version = _from("_state", "stream_version", "The version frames are decoded with, or None.")
    model_def = _from("_state", "model_def", "Motive's MODELDEF (codec.ModelDef), or None.")
    stream_group = _from("_state", "stream_group", "The multicast group frames come to (None: unicast).")
    stream_port = _from("_state", "stream_port", "The multicast data port (None: unicast).")
    frame_rate_hz = _from("_state", "frame_rate_hz", "Motive's answer to FrameRate (Hz), or None.")
    # counters
    frames_accepted = _from("_frames", "frames_accepted", "Frames taken as the newest.")
    frames_stale = _from("_frames", "frames_stale", "Stale or duplicate frames dropped.")
    restarts = _from("_frames", "restarts", "Server restarts recognised.")
    bad_packets = _from("_receiver", "bad_packets", "Undecodable datagrams.")

    def __init__(
        self,
        name: str = "natnet",
        *,
        markers: Mapping[str, str],
        server: str = "127.0.0.1",
        command_port: int = 1510,
        data_port: int | None = None,
        multicast: str | None = None,
        local: str | None = None,
        bitstream=None,
        silence_timeout_s: float = 0.5,
        handshake_timeout_s: float = 2.0,
        keepalive_interval_s: float = 1.0,
        units: str = "m",
        reorder_window: int = 60,
        restart_run: int = 3,
        clock: Clock = time.monotonic,
    ) -> None:
        super().__init__(name, clock=clock)
        if not isinstance(markers, Mapping) or not markers:
            raise ValueError(
                f"markers must be a non-empty mapping plan name → selector "
                f"({MarkerSelector.SYNTAX}), got {markers!r}"
            )
        #: Plan marker name → what it is on the stream.
        self.selectors = {str(k): MarkerSelector.parse(v) for k, v in markers.items()}
        self.settings = NatNetSettings(
            name=name, server=server, command_port=command_port, data_port=data_port,
            multicast=multicast, local=local, bitstream=bitstream, silence_timeout_s=silence_timeout_s,
            handshake_timeout_s=handshake_timeout_s, keepalive_interval_s=keepalive_interval_s,
            units=units, reorder_window=reorder_window, restart_run=restart_run,
        )
        self._state = ServerState(self.settings, self.selectors, self.log)
        self._channel = CommandChannel(self.settings, clock, self.log, lambda: self._state.stream_version)
        self._frames = NewestFrame(self.settings, clock)
        self._receiver = Receiver(self.settings, self._channel, self._frames, self._state, clock, self.log)

    @classmethod
    def from_url(cls, url: str, *, markers: Mapping[str, str], **kwargs) -> "NatNetSensor":
        """Build from ``natnet://host[:port]?options`` (see the class docstring)."""
        opts = url_options(url)
        name = opts.pop("name", "natnet")
        opts.update(kwargs)
        return cls(name, markers=markers, **opts)

    # ------------------------------------------------------------------ PositionSensor
    def marker_names(self) -> list[str]:
        return list(self.selectors)

    def connect(self) -> None:
        if self._receiver.running:
            return
        self._channel.open()
        self._state.reset()  # nothing learnt from an earlier connection carries over
        self._receiver.start()
        try:
            Handshake(self._receiver).run()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        self._receiver.stop()
        if self._channel.sock is not None and self._state.stream_group is None and self._state.connected:
            self._channel.send(codec.Disconnect())
        self._channel.close()
        self._receiver.close_data()
        self._state.connected = False

    def _read_internal(self, timeout: float) -> list[MarkerSample]:
        if not self._receiver.running:
            raise ConnectionLostError(f"{self.name}: not connected; call connect() first")
        frame, host_time = self._frames.take(timeout, self._why_silent)
        return frame_samples(frame, host_time, self._state.resolved, self.selectors, self.settings.scale_mm)

    def _why_silent(self) -> str:
        """Why no frame comes: a known stream problem, else where the client listens."""
        state = self._state
        return state.problem or where_frames_come(state.stream_group, state.stream_port, self.settings)
