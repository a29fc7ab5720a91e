"""A small client of systemd's service notification protocol (``sd_notify(3)``), no dependency.

The service manager passes the address of a Unix datagram socket in ``NOTIFY_SOCKET``: a path
(``/run/systemd/notify``) or, when it starts with ``@``, a name in the abstract namespace (the
``@`` stands for a leading NUL byte). Each notification is one datagram of newline-separated
``KEY=VALUE`` assignments:

- ``READY=1`` — start-up finished (``Type=notify`` units are "active" only after it);
- ``STATUS=…`` — one free-form line shown by ``systemctl status``;
- ``WATCHDOG=1`` — keep-alive; with ``WatchdogSec=`` set, systemd passes ``WATCHDOG_USEC``
  (microseconds; and ``WATCHDOG_PID``, the pid that must ping) and kills the service when no
  ping arrives within that time. Ping about twice per interval;
- ``STOPPING=1`` — shutdown has begun; ``RELOADING=1``; ``EXTEND_TIMEOUT_USEC=…`` — ask for more
  time during start-up or shutdown.

Without ``NOTIFY_SOCKET`` (run from a terminal) every call is a no-op that returns False. A send
that fails is logged (at most once per kind of failure) and never raised: the service keeps
working; the watchdog of systemd will notice if pings stop reaching it.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from typing import Mapping

log = logging.getLogger(__name__)


def socket_address(value: str) -> str | bytes:
    """The ``sendto`` address for a ``NOTIFY_SOCKET`` value: ``@name`` → ``b"\\0name"``
    (abstract namespace), ``/path`` → ``"/path"``. Raises ValueError for anything else
    (systemd also allows ``vsock:`` addresses, which this client does not support)."""
    if not value:
        raise ValueError("NOTIFY_SOCKET is empty; expected an absolute path or @abstract-name")
    if value.startswith("@"):
        if len(value) < 2:
            raise ValueError(f"NOTIFY_SOCKET {value!r}: an abstract name needs at least one character after @")
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    raise ValueError(
        f"NOTIFY_SOCKET {value!r} is not supported; expected an absolute path or @abstract-name"
    )


def watchdog_interval_s(env: Mapping[str, str], pid: int | None = None) -> float | None:
    """The watchdog timeout in seconds from ``WATCHDOG_USEC`` (None when there is no watchdog,
    or when ``WATCHDOG_PID`` names another process). Raises ValueError for a malformed value."""
    raw = env.get("WATCHDOG_USEC")
    if not raw:
        return None
    want_pid = env.get("WATCHDOG_PID")
    if want_pid:
        try:
            if int(want_pid) != (os.getpid() if pid is None else pid):
                return None
        except ValueError as exc:
            raise ValueError(f"WATCHDOG_PID must be a process id, given {want_pid!r}") from exc
    try:
        usec = int(raw)
    except ValueError as exc:
        raise ValueError(f"WATCHDOG_USEC must be an integer number of microseconds, given {raw!r}") from exc
    if usec <= 0:
        raise ValueError(f"WATCHDOG_USEC must be positive, given {raw!r}")
    return usec / 1e6


class SdNotifier:
    """Sends notifications to the service manager. Thread-safe.

    address: a ``NOTIFY_SOCKET`` value; None reads the environment (no socket → disabled).
    ``watchdog_s`` is the watchdog timeout (seconds) systemd announced, or None.
    """

    def __init__(self, address: str | None = None, *, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        value = address if address is not None else env.get("NOTIFY_SOCKET")
        self._address = socket_address(value) if value else None
        self.watchdog_s = watchdog_interval_s(env)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._failed: set[str] = set()
        self.sent = 0

    @property
    def enabled(self) -> bool:
        """True when there is a notification socket to send to."""
        return self._address is not None

    def notify(self, **fields: object) -> bool:
        """Send one datagram of ``KEY=VALUE`` lines (keys upper-cased, values one line each).
        Returns True if the datagram was sent, False when disabled or on a (logged) failure."""
        if self._address is None:
            return False
        lines = []
        for k, v in fields.items():
            text = str(v)
            if "\n" in text:
                raise ValueError(f"notification {k}= must be one line, given {text!r}")
            lines.append(f"{k.upper()}={text}")
        data = "\n".join(lines).encode()
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.sendto(data, self._address)
            except OSError as exc:
                kind = type(exc).__name__
                if kind not in self._failed:
                    self._failed.add(kind)
                    log.warning("sd_notify to %r failed: %s", self._address, exc)
                return False
            self.sent += 1
            return True

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (with a status line if given)."""
        return self.notify(READY=1, **({"STATUS": status} if status is not None else {}))

    def status(self, text: str) -> bool:
        """``STATUS=text``: one line for ``systemctl status``."""
        return self.notify(STATUS=text)

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the service is healthy."""
        return self.notify(WATCHDOG=1)

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        return self.notify(STOPPING=1, **({"STATUS": status} if status is not None else {}))

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: ask for ``seconds`` more before a start/stop timeout."""
        if not seconds > 0:
            raise ValueError(f"extend_timeout needs a positive number of seconds, given {seconds!r}")
        return self.notify(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))

    def close(self) -> None:
        """Close the socket (idempotent)."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None
