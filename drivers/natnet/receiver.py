"""The NatNet receiver thread: reads the command and multicast sockets, decodes each datagram
and hands it on (frames to ``NewestFrame``, re-announcements and bitstream answers to
``ServerState``, replies to ``CommandChannel``); keeps a unicast subscription alive."""

from __future__ import annotations

import logging
import selectors
import socket
import threading

from drivers.base import Clock
from drivers.errors import ProtocolError
from drivers.natnet import codec
from drivers.natnet.command import CommandChannel, connect_message
from drivers.natnet.newest_frame import NewestFrame
from drivers.natnet.server_state import ServerState
from drivers.natnet.settings import NatNetSettings

#: Datagrams read from one socket before the loop looks at the clock again.
DRAIN_AT_MOST = 256


class Receiver:
    """One thread (``start`` / ``stop``) reading the command socket and, when Motive streams
    multicast, the data socket given to ``listen``.

    Unicast, it sends KEEPALIVE every ``settings.keepalive_interval_s`` and CONNECT again every
    ``settings.silence_timeout_s`` while no frame arrives (to rejoin a restarted server).
    An OSError stops it and fails ``channel`` and ``frames`` (their waiters raise).
    ``bad_packets`` counts undecodable datagrams.
    """

    def __init__(
        self, settings: NatNetSettings, channel: CommandChannel, frames: NewestFrame,
        state: ServerState, clock: Clock, log: logging.Logger,
    ) -> None:
        self.settings, self.channel, self.frames, self.state = settings, channel, frames, state
        self.clock, self.log = clock, log
        self.bad_packets = 0
        self.data: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        """True between ``start`` and ``stop``."""
        return self._thread is not None

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.settings.name}-natnet", daemon=True)
        self._thread.start()

    def listen(self, data: socket.socket) -> None:
        """Also read ``data`` (the joined multicast socket; closed by ``stop``)."""
        self.data = data

    def stop(self) -> None:
        """Stop the thread (waits up to 2 s); the sockets stay open (``close_data``)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def close_data(self) -> None:
        """Close the multicast socket, if any (after ``stop``)."""
        if self.data is not None:
            self.data.close()
        self.data = None

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        s, state = self.settings, self.state
        sel = selectors.DefaultSelector()
        registered: set[int] = set()
        next_keepalive = self.clock() + s.keepalive_interval_s
        next_reconnect = 0.0
        try:
            while not self._stop.is_set():
                for sock in (self.channel.sock, self.data):
                    if sock is not None and sock.fileno() not in registered:
                        sel.register(sock, selectors.EVENT_READ)
                        registered.add(sock.fileno())
                for key, _ in sel.select(timeout=0.02):
                    self._drain(key.fileobj)
                now = self.clock()
                if not state.connected:
                    continue
                if state.stream_group is None and now >= next_keepalive:
                    self.channel.send(codec.KeepAlive())
                    next_keepalive = now + s.keepalive_interval_s
                silent = now - self.frames.last_rx
                if state.stream_group is None and silent > s.silence_timeout_s and now >= next_reconnect:
                    self.log.warning("no frame for %.2f s; sending CONNECT again", silent)
                    self.channel.send(connect_message(s))
                    next_reconnect = now + s.silence_timeout_s
        except OSError as exc:
            if not self._stop.is_set():
                self.log.error("NatNet receiver failed: %s", exc)
                self.channel.fail(exc)
                self.frames.fail(exc)
        finally:
            sel.close()

    def _drain(self, sock: socket.socket) -> None:
        for _ in range(DRAIN_AT_MOST):  # bounded: never starve the keep-alive
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return
            self.on_datagram(data, self.clock())

    def on_datagram(self, data: bytes, host_time: float) -> None:
        """Decode one datagram (arrived at ``host_time``, s) and hand it on."""
        state = self.state
        try:
            msg_id = codec.peek_message_id(data)
            if msg_id == codec.NAT_FRAMEOFDATA:
                version = state.stream_version
                if version is None:
                    return  # before SERVERINFO we cannot know the layout
                self._on_frame(codec.decode_packet(data, version), host_time)
                return
            msg = codec.decode_packet(data, state.stream_version or codec.MIN_VERSION)
        except ProtocolError as exc:
            self.bad_packets += 1
            if data[:2] == b"\x05\x00" and state.model_def is None:  # MODELDEF during handshake
                self.channel.put(exc)
            if self.bad_packets <= 5 or self.bad_packets % 1000 == 0:
                self.log.warning("undecodable NatNet packet #%d (%d bytes): %s", self.bad_packets, len(data), exc)
            return
        if isinstance(msg, codec.ServerInfo) and state.handshake_done:
            rejoin, requests = state.on_reannounce(msg)
            if rejoin:
                self.frames.rejoin()
            for request in requests:
                self.channel.send(request)
        elif isinstance(msg, codec.ModelDef) and state.connected and state.model_def is not None:
            state.on_model_def(msg)
        elif isinstance(msg, codec.MessageString):
            self.log.info("Motive says: %s", msg.text)
        elif state.pending_bitstream and isinstance(msg, (codec.Response, codec.UnrecognizedRequest)):
            state.on_bitstream_reply(msg)
        else:
            self.channel.put(msg)

    def _on_frame(self, frame: codec.FrameOfData, host_time: float) -> None:
        reason = self.frames.offer(frame, host_time)
        if reason is not None:
            self.log.warning("NatNet server restarted (%s); re-reading model definitions", reason)
            self.channel.send(codec.RequestModelDef())
