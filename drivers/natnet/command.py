"""The command channel to Motive: the UDP socket requests leave from (and, unicast, frames
arrive on), and the replies the receiver thread queues for whoever is waiting for one."""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable

from drivers.base import Clock
from drivers.errors import ConnectionLostError, DeviceTimeoutError, ProtocolError
from drivers.natnet import codec
from drivers.natnet.settings import NatNetSettings

#: Replies kept for a waiter; older ones are dropped.
KEEP_REPLIES = 16


#: What CONNECT says the client is: name and version.
CLIENT_NAME, CLIENT_VERSION = "remaster", (0, 1, 0, 0)


def connect_message(settings: NatNetSettings) -> codec.Connect:
    """The CONNECT this client sends (NatNetLib layout, asking for ``settings.bitstream``
    when set)."""
    return codec.Connect(CLIENT_NAME, CLIENT_VERSION, settings.bitstream_or_any, "natnetlib")


class CommandChannel:
    """Requests to ``settings.server:command_port`` and their replies.

    ``open()`` binds the socket on ``settings.local`` (any port); the receiver thread reads it
    and hands non-frame messages to ``put``; ``wait_for`` sends a request until its reply is
    queued. ``encode_version()`` gives the NatNet version requests are encoded with (None before
    SERVERINFO: the oldest this driver speaks). ``fail`` wakes every waiter with the receiver's
    error.
    """

    def __init__(
        self, settings: NatNetSettings, clock: Clock, log: logging.Logger,
        encode_version: Callable[[], codec.Version | None],
    ) -> None:
        self.settings = settings
        self.clock = clock
        self.log = log
        self.sock: socket.socket | None = None
        self._encode_version = encode_version
        self._cond = threading.Condition()
        self._replies: list[codec.Message | ProtocolError] = []
        self._failure: BaseException | None = None

    @property
    def failure(self) -> BaseException | None:
        """Why the receiver thread stopped, or None."""
        return self._failure

    def open(self) -> socket.socket:
        """Bind the command socket (non-blocking) on ``settings.local``; ConnectionLostError
        when that address cannot be bound."""
        s = self.settings
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((s.local, 0))
        except OSError as exc:
            sock.close()
            raise ConnectionLostError(f"{s.name}: cannot bind a UDP socket on {s.local}: {exc}") from exc
        sock.setblocking(False)
        self.sock = sock
        return sock

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        self.sock = None

    def send(self, msg) -> None:
        """Send ``msg`` to the server; a failed send is logged, not raised (UDP: the retry or
        the silence check notices)."""
        sock, s = self.sock, self.settings
        if sock is None:
            return
        try:
            sock.sendto(codec.encode_packet(msg, self._encode_version() or codec.MIN_VERSION),
                        (s.server, s.command_port))
        except OSError as exc:
            self.log.warning("send %s to %s:%d failed: %s", type(msg).__name__, s.server, s.command_port, exc)

    def put(self, reply: codec.Message | ProtocolError) -> None:
        """Queue a reply (or the error decoding a MODELDEF) for ``wait_for``."""
        with self._cond:
            self._replies.append(reply)
            del self._replies[:-KEEP_REPLIES]
            self._cond.notify_all()

    def fail(self, exc: BaseException) -> None:
        """The receiver stopped: waiters raise ConnectionLostError from ``exc``."""
        with self._cond:
            self._failure = exc
            self._cond.notify_all()

    def wait_for(self, cls, resend, what: str, *, required: bool = True):
        """Send ``resend`` (every 1/4 of the handshake timeout) until a ``cls`` reply arrives
        (``cls``: a message class or a tuple of them); after ``handshake_timeout_s`` raise
        DeviceTimeoutError naming ``what`` (or return None if not ``required``). Replies of
        that class still queued from an earlier request are dropped first. A queued MODELDEF
        decoding error is raised when waiting for a ``codec.ModelDef``."""
        s = self.settings
        with self._cond:
            self._replies = [m for m in self._replies if not isinstance(m, cls)]
        deadline = self.clock() + s.handshake_timeout_s
        retry = s.handshake_timeout_s / 4
        while True:
            self.send(resend)
            until = min(deadline, self.clock() + retry)
            with self._cond:
                while True:
                    if self._failure is not None:
                        raise ConnectionLostError(f"{s.name}: receiver stopped: {self._failure}")
                    for i, m in enumerate(self._replies):
                        if isinstance(m, cls):
                            return self._replies.pop(i)
                        if isinstance(m, ProtocolError) and cls is codec.ModelDef:
                            raise self._replies.pop(i)
                    left = until - self.clock()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            if self.clock() >= deadline:
                if not required:
                    return None
                raise DeviceTimeoutError(
                    f"{s.name}: no {what} from {s.server}:{s.command_port} within "
                    f"{s.handshake_timeout_s} s; is Motive running on {s.server} with streaming "
                    f"enabled and its command port set to {s.command_port}?"
                )
