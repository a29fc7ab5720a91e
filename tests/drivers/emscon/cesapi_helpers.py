"""CESAPI 1.1.3 (the independent emScon peer) driven the way its ``CommandSync`` reads answers,
polling its buffer with a short sleep instead of busy-waiting a core. Shared by the emScon
tests and ``acquire sim``'s device test."""

from __future__ import annotations

import time

from CESAPI import packet as P

WAIT_S = 20.0

def execute(stream, packet, *, result: bool = False, wait_s: float = WAIT_S):
    """Send ``packet`` with CESAPI and return its answer (the measurement result with
    ``result``) the way CESAPI's CommandSync reads them, skipping notifications."""
    stream.write(packet)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if stream.unreadCount() == 0:
            time.sleep(0.01)
            continue
        got = stream.read()
        kind = P.packetType(got)
        if kind in (P.ES_DT_SingleMeasResult, P.ES_DT_SingleMeasResult2) and result:
            return got
        if kind == P.ES_DT_Error:
            return got
        if kind == P.ES_DT_Command and got.packetInfo.command == packet.packetInfo.command:
            if not result or got.packetInfo.status != P.ES_RS_AllOK:
                return got
    raise AssertionError(f"no answer to command {packet.packetInfo.command} within {wait_s} s")
