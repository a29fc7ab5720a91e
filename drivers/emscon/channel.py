"""``EmsconChannel``: the TCP connection to one emScon server and its command exchange.

emScon TPI is one binary packet per command and one answer per command (``drivers.emscon.codec``
frames and decodes them), with unsolicited ``ES_DT_SystemStatusChange`` notifications in
between. One command is in flight at a time (an ``RLock`` serialises callers). Answers match
commands by command id (emScon has no request ids), so after a timeout the connection is
closed and the next command opens a new one (``auto_reconnect``): a late answer can never be
taken for the next. Errors: a refused command raises the class ``drivers.emscon.status`` maps
its ``ES_ResultStatus`` to; no answer in time → DeviceTimeoutError; transport closed →
ConnectionLostError; unreadable bytes → ProtocolError.
"""

from __future__ import annotations

import collections
import logging
import select
import socket
import threading
import time
from urllib.parse import urlsplit

from drivers.base import Clock, check_timeout
from drivers.emscon import codec as es
from drivers.emscon.codec import Cmd, SSC, Status
from drivers.emscon.status import WARNINGS, error_for, status_name
from drivers.errors import ConnectionLostError, DeviceTimeoutError, ProtocolError


def parse_url(url: str) -> tuple[str, int]:
    """``emscon://host[:port]`` → (host, port); port 700 by default."""
    if not isinstance(url, str):
        raise ValueError(f"url must be emscon://host[:port], got {url!r}")
    parts = urlsplit(url)
    if parts.scheme != "emscon" or not parts.hostname or parts.path not in ("", "/") or parts.query:
        raise ValueError(f"url must be emscon://host[:port] (port {es.DEFAULT_PORT} by default), got {url!r}")
    try:
        port = parts.port or es.DEFAULT_PORT
    except ValueError:
        raise ValueError(f"bad port in {url!r}: emscon://host[:port] with a port 1..65535") from None
    return parts.hostname, port


