"""An outside FRI client against ``acquire sim``: a client written the way KUKA's SDK example
``LBRJointSineOverlay`` behaves (answer every message; in COMMANDING_WAIT echo the ipo position;
in COMMANDING_ACTIVE command ipo + a sine on A4) runs 30 s against the simulated cell's fake
Sunrise, started as a separate process exactly as a user starts it, with no fault."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from drivers.kuka_fri.messages import (
    COMMAND_MESSAGE_ID,
    CommandData,
    FRICommandMessage,
    MessageHeader,
    SessionState,
    decode_monitoring,
)

RUN_S = 30.0
AMPLITUDE_RAD = 0.04  # the SDK example's defaults: 0.04 rad, 0.25 Hz, joint mask A4
FREQUENCY_HZ = 0.25
JOINT = 3


def _realtime() -> None:
    """As an FRI client on a cell PC runs: SCHED_FIFO where permitted."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
    except (AttributeError, PermissionError, OSError):
        pass


@pytest.mark.slow  # a 30 s soak of an SDK-style client
@pytest.mark.parametrize("version", ["2.7"])
def test_an_sdk_style_sine_overlay_client_runs_30_s_against_acquire_sim(version):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(60.0)  # the first message: the process starts (imports) first
    port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "acquire", "sim", "--fri-port", str(port), "--fri-version", version,
         "--duration", str(RUN_S + 60), "--time-scale", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    states, measured, ipo_first, commanded = [], [], None, []
    try:
        _realtime()
        seq, phi, t_active = 0, 0.0, None
        deadline = time.monotonic() + RUN_S + 30.0
        while time.monotonic() < deadline:
            data, addr = sock.recvfrom(4096)
            sock.settimeout(5.0)
            m = decode_monitoring(data)
            state = m.connection_info.session_state
            states.append(state)
            if state == SessionState.IDLE:
                continue  # the SDK sends nothing in IDLE
            cd = None
            if state == SessionState.COMMANDING_WAIT:
                cd = CommandData(joint_position=m.ipo_data.joint_position)
            elif state == SessionState.COMMANDING_ACTIVE:
                if t_active is None:
                    t_active = time.monotonic()
                    ipo_first = np.asarray(m.ipo_data.joint_position)
                q = np.asarray(m.ipo_data.joint_position, dtype=float)
                q[JOINT] += AMPLITUDE_RAD * math.sin(phi)
                phi += 2 * math.pi * FREQUENCY_HZ * m.connection_info.send_period / 1000.0
                cd = CommandData(joint_position=tuple(q.tolist()))
                commanded.append(q)
                measured.append(np.asarray(m.monitor_data.measured_joint_position))
            # monitoring states: FRI 2.x's LBRClient::monitor() sets nothing; a header-only answer
            sock.sendto(FRICommandMessage(MessageHeader(COMMAND_MESSAGE_ID, seq, m.header.sequence_counter),
                                          cd).encode(), addr)
            seq += 1
            if t_active is not None and time.monotonic() - t_active >= RUN_S:
                break
    finally:
        sock.close()
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert t_active is not None, f"the fake Sunrise never started commanding; states {set(states)}\n{out}"
    first = states.index(SessionState.COMMANDING_ACTIVE)
    left = [s for s in states[first:] if s != SessionState.COMMANDING_ACTIVE]
    assert not left, f"the session left COMMANDING_ACTIVE ({left[:3]}): a fault\n{out}"
    assert len(measured) >= RUN_S / 0.005 * 0.5
    a4 = np.asarray(measured)[:, JOINT] - ipo_first[JOINT]
    assert np.ptp(a4) > 1.8 * AMPLITUDE_RAD  # the robot followed the overlay, both ways
    assert np.max(np.abs(a4)) < 1.1 * AMPLITUDE_RAD  # and did not run away (ipo did not accumulate)
    others = np.delete(np.asarray(measured) - ipo_first, JOINT, axis=1)
    assert np.max(np.abs(others)) < 1e-6
