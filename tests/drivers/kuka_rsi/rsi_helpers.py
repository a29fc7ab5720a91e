"""Helpers for the RSI tests: KR 6 limits, a commander + fake KR C4 rig, command-stream checks."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import time

import numpy as np

from drivers.kuka_rsi.commander import RsiCommander
from drivers.kuka_rsi.fake import FakeKrc4, ReceivedCommand
from drivers.protocols import JointLimits

#: KUKA KR 6 R900-2 numbers (fixtures/robots/kuka_kr6_r900_2.yaml), degrees.
KR6_LOWER = [-170, -190, -120, -185, -120, -350]
KR6_UPPER = [170, 45, 156, 185, 120, 350]
KR6_SPEED = [360, 300, 360, 450, 450, 540]
KR6_ACCEL = [1080, 900, 1080, 1350, 1350, 1620]
HOME_DEG = [0.0, -90.0, 90.0, 0.0, 45.0, 0.0]

#: Wire rounding (7 decimals): a difference of two values is off by at most 1e-7°, a second
#: difference by 2e-7°.
WIRE_SLACK_DEG = 2.5e-7


def kr6_limits(speed_scale: float = 1.0, accel_scale: float = 1.0) -> JointLimits:
    return JointLimits(
        lower_rad=np.radians(KR6_LOWER),
        upper_rad=np.radians(KR6_UPPER),
        max_velocity_rad_s=np.radians(KR6_SPEED) * speed_scale,
        max_acceleration_rad_s2=np.radians(KR6_ACCEL) * accel_scale,
        names=("A1", "A2", "A3", "A4", "A5", "A6"),
    )


@contextlib.contextmanager
def rig(limits: JointLimits | None = None, *, fake_kwargs=None, connect=True, **commander_kwargs):
    """A commander on an ephemeral loopback port and a fake KR C4 sending to it."""
    limits = limits or kr6_limits()
    # (the exchange process takes seconds to start beside CPU hogs and other test workers)
    commander_kwargs.setdefault("connect_timeout", 30.0)
    fake_kwargs = dict(fake_kwargs or {})
    fake_kwargs.setdefault("initial_deg", HOME_DEG)
    fake_kwargs.setdefault("max_runtime_s", 60.0)
    if not fake_kwargs.get("lockstep"):
        fake_kwargs.setdefault("rt_priority", 40)  # keep the 4 ms cycle on a loaded test host
    else:
        # The lockstep fake is an ordinary thread of this process (it answers as fast as the
        # exchange does, so a real-time one would hold a CPU): on a loaded machine it can stall
        # for a few hundred ms between packets. Lockstep tests check the command stream, so the
        # commander's silence and staleness limits are widened (silence is tested in real time).
        commander_kwargs.setdefault("timeout_cycles", 500)
        commander_kwargs.setdefault("max_state_age_s", 2.0)
    c = RsiCommander(limits, host="127.0.0.1", port=0, **commander_kwargs)
    f = FakeKrc4(c.bind(), **fake_kwargs)
    try:
        f.start()
        if connect:
            c.connect()
        yield c, f
    finally:
        c.close()
        f.close()


def stream_excess(
    commands: list[ReceivedCommand], ref_deg, limits: JointLimits, dt: float
) -> dict[str, float]:
    """How far the answered AK stream goes beyond the limits, cycle by cycle (≤ 0: within).

    Returns the worst (value − limit) in degrees for the position, the per-cycle step (velocity)
    and the per-cycle second difference (acceleration); the robot is at rest before the first.
    """
    ak = np.array([c.correction_deg for c in commands], dtype=float)
    ak = np.vstack([ak[:1], ak[:1], ak])
    pos = np.asarray(ref_deg, dtype=float) + ak
    step = np.abs(np.diff(ak, axis=0))
    acc = np.abs(np.diff(ak, n=2, axis=0))
    v = np.degrees(limits.max_velocity_rad_s) * dt
    a = np.degrees(limits.max_acceleration_rad_s2) * dt**2
    lo, hi = np.degrees(limits.lower_rad), np.degrees(limits.upper_rad)
    return {
        "position": float(max((lo - pos).max(), (pos - hi).max())),
        "velocity": float((step - v).max() - WIRE_SLACK_DEG),
        "acceleration": float((acc - a).max() - WIRE_SLACK_DEG),
        "velocity_ratio": float((step / v).max()),
        "acceleration_ratio": float((acc / a).max()),
    }


def assert_stream_within_limits(commands, ref_deg, limits, dt=0.004) -> dict[str, float]:
    assert len(commands) > 2, "no command stream to check"
    ex = stream_excess(commands, ref_deg, limits, dt)
    assert ex["position"] <= 0, ex
    assert ex["velocity"] <= 0, ex
    assert ex["acceleration"] <= 0, ex
    return ex


def deg(x) -> np.ndarray:
    return np.radians(np.asarray(x, dtype=float))


SETTLE_TOL = math.radians(0.0005)


def pause_process(pid: int, seconds: float) -> None:
    """Stop process ``pid`` for ``seconds`` (SIGSTOP/SIGCONT): an exchange process the host did
    not schedule, seen from the controller as late answers."""
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)
