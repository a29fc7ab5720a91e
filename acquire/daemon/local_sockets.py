"""Unix sockets on the cell PC, seen from both ends: who may connect, and who is listening.

The daemon serves its operators on Unix sockets (the control socket, ``acquire.daemon.control_socket``,
and the Zenoh listener ``unixsock-stream//run/remaster/zenoh.sock``). The kernel guards both ends,
with nothing of our own design:

- **Who may connect** (the daemon's side, ``hand_to_group``): ``connect(2)`` on a Unix socket needs
  write permission on its file. The daemon makes each socket ``<its user>:<operators' group>``,
  mode 0660, in a folder nobody else may write (systemd's ``RuntimeDirectory=remaster``). Any other
  account gets EACCES before a byte is exchanged.
- **Who is listening** (the client's side): a client sends nothing (no request, no SCRAM
  client-first or client-final) until it knows the listener is the daemon's account. Root, the
  client's own uid and the daemon's account (``REMASTER_DAEMON_USER``, default ``remaster``) are
  trusted (``trusted_uids``).

  - On the control socket the kernel says who listens: ``SO_PEERCRED`` of the connected socket
    gives the uid of the process that called ``listen()`` (``check_listener``).
  - On a Zenoh ``unixsock-stream`` endpoint, Zenoh gives no access to the socket, so the client
    checks the path before it connects (``check_socket_path``): the socket and every folder above
    it must belong to a trusted uid, and no other account may write any of those folders. Only a
    trusted account can then have created, or can replace, the socket at that path. This follows
    OpenSSH's ``StrictModes`` check of a key's path.
  - TCP on loopback carries no owner a client can check. While the daemon is down (or
    restarting) any local process can listen on its port. So a client sends credentials over
    ``tcp/`` to nobody, and believes only replies that say so (``credential_endpoint_problem``).
    Remote callers use ``tls/`` or ``quic/`` with the CA that signed the daemon's certificate.
"""

from __future__ import annotations

import grp
import os
import pwd
import socket
import stat
import struct
from dataclasses import dataclass
from pathlib import Path

#: The daemon's account when ``REMASTER_DAEMON_USER`` is not set (the systemd unit's ``User=``).
DEFAULT_DAEMON_USER = "remaster"
#: Zenoh's protocol name for a Unix stream socket endpoint (``unixsock-stream//run/remaster/zenoh.sock``).
UNIXSOCK = "unixsock-stream"
#: Where a client on the cell PC reaches the daemon's Zenoh router by default.
DEFAULT_ZENOH_SOCKET = "/run/remaster/zenoh.sock"
DEFAULT_LOCAL_ENDPOINT = f"{UNIXSOCK}/{DEFAULT_ZENOH_SOCKET}"
#: Endpoints whose server a client authenticates by its certificate (given the CA).
_CERTIFIED = ("tls", "quic")
#: Linux's SO_PEERGROUPS (socket(7), since 4.13); Python's socket module does not name it.
_SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)


class UntrustedPeer(PermissionError):
    """The listener could be another account than the daemon's; the message says why and what to do."""


@dataclass(frozen=True)
class Listener:
    """Whom a client expects at a Zenoh endpoint, as the checks' messages name it and say what to set."""

    name: str            # "the daemon"
    socket: str          # its Unix socket, e.g. /run/remaster/zenoh.sock (its folder: systemd's RuntimeDirectory)
    listen_field: str    # where its listen endpoints are configured
    account_hint: str    # what to set when it runs as another account
    ca_hint: str         # where the client names the CA that signed its certificate
    instead: str         # what a client uses instead of an endpoint nothing authenticates

    @property
    def folder(self) -> str:
        return os.path.dirname(self.socket)


#: The cell's daemon, seen from the CLI on the cell PC (``acquire.commands.daemon``).
DAEMON = Listener(
    "the daemon", DEFAULT_ZENOH_SOCKET, "zenoh.listen", "set REMASTER_DAEMON_USER", "--tls-ca",
    f"On the cell PC use the control socket (no --connect, no --client) or the daemon's {DEFAULT_LOCAL_ENDPOINT}; "
    "from elsewhere tls/HOST:PORT with --tls-ca")


