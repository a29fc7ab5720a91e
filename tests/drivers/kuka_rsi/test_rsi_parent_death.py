"""The main process dies (kill -9) mid-move: the RSI exchange process stops the robot within the
limits by itself, holds, sends the Stop flag and exits; the controller sees an orderly end."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rsi_helpers import HOME_DEG, assert_stream_within_limits, kr6_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from orphan_helpers import CommanderProcess, process_ended  # noqa: E402

from drivers.kuka_rsi.fake import FakeKrc4  # noqa: E402

TARGET_DEG = [150.0, -90.0, 90.0, 0.0, 45.0, 0.0]

SCRIPT = f"""
import sys
import numpy as np
from rsi_helpers import kr6_limits
from drivers.kuka_rsi.commander import RsiCommander

c = RsiCommander(kr6_limits(), host="127.0.0.1", port=0, connect_timeout=30.0, orphan_hold_s=0.5)
print("port", c.bind()[1], flush=True)
print("exchange", c.exchange_pid, flush=True)
sys.stdin.readline()
c.connect()
print("moving", flush=True)
c.move_to(np.radians({TARGET_DEG!r}), 1.0, 10.0)
print("arrived", flush=True)
"""

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kill -9 and /proc: Linux")


def test_kill_9_mid_move_stops_within_limits_holds_and_ends_rsi_with_the_stop_flag():
    limits = kr6_limits()
    owner = CommanderProcess(SCRIPT, Path(__file__).parent)
    fake = None
    try:
        port = int(owner.expect("port"))
        exchange_pid = int(owner.expect("exchange"))
        fake = FakeKrc4(("127.0.0.1", port), initial_deg=HOME_DEG, rt_priority=40, max_runtime_s=60)
        fake.start()
        owner.say("go")
        owner.expect("moving")
        deadline = time.monotonic() + 10.0
        while not (fake.received() and fake.received()[-1].correction_deg[0] > 15.0):  # accelerating
            assert time.monotonic() < deadline, "the move did not start"
            time.sleep(0.002)
        owner.kill9()
        killed_at = len(fake.received())
        assert fake.wait_stopped(10.0), "the controller never saw the end of the RSI session"
        assert process_ended(exchange_pid, 5.0), "the exchange process outlived its job"
        stats = fake.stats()
        received = fake.received()
    finally:
        owner.close()
        if fake is not None:
            fake.close()
    assert stats.stopped_reason == "Stop flag from the sensor"
    assert stats.malformed_answers == 0
    assert received[-1].stop and not any(r.stop for r in received[:-1])
    # every cycle within the position, velocity and acceleration limits, the stop included
    assert_stream_within_limits(received, HOME_DEG, limits)
    ak = np.array([r.correction_deg for r in received])
    step = np.abs(np.diff(ak[:, 0]))
    assert step[killed_at - 5 : killed_at].max() > 0.3  # it was moving fast when the owner died
    assert 15.0 < ak[-1, 0] < 120.0  # stopped short of the target (150°), not run to it
    # held at rest for the grace (0.5 s = 125 cycles) before the Stop flag
    held = ak[-100:] - ak[-1]
    np.testing.assert_allclose(held, 0.0, atol=1e-9)
    assert fake.actual_deg()[0] == pytest.approx(ak[-1, 0], abs=0.5)
