"""Fixtures for the emScon tests: a one-reflector scene, the simulated tracker, the fake emScon
server on TCP loopback and a connected ``EmsconSensor``.

The scene is ours (not the simulated cell): a test moves the reflector or breaks the beam by
setting ``scene.position_mm`` / ``scene.visible``.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.emscon.client import EmsconSensor
from drivers.emscon.fake import EmsconServer, FakeEmscon
from drivers.sim.clock import SimClock
from drivers.sim.scene import MarkerObservation
from drivers.tracker.fake import FakeTracker

#: Where the reflector starts, tracker frame, mm (about 2.03 m from the head).
REFLECTOR_MM = (2000.0, 300.0, -100.0)


class OneReflectorScene:
    """A ``MarkerScene`` with one reflector ``smr`` and a switchable line of sight."""

    def __init__(self, position_mm=REFLECTOR_MM, visible: bool = True) -> None:
        self.position_mm = np.asarray(position_mm, dtype=float)
        self.visible = visible

    def observe(self, sensor: str) -> list[MarkerObservation]:
        if sensor != "tracker":
            raise ValueError(f"this scene only serves the tracker, asked for {sensor!r}")
        return [MarkerObservation("smr", self.position_mm.copy(), self.visible)]


@pytest.fixture
def scene() -> OneReflectorScene:
    return OneReflectorScene()


@pytest.fixture
def make_server(scene):
    """``make_server(tracker={...}, server={...})``: an EmsconServer on a FakeTracker (1000×
    simulated clock) on ``scene``; closed at the end of the test."""
    made = []

    def make(tracker: dict | None = None, server: dict | None = None) -> EmsconServer:
        kw = dict(tracker or {})
        kw.setdefault("clock", SimClock(time_scale=1000.0))
        kw.setdefault("seed", 1)
        srv = EmsconServer(FakeEmscon(FakeTracker(scene, **kw), **(server or {})), seed=3)
        made.append(srv)
        return srv

    yield make
    for srv in made:
        srv.close()


@pytest.fixture
def server(make_server) -> EmsconServer:
    return make_server()


@pytest.fixture
def sensor(server):
    """A connected ``EmsconSensor`` on ``server``."""
    with EmsconSensor(server.url, reply_timeout=5.0) as s:
        yield s