# ------------------------------------------------------------------------- the daemon's side
def resolve_group(group: str | int, field: str = "control_socket.group") -> int:
    """The gid of ``group`` (a name or a number); ValueError naming ``field`` when it does not exist."""
    if isinstance(group, int) or str(group).isdigit():
        return int(group)
    try:
        return grp.getgrnam(str(group)).gr_gid
    except KeyError:
        raise ValueError(f"{field}: no group {group!r} on this host; create it "
                         f"(groupadd --system {group}) and add the operators to it") from None


def group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def check_socket_folder(path: Path, runtime_directory: str = "remaster") -> None:
    """OSError unless the folder of the socket ``path`` exists and others may not write it (else
    anyone could put their own socket in the listener's place); ``runtime_directory``: the
    systemd unit's ``RuntimeDirectory=`` that makes it."""
    folder = Path(path).parent
    if not folder.is_dir():
        raise OSError(f"socket folder {folder} does not exist (systemd makes it: RuntimeDirectory={runtime_directory})")
    if stat.S_IMODE(folder.stat().st_mode) & stat.S_IWOTH:
        raise OSError(f"socket folder {folder} is writable by others: anyone could replace the socket; "
                      f"chmod o-w {folder}")


def hand_to_group(path: Path, gid: int | None) -> None:
    """Give the socket at ``path`` (made by this process) to group ``gid`` with mode 0660, or
    keep it to this process's user (mode 0600) when ``gid`` is None. OSError saying what to do
    when the group cannot be given (the daemon's user must be in that group)."""
    try:
        if gid is not None:
            os.chown(path, -1, gid)
        os.chmod(path, 0o600 if gid is None else 0o660)
    except OSError as exc:
        raise OSError(f"cannot give socket {path} to group {group_name(gid) if gid is not None else '-'}: "
                      f"{exc.strerror or exc} (the service's user must be in that group: SupplementaryGroups= of its unit)") from exc


def peer_credentials(conn: socket.socket) -> tuple[int, int, int, frozenset[int]]:
    """(pid, uid, gid, supplementary gids) of the process at the other end of ``conn``, as the
    kernel recorded them (the client's at ``connect()``; the server's at ``listen()``)."""
    pid, uid, gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    try:
        raw = conn.getsockopt(socket.SOL_SOCKET, _SO_PEERGROUPS, 1024)  # 256 groups: Python's largest buffer
        groups = frozenset(struct.unpack(f"{len(raw) // 4}I", raw))
    except OSError:  # more than 256 groups, or a kernel before 4.13: the account's groups instead
        try:
            groups = frozenset(os.getgrouplist(pwd.getpwuid(uid).pw_name, gid))
        except KeyError:
            groups = frozenset()
    return pid, uid, gid, groups | {gid}


def user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


# ------------------------------------------------------------------------- the client's side
def daemon_user() -> str:
    """The daemon's account: ``$REMASTER_DAEMON_USER``, else ``remaster``."""
    return os.environ.get("REMASTER_DAEMON_USER") or DEFAULT_DAEMON_USER


def trusted_uids(user: str | None = None) -> frozenset[int]:
    """The uids a listener may have: root, this process's own, and the daemon's account ``user``
    (default ``daemon_user()``; a name or a number; ignored when no such account exists)."""
    user = user or daemon_user()
    uids = {0, os.getuid()}
    if user.isdigit():
        uids.add(int(user))
    else:
        try:
            uids.add(pwd.getpwnam(user).pw_uid)
        except KeyError:
            pass
    return frozenset(uids)


def _trusted_text(trusted: frozenset[int]) -> str:
    return ", ".join(sorted(user_name(u) for u in trusted))


def check_listener(conn: socket.socket, path: Path, trusted: frozenset[int]) -> None:
    """UntrustedPeer unless the process listening at the other end of the connected Unix socket
    ``conn`` runs as one of ``trusted`` (the kernel's SO_PEERCRED)."""
    pid, uid, _, _ = peer_credentials(conn)
    if uid not in trusted:
        raise UntrustedPeer(f"{path} is served by uid {uid} ({user_name(uid)}), pid {pid}, not by the daemon's "
                            f"account (allowed: {_trusted_text(trusted)}); nothing was sent. If the daemon runs as "
                            "another user, set REMASTER_DAEMON_USER")


