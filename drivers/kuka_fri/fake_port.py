"""The fake Sunrise's UDP socket: it sends from the FRI port once a client holds it, as a
Sunrise cabinet does (``FakeSunrise`` in ``fake.py`` uses it)."""

from __future__ import annotations

import logging
import select
import socket
import time
from typing import Callable

log = logging.getLogger("remaster.fake.sunrise")

#: Wall seconds between tries to take the FRI port, until a client holds its port (``claim``).
CLAIM_EVERY_S = 0.5


class FriPort:
    """A non-blocking UDP socket to one FRI client, on loopback.

    client_address: (host, port) of the FRI client. controller_host: the loopback address the
    cabinet sends from, on the client's port (the FRI port) once it can be taken; until then an
    ephemeral port on 127.0.0.1.
    """

    def __init__(self, client_address: tuple[str, int], controller_host: str) -> None:
        self.client_address = client_address
        self.controller_host = controller_host
        self.on_fri_port = False
        self._warned = False
        self._next_claim = 0.0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.setblocking(False)

    @property
    def address(self) -> tuple[str, int]:
        """The (host, port) answers go to."""
        return self._sock.getsockname()

    def claim(self, on_answer: Callable[[bytes], None]) -> None:
        """Send from the FRI port (``controller_host``:client port) once a client holds its
        port, as Sunrise does. Not before: a client that binds the port on every address (KUKA's
        SDK does, without ``SO_REUSEADDR``) could not start while we held it. If the client holds
        it on every address we cannot bind it either: we keep sending from an ephemeral port
        (such a client answers whoever sent). KUKA's SDK given a controller host ``connect()``s,
        which on Linux narrows its socket to one local address (127.0.0.1 for 127.0.0.2), so the
        port on ``controller_host`` is then free. Answers already queued on the old socket go to
        ``on_answer``. Tried at most every ``CLAIM_EVERY_S``."""
        now = time.monotonic()
        if self.on_fri_port or now < self._next_claim:
            return
        self._next_claim = now + CLAIM_EVERY_S
        host, port = self.client_address
        probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            probe.bind((host, port))  # succeeds only while no client holds the port
        except OSError:
            pass
        else:
            return
        finally:
            probe.close()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.controller_host, port))
        except OSError as exc:
            sock.close()
            if not self._warned:
                self._warned = True
                log.info(  # such a client answers whoever sends: it works, it is only not a cabinet's port
                    "fake Sunrise: sending from %s:%d, not the FRI port %s:%d (%s): the FRI client holds its "
                    "port on every address (KUKA's SDK example started without a controller host)",
                    *self._sock.getsockname(), self.controller_host, port, exc)
            return
        sock.setblocking(False)
        old, self._sock = self._sock, sock
        self.on_fri_port = True
        self._drain(old, on_answer)
        old.close()
        log.info("fake Sunrise: sending from the FRI port %s:%d", self.controller_host, port)

    def collect_until(self, deadline: float, on_answer: Callable[[bytes], None]) -> None:
        """Hand every answer that arrives before ``deadline`` (``time.monotonic()``) to
        ``on_answer``, then whatever is queued: our own thread may have been descheduled past the
        deadline, which is not the client's fault."""
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            ready, _, _ = select.select([self._sock], [], [], remaining)
            if ready:
                self._drain(self._sock, on_answer)
        self._drain(self._sock, on_answer)

    def send(self, data: bytes) -> None:
        try:
            self._sock.sendto(data, self.client_address)
        except OSError as exc:  # e.g. ECONNREFUSED from an earlier ICMP: keep sending
            log.debug("fake Sunrise: send failed: %s", exc)

    def close(self) -> None:
        self._sock.close()

    @staticmethod
    def _drain(sock: socket.socket, on_answer: Callable[[bytes], None]) -> None:
        while True:
            try:
                data, _addr = sock.recvfrom(65536)
            except BlockingIOError:
                return
            except OSError as exc:  # ICMP port unreachable surfaces here on Linux
                log.debug("fake Sunrise: receive failed: %s", exc)
                return
            on_answer(data)
