"""A simulated cell started for a run: its fake devices up, described as any cell is.

``SimulatedCell(cell_file, …).start()`` builds the ``SimCell`` on its own ``SimClock``, starts
every fake on loopback (``SimLaunch``) and ``describe(…)`` hands over a
``drivers.cell.CellDescription`` — device URLs per plan device, the cell's clock, and the
cell's timing allowances (``allowances`` in the cell file, wall ms) in the commander URL's
query — exactly what a real cell's description holds. The run never sees more than that.

What only a simulation has — the hidden truth — is asked of this object after the run
(``truth_offsets_deg``, ``mean_sag_deg``), by whoever wants to print it beside the fit.

``acquire run --fake`` is "start this, then run"; ``acquire daemon`` with ``fake`` starts one
for its whole life and describes it to every run. The devices run in a process of their own, at
SCHED_FIFO where the host permits it (``drivers.sim.process.CellProcess``), as a real cell's
controller and sensors are machines of their own: the run's fit, recorder and bus cannot make
the simulated controller late. ``process=False`` keeps them as threads of this process (for a
test that reaches into a fake device). Units: ms and s as named; angles deg.
"""

from __future__ import annotations

import logging
import math
import socket
from pathlib import Path
from typing import Sequence

import numpy as np

from drivers.cell import CellDescription
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH
from drivers.sim.launch import SimLaunch
from drivers.sim.process import CellProcess

log = logging.getLogger(__name__)

