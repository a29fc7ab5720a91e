"""The daemon's local control plane: a Unix socket that the OS guards and that names its caller.

Why: on Zenoh, every local account reaches the router on loopback, sees what is routed to the
queryables it declares, and shares the daemon's SCRAM state (a flood of client-firsts once
evicted an operator's pending abort). Here the operating system does the authentication, with
nothing of our own design:

- **Who can connect**: the socket file is ``<daemon user>:<group>``, mode 0660 (``connect(2)``
  needs write permission on it): the operators' group, the daemon's user and root. Any other
  account gets EACCES from the kernel before a byte is exchanged.
- **Who connected**: the kernel's peer credentials of the connection (``SO_PEERCRED``: pid, uid,
  gid; ``SO_PEERGROUPS``: the supplementary groups at ``connect()``), checked again by the daemon:
  a caller must be root, the daemon's own user, or hold the group — a socket someone made wider
  by hand still lets nobody else in.
- **Who listens**: the client checks the kernel's peer credentials too — the uid of the process
  that listens at the path (``SO_PEERCRED``) must be root, the client's own or the daemon's
  account (``acquire.daemon.local_sockets``) — before it sends its request, so a socket another
  account put at a path an operator was given (``--socket``) neither reads a request nor
  answers one that is believed.
- **No secret**: nothing travels that a reader could reuse and nothing is stored in the daemon's
  configuration for local callers, so a configuration reader has nothing to act with; and a
  stream socket is point to point: no other account sees a request.
- **No shared state to exhaust**: a connection is served by a thread of its own, at most
  ``MAX_PER_UID`` at once per uid and ``MAX_CONNECTIONS`` in all, none of them touched by what
  arrives over Zenoh. ``abort`` and ``pause`` need no exchange and no table.

Framing (not a security protocol: the kernel authenticates): the client sends one JSON object
``{"op": OPERATION, "request": {…}}`` and a newline, at most ``MAX_REQUEST_BYTES`` plus a little;
the daemon answers with one JSON object and a newline — the same reply bodies as on Zenoh
(``{"ok": true, …}`` or ``{"ok": false, "error": KIND, "message": …}``) — and closes. Every
refusal is one warning line, rate-limited per uid.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import stat
import threading
from pathlib import Path
from typing import Any, Callable

from acquire.daemon.control import (
    MAX_REQUEST_BYTES,
    OPERATIONS,
    BadRequest,
    ControlError,
    Identity,
    NoReply,
    Refused,
    Unverified,
    outcome,
)
from acquire.daemon.local_sockets import (
    UntrustedPeer,
    check_listener,
    check_socket_folder,
    group_name,
    hand_to_group,
    peer_credentials,
    resolve_group,
    trusted_uids,
    user_name,
)
from acquire.live.logthrottle import Throttle, clip

log = logging.getLogger(__name__)

#: Connections served at once per uid (beyond: refused with "busy"; no uid can starve another).
MAX_PER_UID = 4
#: Connections served at once in all.
MAX_CONNECTIONS = 64
#: Seconds a caller has to send its request.
READ_TIMEOUT_S = 5.0
#: What the server calls to perform an operation: (op, payload bytes or None, identity) → reply body.
Perform = Callable[[str, "bytes | None", Identity], dict]


class ControlSocketServer:
    """Serves control requests on a Unix socket at ``path`` (see the module docstring).

    group: the operators' group (name or gid): the socket's group; its members may connect.
    allow: the permissions a caller holds. perform: does the operation (``ControlServer.perform``).
    """

    def __init__(self, path: Path, group: str | int, allow: list[str], perform: Perform, *,
                 throttle: Throttle | None = None) -> None:
        self.path = Path(path)
        self.gid = resolve_group(group)
        self.allow = frozenset(allow)
        self._perform = perform
        self._throttle = throttle or Throttle()
        self._lock = threading.Lock()
        self._per_uid: dict[int, int] = {}
        self._open = 0
        self.served = 0
        self.refused = 0
        self._sock = self._bind()
        self._thread = threading.Thread(target=self._accept_loop, name="control-socket", daemon=True)
        self._thread.start()
        log.info("control socket %s (group %s, mode 0660): %s", self.path, self._group_name(), sorted(self.allow))

    def _group_name(self) -> str:
        return group_name(self.gid)

    def _bind(self) -> socket.socket:
        check_socket_folder(self.path)
        self._remove_stale()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # born 0600: nobody but us until it has its group
        try:
            sock.bind(str(self.path))
        finally:
            os.umask(old)
        try:
            hand_to_group(self.path, self.gid)
        except OSError:
            sock.close()
            self.path.unlink(missing_ok=True)
            raise
        sock.listen(32)
        return sock

    def _remove_stale(self) -> None:
        """Remove a socket left by a daemon that died; refuse when one still answers there."""
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            raise OSError(f"{self.path} exists and is not a socket; remove it or choose another control_socket.path")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(self.path))
        except OSError:
            self.path.unlink()
            return
        finally:
            probe.close()
        raise OSError(f"another daemon serves the control socket {self.path}")

    def close(self) -> None:
        """Stop accepting (idempotent) and remove the socket; requests being served finish."""
        sock, self._sock = self._sock, None
        if sock is None:
            return
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        sock.close()
        self._thread.join(5)
        self.path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ serving
    def _accept_loop(self) -> None:
        while True:
            sock = self._sock
            if sock is None:
                return
            try:
                conn, _ = sock.accept()
            except OSError:
                return
            try:
                self._admit(conn)
            except Exception:  # noqa: BLE001 - one bad connection must not stop the control plane
                log.debug("control socket: connection dropped", exc_info=True)
                conn.close()

    def _admit(self, conn: socket.socket) -> None:
        pid, uid, gid, groups = peer_credentials(conn)
        who = f"uid {uid} ({user_name(uid)}), pid {pid}"
        if uid not in (0, os.getuid()) and self.gid not in groups:
            self._refuse(conn, who, f"not in group {self._group_name()}")
            return
        with self._lock:
            busy = self._per_uid.get(uid, 0) >= MAX_PER_UID or self._open >= MAX_CONNECTIONS
            if not busy:
                self._per_uid[uid] = self._per_uid.get(uid, 0) + 1
                self._open += 1
        if busy:
            self._refuse(conn, who, f"busy: {MAX_PER_UID} requests of this uid (or {MAX_CONNECTIONS} in all) "
                                    "are being served", kind="conflict")
            return
        identity = Identity(f"uid {uid} ({user_name(uid)})", None, None, self.allow)
        threading.Thread(target=self._serve, args=(conn, uid, identity), name=f"control-socket-{uid}",
                         daemon=True).start()

    def _refuse(self, conn: socket.socket, who: str, reason: str, kind: str = "refused") -> None:
        with self._lock:
            self.refused += 1
        self._warn(who, "control socket: refused %s: %s", who, reason)
        try:
            conn.settimeout(0.2)  # take the request off the wire (unread, it would turn the close into a reset)
            try:
                conn.recv(65536)
            except OSError:
                pass
            conn.sendall(_line({"ok": False, "error": kind, "message": reason}))
            conn.shutdown(socket.SHUT_WR)
        except OSError:
            pass
        finally:
            conn.close()

    def _serve(self, conn: socket.socket, uid: int, identity: Identity) -> None:
        try:
            conn.settimeout(READ_TIMEOUT_S)
            try:
                op, payload = _read_request(conn)
                body = {"ok": True, **self._perform(op, payload, identity)}
            except ControlError as exc:
                if isinstance(exc, BadRequest):
                    self._warn(identity.client, "control socket: bad request from %s: %s", identity.client, clip(exc))
                body = {"ok": False, "error": exc.kind, "message": str(exc)}
            except Exception as exc:  # noqa: BLE001 - a bug becomes an error reply, never a hang
                self._warn(identity.client, "control socket: request from %s failed: %s: %s", identity.client,
                           type(exc).__name__, clip(exc))
                log.debug("control socket request failed", exc_info=True)
                body = {"ok": False, "error": "failed", "message": f"{type(exc).__name__}: {clip(exc)}"}
            conn.sendall(_line(body))
            with self._lock:
                self.served += 1
        except OSError as exc:
            log.debug("control socket: %s: %s", identity.client, exc)
        finally:
            conn.close()
            with self._lock:
                self._open -= 1
                self._per_uid[uid] -= 1
                if not self._per_uid[uid]:
                    del self._per_uid[uid]

    def _warn(self, source: str | None, fmt: str, *args: object) -> None:
        dropped = self._throttle.admit(source or "unknown")
        if dropped is None:
            return
        suffix = f" [{dropped} similar lines from {source} suppressed]" if dropped else ""
        log.warning("%s%s", clip(fmt % args, 600), suffix)


def _line(body: dict) -> bytes:
    return json.dumps(body, default=str).encode() + b"\n"


def _read_request(conn: socket.socket) -> tuple[str, bytes | None]:
    """(operation, payload bytes or None) of the one request line on ``conn``; BadRequest if
    it is too long, not JSON or names no operation."""
    limit = MAX_REQUEST_BYTES + 4096
    data = bytearray()
    received = 0
    while not data.endswith(b"\n") and received <= 8 * limit:
        chunk = conn.recv(65536)
        if not chunk:
            break
        received += len(chunk)
        if received <= limit:
            data += chunk
        else:  # read on to the end (bounded) so the caller gets the reply rather than a reset
            data = bytearray(chunk[-1:])
    if received > limit:
        raise BadRequest(f"request longer than {limit} bytes")
    try:
        message = json.loads(bytes(data).decode())
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise BadRequest(f"request is not one JSON object and a newline: {clip(exc, 120)}") from None
    if not isinstance(message, dict) or message.get("op") not in OPERATIONS:
        op = message.get("op") if isinstance(message, dict) else None
        raise BadRequest(f"unknown operation {clip(repr(op), 40)}; allowed: {', '.join(OPERATIONS)}")
    request = message.get("request")
    if request is not None and not isinstance(request, dict):
        raise BadRequest(f"request must be a JSON object, given {type(request).__name__}")
    return message["op"], (json.dumps(request).encode() if request else None)


class SocketClient:
    """The client of the control socket: ``call(op, request)`` returns the reply body or raises
    the ControlError of the reply; Refused when the OS refuses the connection (not in the
    group), NoReply when no daemon serves the socket, Unverified (before anything is sent) when
    the process listening there is not one of ``trusted`` uids (default ``trusted_uids()``: root,
    this user, the daemon's account)."""

    def __init__(self, path: Path, trusted: frozenset[int] | None = None) -> None:
        self.path = Path(path)
        self.trusted = trusted_uids() if trusted is None else trusted

    def call(self, op: str, request: dict[str, Any] | None = None, *, timeout: float = 10.0) -> dict:
        if op not in OPERATIONS:
            raise ValueError(f"unknown operation {op!r}; allowed: {', '.join(OPERATIONS)}")
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout)
            try:
                sock.connect(str(self.path))
            except PermissionError:
                raise Refused(f"permission denied on the control socket {self.path}: only its group may use it "
                              f"({_owner_text(self.path)}); ask for membership, then log in again") from None
            except (FileNotFoundError, ConnectionRefusedError) as exc:
                raise NoReply(f"no daemon serves the control socket {self.path} ({exc.strerror}): is it running, "
                              "with control_socket: in its configuration?") from None
            try:
                check_listener(sock, self.path, self.trusted)
            except UntrustedPeer as exc:
                raise Unverified(str(exc)) from None
            try:
                try:
                    sock.sendall(_line({"op": op, "request": request or None}))
                except (BrokenPipeError, ConnectionResetError):
                    pass  # refused before reading it: the refusal may still be there to read
                data = bytearray()
                while not data.endswith(b"\n"):
                    chunk = sock.recv(65536)
                    if not chunk:
                        break
                    data += chunk
            except socket.timeout:
                raise NoReply(f"no reply to control/{op} on {self.path} within {timeout:g} s") from None
            except ConnectionResetError:
                pass  # a reply that arrived is still parsed below
        try:
            body = json.loads(bytes(data).decode())
        except (UnicodeDecodeError, ValueError):
            raise NoReply(f"the daemon closed the control socket {self.path} without a reply to control/{op}") from None
        if not isinstance(body, dict):
            raise ControlError(f"reply to control/{op} is not a JSON object")
        return outcome(body)


def _owner_text(path: Path) -> str:
    try:
        st = os.stat(path)
        return f"group {group_name(st.st_gid)}"
    except OSError:
        return "see ls -l"
