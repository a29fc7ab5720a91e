"""Hand-guiding under FRI (socket calibration): a person pushes the arm in joint impedance.
Over real UDP: the measured position leaves the commanded one while the commanded stays put, and a session that (re)starts while
the arm is held starts commanding from the interpolator's position, as the FRI SDK's
LBRClient::command() does — not from the pushed, measured one — so nothing jumps."""

from __future__ import annotations

import numpy as np
from fri_helpers import fri_pair

from drivers.kuka_fri.messages import SessionState

Q0 = np.radians([0.0, 20.0, 0.0, -90.0, 0.0, -30.0, 0.0])
PUSH = np.radians([0.0, 0.4, -0.3, 0.2, 0.0, 0.1, 0.0])


def test_a_pushed_arm_reports_its_push_and_restarts_commanding_without_a_jump(limits):
    with fri_pair(limits, initial_position_rad=Q0, send_period_ms=5) as (commander, fake):
        fake.hand_guide(PUSH)
        state = commander.wait_settled(tolerance_rad=1e-5, window_s=0.05, timeout=10.0)
        np.testing.assert_allclose(state.position_rad - state.commanded_rad, PUSH, atol=1e-4)
        np.testing.assert_allclose(state.commanded_rad, Q0, atol=1e-9)
        # the session drops and comes back while the arm is held: no violation, no jump
        fake.stop_commanding()
        fake.wait_state(SessionState.MONITORING_READY, 5.0)
        fake.start_commanding()
        fake.wait_state(SessionState.COMMANDING_ACTIVE, 5.0)
        commander.wait_session(SessionState.COMMANDING_ACTIVE, 5.0)
        target = Q0 + np.radians([5.0, 0, 0, 0, 0, 0, 0])
        commander.move_to(target, 0.5, timeout=10.0)  # starts while the hand is still on the arm
        fake.release()
        state = commander.wait_settled(tolerance_rad=1e-5, window_s=0.05, timeout=10.0)
        np.testing.assert_allclose(state.position_rad, target, atol=1e-4)
        assert fake.stats.violations == []
