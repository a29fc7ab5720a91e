"""UDP receive with the kernel's arrival time stamp (Linux ``SO_TIMESTAMPNS``).

A thread may wake up some time after a datagram arrived (scheduling, the GIL); judging "late"
by the wake-up time would blame the sender for the receiver's delay. With kernel stamps both
the fake controller (deadline check) and the commander (answer latency) measure from the
moment the packet reached the host. Stamps are ``time.time()`` seconds (CLOCK_REALTIME); where
the option is not available the stamp is the time ``recvfrom`` returned.
"""

from __future__ import annotations

import socket
import struct
import sys
import time

# Linux values (asm-generic and x86): SO_TIMESTAMPNS_OLD == SCM_TIMESTAMPNS_OLD == 35.
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")
_CMSG_SPACE = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0


def enable_rx_timestamps(sock: socket.socket) -> bool:
    """Ask the kernel to stamp received datagrams; False when the platform cannot."""
    if not sys.platform.startswith("linux") or not _CMSG_SPACE:
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def recv_stamped(sock: socket.socket, bufsize: int, stamped: bool) -> tuple[bytes, tuple, float]:
    """(data, source address, arrival wall time in s). Raises what ``recvfrom`` raises."""
    if not stamped:
        data, addr = sock.recvfrom(bufsize)
        return data, addr, time.time()
    data, anc, _flags, addr = sock.recvmsg(bufsize, _CMSG_SPACE)
    for level, typ, payload in anc:
        if level == socket.SOL_SOCKET and typ == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(payload)
            return data, addr, sec + nsec * 1e-9
    return data, addr, time.time()