#: Simulated seconds per wall second when nobody says (a plan without a ``fake`` section).
DEFAULT_TIME_SCALE = 4.0
#: Shortest wall time of one fake controller cycle (see ``SimulatedCell.fri_send_period_ms``).
MIN_WALL_PERIOD_S = 0.002
#: The commander driver that speaks to each kind of controller (``RobotModel.controller``).
COMMANDER_OF_CONTROLLER = {"sunrise": "fri", "kss": "rsi"}
#: The fake device kind (``DeviceAddress.kind``) each position-sensor driver talks to.
DEVICE_OF_DRIVER = {"natnet": "natnet", "tracker": "tracker", "emscon": "emscon"}
#: Sensor drivers that are no device: the robot is the instrument and the cell's operator
#: guides it (their URL passes through unchanged; the cell needs a ``sockets`` section).
OPERATOR_DRIVERS = ("socket",)


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port on ``host`` free right now, for the commander the fake controller sends to."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class SimulatedCell:
    """The simulated cell of one cell file, started on loopback.

    cell_file: the cell YAML (``drivers.sim.config``; None: the packaged default). seed:
    overrides the file's. time_scale: simulated seconds per wall second (> 0). sensors: the
    (name, driver) of the plan sensors it will be described for — decides which protocols its
    trackers speak; empty: every tracker speaks both (line and emScon). max_runtime_s: wall
    seconds after which the fake controller stops sending by itself. process: run the devices
    in a process of their own (``CellProcess``, real-time where permitted); False: as threads of
    this one (``SimLaunch``: a test can reach into a fake device through ``launch``).
    """

    def __init__(self, cell_file: str | Path | None = None, *, seed: int | None = None,
                 time_scale: float = DEFAULT_TIME_SCALE, sensors: Sequence[tuple[str, str]] = (),
                 max_runtime_s: float = 3600.0, process: bool = True) -> None:
        self.cell_file = Path(cell_file) if cell_file is not None else DEFAULT_CONFIG_PATH
        self.time_scale = float(time_scale)
        self.clock = SimClock(self.time_scale)
        self.cell = SimCell.from_yaml(self.cell_file, seed=seed, clock=self.clock)
        self.sensors = [(str(n), str(d)) for n, d in sensors]
        self.max_runtime_s = float(max_runtime_s)
        self.process = bool(process)
        self.port: int | None = None
        self.launch: SimLaunch | CellProcess | None = None

    # --- what the cell is --------------------------------------------------------------------
    @property
    def commander_driver(self) -> str | None:
        """The commander driver this cell's controller speaks (fri, rsi), None if it has none."""
        return COMMANDER_OF_CONTROLLER.get(self.cell.model.controller)

    def robot_mismatch(self, n_joints: int, controller: str, name: str = "the plan's robot") -> str | None:
        """Why a plan for a robot of ``n_joints`` axes on a ``controller`` cannot run here, or None."""
        m = self.cell.model
        if m.n_joints == n_joints and m.controller == controller:
            return None
        return (f"the simulated cell {self.cell_file} has a {m.name} ({m.n_joints} axes, {m.controller}); "
                f"{name} has {n_joints} axes on a {controller} controller; give a matching cell file")

    def fri_send_period_ms(self) -> int:
        """The fake Sunrise's send period (simulated ms): FRI allows 1–100 ms; one cycle lasts at
        least ``MIN_WALL_PERIOD_S`` of wall time, so a faster-than-real-time cell does not ask
        Python for sub-millisecond exchanges. The commander steps its trajectory by the period
        the controller reports, so the motion and every per-cycle limit check stay exact."""
        return int(min(100, max(5, math.ceil(MIN_WALL_PERIOD_S * 1000.0 * self.time_scale))))

    def _tracker_protocols(self) -> dict[str, tuple[str, ...]]:
        trackers = [s.name for s in self.cell.config.sensors if s.kind == "tracker"]
        if not self.sensors:
            return {t: ("line", "emscon") for t in trackers}
        out: dict[str, list[str]] = {}
        for name, driver in self.sensors:
            proto = {"tracker": "line", "emscon": "emscon"}.get(driver)
            if proto is None or not trackers:
                continue
            target = name if name in trackers else trackers[0]
            if proto not in out.setdefault(target, []):
                out[target].append(proto)
        return {k: tuple(v) for k, v in out.items()}

    # --- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "SimulatedCell":
        """Start every fake; the controller sends to a free loopback port the commander will
        bind (a commander not listening yet is what a real controller meets too)."""
        if self.launch is not None:
            raise RuntimeError("the simulated cell is already started")
        self.port = free_udp_port()
        options = dict(fri_port=self.port, rsi_port=self.port, fri_send_period_ms=self.fri_send_period_ms(),
                       tracker_protocols=self._tracker_protocols(), max_runtime_s=self.max_runtime_s)
        if self.process:  # the cell file and seed again in the child: its own SimCell, on this clock
            self.launch = CellProcess(self.cell_file, clock=self.clock, seed=self.cell.config.seed,
                                      launch_options=options).start()
        else:
            self.launch = SimLaunch(self.cell, **options).start()
        # (``describe()`` carries ``launch.describe()`` lines as notes: whoever opens the devices logs them)
        return self

    def close(self) -> None:
        """Stop every fake (idempotent)."""
        if self.launch is not None:
            self.launch.close()
            self.launch = None

    def __enter__(self) -> "SimulatedCell":
        return self.start() if self.launch is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- the description ---------------------------------------------------------------------
    def commander_url(self, driver: str | None = None) -> str:
        """The commander's URL: the port the fake controller sends to, with the cell file's
        allowances (wall ms × time scale = simulated ms, the commander's clock) in the query."""
        if self.launch is None or self.port is None:
            raise RuntimeError("start the simulated cell before asking for its URLs")
        driver = driver or self.commander_driver
        a = self.cell.config.allowances
        silence, age = a.silence_ms * self.time_scale, a.state_age_ms * self.time_scale
        if driver == "fri" and self.commander_driver == "fri":
            return f"fri://127.0.0.1:{self.port}?timeout_ms={silence:g}&max_state_age_ms={age:g}"
        if driver == "rsi" and self.commander_driver == "rsi":
            return f"rsi://127.0.0.1:{self.port}?max_state_age_s={age / 1000.0:g}"
        raise ValueError(f"the simulated cell's controller ({self.cell.model.controller}) speaks "
                         f"{self.commander_driver or 'no commander protocol'}; given commander driver {driver!r}")

    def sensor_url(self, name: str, driver: str, url: str = "") -> str:
        """The fake device address for a plan sensor ``name`` of ``driver``: the cell's device of
        that name and kind, else its first device of the kind. An operator-guided sensor
        (``OPERATOR_DRIVERS``) keeps its own ``url``."""
        if self.launch is None:
            raise RuntimeError("start the simulated cell before asking for its URLs")
        if driver in OPERATOR_DRIVERS:
            if self.cell.config.sockets is None:
                raise ValueError(f"sensor {name!r} ({driver}): the simulated cell {self.cell_file} has no sockets "
                                 "section; use a cell with sockets (e.g. fixtures/sim/socket.yaml)")
            return url
        addrs = self.launch.addresses
        kind = DEVICE_OF_DRIVER.get(driver)
        if kind is None and name in addrs:
            return addrs[name].url
        for key in (name, f"{name}-emscon"):
            if key in addrs and addrs[key].kind == kind:
                return addrs[key].url
        for a in addrs.values():
            if a.kind == kind:
                return a.url
        raise ValueError(f"sensor {name!r} ({driver}): the simulated cell has no such device; it has {sorted(addrs)}")

    def describe(self, commander_driver: str | None = None,
                 sensors: Sequence[tuple[str, str, str]] = ()) -> CellDescription:
        """The description a run gets: ``sensors`` are the plan's (name, driver, url)."""
        urls = {name: self.sensor_url(name, driver, url) for name, driver, url in sensors}
        assert self.launch is not None
        return CellDescription(
            commander_url=self.commander_url(commander_driver), sensor_urls=urls, clock=self.clock.now,
            sleep=self.clock.sleep, time_scale=self.time_scale,
            metadata={"cell_source": "simulated", "cell_file": str(self.cell_file),
                      "sim_seed": str(self.cell.config.seed), "time_scale": f"{self.time_scale:g}"},
            notes=tuple(self.launch.describe()),
        )

    @property
    def model(self):
        """The cell's robot model (``calib.robot.model.RobotModel``)."""
        return self.cell.model

    def devices(self) -> list[tuple[str, str, str]]:
        """Every position sensor of the cell, once, as (name, driver, url) — for a daemon that
        serves the cell before any plan names its sensors."""
        if self.launch is None:
            raise RuntimeError("start the simulated cell first")
        addrs = self.launch.addresses
        out = []
        for name in self.cell.config.sensor_names:
            a = addrs.get(name) or addrs.get(f"{name}-emscon")
            if a is not None:
                out.append((name, a.kind, a.url))
        return out

    # --- what only a simulation knows ----------------------------------------------------------
    # (asked of the cell the devices ran around: the cell process's while it runs)
    def truth_offsets_deg(self) -> list[float]:
        """The cell's hidden zero-offsets (deg, controller convention), one per joint."""
        if isinstance(self.launch, CellProcess):
            return self.launch.truth_offsets_deg()
        return [float(v) for v in self.cell.truth.offsets_deg]

    def mean_sag_deg(self, q_rad) -> list[float]:
        """The cell's gravity sag of each joint averaged over configurations ``q_rad`` (k, n)
        rad, deg: a zero-offset fit cannot tell its mean from an offset."""
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        if isinstance(self.launch, CellProcess):
            return self.launch.mean_sag_deg(q)
        return np.degrees(self.cell.deflection(q).mean(axis=0)).tolist()