def check_socket_path(path: str | Path, trusted: frozenset[int], listener: Listener = DAEMON) -> None:
    """UntrustedPeer unless only ``trusted`` accounts can have put a socket at ``path``: it is a
    socket, and it, every folder above it and every link on the way (as written and with links
    resolved) belong to one of them, and no folder is writable by anybody else (a sticky folder
    such as /tmp counts as unwritable: its entries can be replaced only by their owners).
    ``listener``: whom the messages name."""
    given = Path(os.path.abspath(path))
    real = Path(os.path.realpath(given))
    who = listener.name
    if not os.path.lexists(real):
        raise UntrustedPeer(f"no socket at {path}: is {who} running, with {UNIXSOCK}/{path} among its "
                            f"{listener.listen_field} endpoints?")
    for chain in dict.fromkeys((given, real)):  # a link in the path: both its folders and its target's
        for entry in (*reversed(chain.parents), chain):
            try:
                st = os.lstat(entry)
            except OSError as exc:
                raise UntrustedPeer(f"cannot check {entry} on the way to {path}: {exc.strerror or exc}") from None
            mode = stat.S_IMODE(st.st_mode)
            if st.st_uid not in trusted and entry == chain and not stat.S_ISLNK(st.st_mode):
                raise UntrustedPeer(f"the socket {path} belongs to uid {st.st_uid} ({user_name(st.st_uid)}), not to "
                                    f"{who}'s account (allowed: {_trusted_text(trusted)}). If {who} runs "
                                    f"as another user, {listener.account_hint}")
            if st.st_uid not in trusted:
                raise UntrustedPeer(f"{entry} (on the way to {path}) belongs to uid {st.st_uid} "
                                    f"({user_name(st.st_uid)}), who could put a socket there; allowed owners: "
                                    f"{_trusted_text(trusted)}")
            if stat.S_ISDIR(st.st_mode) and mode & (stat.S_IWGRP | stat.S_IWOTH) and not mode & stat.S_ISVTX:
                raise UntrustedPeer(f"{entry} (on the way to {path}) has mode {mode:04o}: other accounts may "
                                    "write it and put a socket there. Allowed: folders that "
                                    f"only their owner may write ({who}'s is {listener.folder}, mode 0755)")
    if not stat.S_ISSOCK(os.lstat(real).st_mode):
        raise UntrustedPeer(f"{path} is not a socket")


def socket_path_of(endpoint: str) -> str | None:
    """The file of a ``unixsock-stream/<path>`` Zenoh endpoint, or None for another protocol."""
    proto, _, rest = endpoint.partition("/")
    if proto != UNIXSOCK:
        return None
    return rest.split("#", 1)[0].split("?", 1)[0]


def credential_endpoint_problem(endpoint: str, *, tls_ca: Path | str | None, trusted: frozenset[int],
                                listener: Listener = DAEMON) -> str | None:
    """Why a client must not send a credential to (or believe an unsigned reply from) Zenoh
    ``endpoint``, or None when the listener there is authenticated: a ``unixsock-stream`` socket
    that passes ``check_socket_path``, or ``tls/``/``quic/`` with the CA ``tls_ca`` that signed
    the listener's certificate. ``listener``: whom the messages name, and what they advise."""
    path = socket_path_of(endpoint)
    if path is not None:
        try:
            check_socket_path(path, trusted, listener)
        except UntrustedPeer as exc:
            return str(exc)
        return None
    proto = endpoint.partition("/")[0]
    if proto in _CERTIFIED:
        if tls_ca is None:
            return (f"give {listener.ca_hint} (the CA that signed {listener.name}'s certificate), or nothing "
                    "authenticates the listener")
        return None
    return (f"nothing authenticates a {proto}/ listener: while {listener.name} is down any local "
            f"process can listen there. {listener.instead}")
