"""Fixtures for the tracker tests: a one-reflector scene, the fake device and its servers.

The scene is ours (not the simulated cell): a test moves the reflector or breaks the beam by
setting ``scene.position_mm`` / ``scene.visible``.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerObservation
from drivers.tracker.client import TrackerSensor
from drivers.tracker.fake import FakeTracker, PtyTrackerServer, TcpTrackerServer

#: Where the reflector starts, tracker frame, mm (about 2.03 m from the head).
REFLECTOR_MM = (2000.0, 300.0, -100.0)


class OneReflectorScene:
    """A ``MarkerScene`` with one reflector ``smr`` and a switchable line of sight."""

    def __init__(self, position_mm=REFLECTOR_MM, visible: bool = True) -> None:
        self.position_mm = np.asarray(position_mm, dtype=float)
        self.visible = visible
        #: when set, the beam breaks after this many more observations (mid-command breaks)
        self.break_after: int | None = None

    def observe(self, sensor: str) -> list[MarkerObservation]:
        if sensor != "tracker":
            raise ValueError(f"this scene only serves the tracker, asked for {sensor!r}")
        if self.break_after is not None:
            if self.break_after <= 0:
                self.visible, self.break_after = False, None
            else:
                self.break_after -= 1
        return [MarkerObservation("smr", self.position_mm.copy(), self.visible)]


class ManualClock:
    """A device clock that only moves when told (``advance``) or when the device waits."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, sim_seconds: float) -> None:
        self.t += max(0.0, sim_seconds)

    def advance(self, seconds: float) -> None:
        self.t += seconds


@pytest.fixture
def manual_clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def scene() -> OneReflectorScene:
    return OneReflectorScene()


@pytest.fixture
def make_device(scene):
    """``make_device(**overrides)``: a FakeTracker on ``scene`` with a 1000× simulated clock."""

    def make(**kw) -> FakeTracker:
        kw.setdefault("clock", SimClock(time_scale=1000.0))
        kw.setdefault("seed", 1)
        return FakeTracker(scene, **kw)

    return make


@pytest.fixture
def device(make_device) -> FakeTracker:
    return make_device()


@pytest.fixture(params=["tcp", "pty"])
def server(request, device):
    """The fake tracker served over TCP loopback and over a pseudo-terminal."""
    cls = TcpTrackerServer if request.param == "tcp" else PtyTrackerServer
    srv = cls(device, seed=3)
    yield srv
    srv.close()


@pytest.fixture
def tcp_server(device):
    srv = TcpTrackerServer(device, seed=3)
    yield srv
    srv.close()


@pytest.fixture
def tracker(server):
    """A connected ``TrackerSensor`` on ``server`` (both transports)."""
    with TrackerSensor.from_url(server.url, reply_timeout=2.0) as sensor:
        yield sensor