class EmsconChannel:
    """The command channel to the emScon server at ``url``.

    name: device name for errors and logs; reply_timeout: seconds for an ordinary answer (and
    for a send); auto_reconnect: a command on a closed channel opens it again (else
    ConnectionLostError); clock: host time source for answers and notifications (s).
    ``events``: notifications as (ES_SystemStatusChange, host time), newest last;
    ``beam_ready``: beam state from the last MeasStatus notification (None: not told yet).
    """

    def __init__(self, url: str, *, name: str, reply_timeout: float, auto_reconnect: bool, clock: Clock,
                 log: logging.Logger) -> None:
        self.host, self.port = parse_url(url)
        self.url = url
        self.name = name
        self.reply_timeout = check_timeout(reply_timeout)
        self.auto_reconnect = auto_reconnect
        self.clock = clock
        self.log = log
        self.events: collections.deque[tuple[int, float]] = collections.deque(maxlen=256)
        self.beam_ready: bool | None = None
        #: held by a caller that needs several commands without another caller's in between
        self.lock = threading.RLock()
        self._sock: socket.socket | None = None
        self._buf = bytearray()
        self._frames: collections.deque[bytes] = collections.deque()

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def open(self) -> None:
        """Connect (TCP_NODELAY, non-blocking). DeviceTimeoutError / ConnectionLostError."""
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.reply_timeout)
        except socket.timeout as exc:
            raise DeviceTimeoutError(f"{self.name}: no emScon server answered at {self.host}:{self.port} "
                                     f"within {self.reply_timeout:.3g} s") from exc
        except OSError as exc:
            raise ConnectionLostError(f"{self.name}: cannot connect to the emScon server at {self.host}:{self.port}: "
                                      f"{exc}; is the server running and the port right (default 700)?") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self._sock = sock
        self._buf.clear()
        self._frames.clear()
        self.log.info("connected to emScon server %s:%d", self.host, self.port)

    def close(self) -> None:
        with self.lock:
            if self._sock is None:
                return
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._sock.close()
            self._sock = None
            self.log.info("closed %s:%d", self.host, self.port)

    def request(self, req: es.Request, timeout: float | None = None) -> es.Answer:
        """Send ``req`` and return its answer (raises the mapped error for a refusal)."""
        return self.exchange(req, timeout)[0]

    def exchange(self, req: es.Request, timeout: float | None = None, *, want_result: bool = False):
        """Send ``req``; return (answer, host time). ``want_result``: wait for the
        ``SingleMeasResult`` (StartMeasurement). GetReflectors returns the list of its answers
        (the server sends one per reflector and says how many in each)."""
        timeout = self.reply_timeout if timeout is None else check_timeout(timeout)
        with self.lock:
            if self._sock is None:
                if not self.auto_reconnect:
                    raise ConnectionLostError(f"{self.name}: not connected to {self.url}; call connect()")
                self.open()
            data = es.encode(req)
            self._send(data)
            deadline = time.monotonic() + timeout
            got: list[es.Answer] = []
            what = f"{self.name}: {req.command.name}"
            while True:
                frame = self._read_frame(deadline)
                if frame is None:
                    self.close()  # a late answer must not be taken for the next command's
                    raise DeviceTimeoutError(f"{what}: no answer within {timeout:.3g} s from {self.host}:{self.port}")
                host_time = self.clock()
                try:
                    packet = es.decode(frame)
                except ProtocolError as exc:
                    self.close()
                    raise ProtocolError(f"{what}: unreadable packet from the server: {exc}") from None
                if isinstance(packet, es.StatusChange):
                    self._note(packet.change, host_time)
                    continue
                if isinstance(packet, es.ErrorAnswer):
                    if packet.command in (req.command, Cmd.Unknown):
                        raise error_for(packet.status, f"{what} (ES_DT_Error)")
                    self.log.debug("discarding an error answer to command %d", packet.command)
                    continue
                if isinstance(packet, es.DataResult):
                    if want_result and packet.type in (es.DataType.SingleMeasResult, es.DataType.SingleMeasResult2,
                                                       es.DataType.StationaryProbeMeasResult):
                        if packet.status != Status.AllOK and packet.status not in WARNINGS:
                            raise error_for(packet.status, f"{what} result")
                        return packet, host_time
                    self.log.debug("discarding an unexpected %s", packet.type.name)
                    continue
                if packet.command != req.command:
                    self.log.debug("discarding an answer to %s while waiting for %s", packet.command, req.command.name)
                    continue
                if packet.status != Status.AllOK:
                    if packet.status not in WARNINGS:
                        raise error_for(packet.status, what)
                    self.log.warning("%s: executed with %s", what, status_name(packet.status))
                if want_result:
                    continue  # the continuous-mode style confirmation; the result follows
                if req.command is not Cmd.GetReflectors:
                    return packet, host_time
                got.append(packet)
                if len(got) >= max(1, int(packet.values.get("iTotalReflectors", 1))):
                    return got, host_time

    def _note(self, change: int, host_time: float) -> None:
        self.events.append((change, host_time))
        try:
            name = SSC(change).name
        except ValueError:
            name = str(change)
        if change == SSC.MeasStatus_NotReady:
            self.beam_ready = False
        elif change == SSC.MeasStatus_Ready:
            self.beam_ready = True
        self.log.info("server notification %s", name)

    def _send(self, data: bytes) -> None:
        view = memoryview(data)
        deadline = time.monotonic() + self.reply_timeout
        while view:
            try:
                n = self._sock.send(view)
                view = view[n:]
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([], [self._sock], [], left)[1]:
                    self.close()
                    raise DeviceTimeoutError(f"{self.name}: could not send to {self.host}:{self.port} "
                                             f"within {self.reply_timeout:.3g} s") from None
            except OSError as exc:
                self.close()
                raise ConnectionLostError(f"{self.name}: connection to {self.host}:{self.port} lost: {exc}") from exc

    def _read_frame(self, deadline: float) -> bytes | None:
        while not self._frames:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                ready, _, _ = select.select([self._sock], [], [], remaining)
                if not ready:
                    return None
                data = self._sock.recv(65536)
            except BlockingIOError:
                continue
            except OSError as exc:
                self.close()
                raise ConnectionLostError(f"{self.name}: connection to {self.host}:{self.port} lost: {exc}") from exc
            if not data:
                self.close()
                raise ConnectionLostError(f"{self.name}: the emScon server at {self.host}:{self.port} closed the connection")
            self._buf += data
            try:
                self._frames.extend(es.split_frames(self._buf))
            except ProtocolError as exc:
                self.close()
                raise ProtocolError(f"{self.name}: {exc}") from None
        return self._frames.popleft()
