"""The main process dies (kill -9) mid-move: the FRI exchange process decelerates within the
limits by itself, holds, then stops answering as the SDK's client does when its application
disconnects; Sunrise ends commanding (the session drops to MONITORING_WAIT) and sees nothing
malformed."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from fri_helpers import assert_timed_commands_within_limits, iiwa14_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from orphan_helpers import CommanderProcess, process_ended  # noqa: E402

from drivers.kuka_fri.fake import FakeSunrise  # noqa: E402
from drivers.kuka_fri.messages import SessionState  # noqa: E402

Q0 = np.radians([0.0, 30.0, 0.0, -45.0, 0.0, 30.0, 0.0])
FAR = np.radians([80.0, 70.0, -60.0, -100.0, 90.0, 80.0, 120.0])

SCRIPT = f"""
import sys
import numpy as np
from fri_helpers import iiwa14_limits
from drivers.kuka_fri.commander import FriCommander
from drivers.kuka_fri.messages import SessionState

c = FriCommander.from_url("fri://127.0.0.1:0", limits=iiwa14_limits(), orphan_hold_s=0.5)
c.connect()
print("port", c.address[1], flush=True)
print("exchange", c.exchange_pid, flush=True)
sys.stdin.readline()
c.wait_session(SessionState.COMMANDING_ACTIVE, 5.0)
print("moving", flush=True)
c.move_to(np.array({FAR.tolist()!r}), 1.0, 20.0)
print("arrived", flush=True)
"""

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kill -9 and /proc: Linux")


def test_kill_9_mid_move_decelerates_within_limits_holds_and_ends_commanding():
    limits = iiwa14_limits()
    owner = CommanderProcess(SCRIPT, Path(__file__).parent)
    fake = None
    try:
        port = int(owner.expect("port"))
        exchange_pid = int(owner.expect("exchange"))
        fake = FakeSunrise(("127.0.0.1", port), limits=limits, initial_position_rad=Q0, rt_priority=40)
        fake.start()
        fake.wait_state(SessionState.MONITORING_READY, 5.0)
        fake.start_commanding()
        fake.wait_state(SessionState.COMMANDING_ACTIVE, 5.0)
        owner.say("go")
        owner.expect("moving")
        deadline = time.monotonic() + 10.0
        while len(fake.stats.commands) < 150 or np.abs(fake.stats.commands[-1][1] - Q0).max() < math.radians(10):
            assert time.monotonic() < deadline, "the move did not start"
            time.sleep(0.005)
        owner.kill9()
        killed_at = len(fake.stats.commands)
        fake.wait_state(SessionState.MONITORING_WAIT, 10.0)
        assert process_ended(exchange_pid, 5.0), "the exchange process outlived its job"
        stats = fake.stats
        commands = list(stats.commands)
        drops = stats.session_drops
    finally:
        owner.close()
        if fake is not None:
            fake.stop()
    assert drops == 1 and stats.violations == []
    assert stats.malformed_answers == 0 and stats.bad_reflections == 0
    # every set-point within the limits, the deceleration included
    assert_timed_commands_within_limits(commands, limits, 0.005)
    q = np.array([c[1] for c in commands])
    assert np.abs(q[killed_at - 1] - q[killed_at - 2]).max() > math.radians(0.1)  # moving when it died
    assert np.all(np.abs(q[-1] - FAR) > math.radians(5))  # stopped short of the target
    # held at rest for the grace (0.5 s = 100 answers of 5 ms) before it fell silent
    np.testing.assert_allclose(q[-80:] - q[-1], 0.0, atol=1e-12)
