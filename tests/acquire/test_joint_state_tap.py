"""The joint-state tap: a tick that cannot be recorded is skipped with a warning; only a closed
log ends the tap (it once ended on any error, and the run's /joint_state and /tf went silent)."""

from __future__ import annotations

import json
import logging
import time

import numpy as np
from mcap.reader import make_reader

from acquire.record.recorder import RunLog
from acquire.run import JointStateTap
from drivers.protocols import JointState

Q = np.radians([10.0, -80.0, 80.0, 5.0, 50.0, -20.0])


class StubCommander:
    name = "robot"

    def joint_state(self) -> JointState:
        return JointState(position_rad=Q.copy(), device_time=time.monotonic(), host_time=time.time())


class FailingOnce:
    """A run log whose first ``fail`` joint-state writes raise ``error``; the rest go through."""

    def __init__(self, log: RunLog, error: Exception, fail: int = 2) -> None:
        self.log, self.error, self.fail = log, error, fail
        self.written = 0

    @property
    def closed(self) -> bool:
        return self.log.closed

    def record_joint_state(self, *args, **kwargs) -> None:
        if self.fail > 0:
            self.fail -= 1
            raise self.error
        self.log.record_joint_state(*args, **kwargs)
        self.written += 1


def wait_for(predicate, timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_a_failed_tick_is_skipped_with_a_warning_and_the_tap_goes_on(tmp_path, caplog):
    path = tmp_path / "run.mcap"
    log = RunLog.create(path, run_id="tap", plan_text="", model_text="", metadata={})
    flaky = FailingOnce(log, OSError(28, "No space left on device"))
    names = ["A1", "A2", "A3", "A4", "A5", "A6"]
    with caplog.at_level(logging.WARNING, logger="acquire.run"):
        tap = JointStateTap(StubCommander(), flaky, None, "cell", names, period_s=0.005).start()
        try:
            assert wait_for(lambda: flaky.written >= 3), "the tap stopped after a failed tick"
        finally:
            tap.stop()
    log.close()
    warnings = [r.getMessage() for r in caplog.records if "joint state not recorded" in r.getMessage()]
    assert warnings and "No space left on device" in warnings[0]
    with open(path, "rb") as fh:
        docs = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=["/joint_state"])]
    assert len(docs) == flaky.written >= 3
    np.testing.assert_allclose(docs[-1]["position_rad"], Q, atol=1e-8)


def test_the_tap_ends_when_the_log_is_closed(tmp_path):
    log = RunLog.create(tmp_path / "run.mcap", run_id="tap", plan_text="", model_text="", metadata={})
    tap = JointStateTap(StubCommander(), log, None, "cell", ["A1", "A2", "A3", "A4", "A5", "A6"], period_s=0.005).start()
    log.close()
    assert wait_for(lambda: not tap._thread.is_alive(), 10.0)  # ended on its own, not by stop()
