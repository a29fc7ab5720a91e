"""The cell's devices while no run holds them (``DeviceHost``), and where the daemon's cell comes from.

A daemon serves one cell. A real cell is its configuration: the configured commander and
sensors while idle, and every plan's own device URLs for a run (``acquire.run.plan_cell``). A
simulated cell is started by ``acquire daemon`` (``acquire.commands.fake.daemon_cell``) before the
daemon, and handed to it as a ``CellSource``: the same object describes its devices to the idle
host and to every run, which cannot tell it from a real cell.
"""

from __future__ import annotations

import logging
from typing import Protocol, Sequence

from acquire.daemon.config import DaemonConfig
from drivers.cell import CellDescription
from drivers.errors import DriverError

log = logging.getLogger(__name__)

#: Wall seconds to wait for the idle devices to come up.
DEVICE_START_TIMEOUT_S = 20.0


class CellSource(Protocol):
    """A cell that describes itself (``drivers.sim.running.SimulatedCell`` is one).

    model: its robot model (``calib.robot.model.RobotModel``: joint limits of the idle commander).
    commander_driver: the driver its controller speaks (fri, rsi). devices(): its position
    sensors as (name, driver, url). describe(commander_driver, sensors): the
    ``CellDescription`` for a plan's commander driver and (name, driver, url) sensors
    (ValueError when the cell has no such device). robot_mismatch(n_joints, controller, name):
    why a plan's robot cannot run here, or None.
    """

    model: object
    commander_driver: str | None

    def devices(self) -> list[tuple[str, str, str]]: ...

    def describe(self, commander_driver: str | None = None,
                 sensors: Sequence[tuple[str, str, str]] = ()) -> CellDescription: ...

    def robot_mismatch(self, n_joints: int, controller: str, name: str = ...) -> str | None: ...


def cell_for_plan(source: CellSource | None, lp) -> CellDescription:
    """The description a run of ``lp`` gets: ``source``'s devices for the plan's, or without a
    source the plan's own URLs. ValueError when the cell cannot run the plan."""
    from acquire.run import plan_cell

    if source is None:
        return plan_cell(lp)
    problem = source.robot_mismatch(lp.model.n_joints, lp.model.controller, f"the plan's robot {lp.model.name}")
    if problem:
        raise ValueError(problem)
    return source.describe(lp.plan.commander.driver, [(s.name, s.driver, s.url) for s in lp.plan.sensors])


class DeviceHost:
    """The cell's devices while no run holds them.

    Without a ``source``: the configured commander (``connect`` binds its port and starts its
    exchange thread) and sensors; a real controller streams only while its robot program runs.
    With a ``source`` (a cell that describes itself, e.g. the simulated cell): a commander of
    the cell's controller kind at the cell's commander URL, on the cell's clock, streaming.
    """

    def __init__(self, cfg: DaemonConfig, source: CellSource | None = None) -> None:
        self.cfg = cfg
        self.source = source
        self.commander = None
        self.sensors: list = []
        self.expect_stream = False
        self.names: list[str] = []

    def open(self) -> list[str]:
        """Bring every device up; returns their names. On failure everything is closed again."""
        try:
            if self.source is not None:
                self._open_described()
            else:
                self._open_configured()
        except BaseException:
            self.close()
            raise
        return list(self.names)

    def _open_configured(self) -> None:
        from acquire.run import open_commander, open_sensor
        from calib.robot.model import load_robot_model
        from drivers.protocols import JointLimits

        if self.cfg.commander is None and not self.cfg.sensors:
            raise ValueError("no devices to bring up: the configuration has none, and no cell was handed over "
                             "(with 'fake', `acquire daemon` starts the simulated cell and hands it to the daemon)")
        names = []
        if self.cfg.commander is not None:
            model = load_robot_model(self.cfg.robot)
            cmd = open_commander(self.cfg.commander, JointLimits.from_model(model))
            cmd.name = self.cfg.commander.name
            self.commander = cmd
            cmd.connect()
            names.append(self.cfg.commander.name)
        for spec in self.cfg.sensors:
            self.sensors.append(open_sensor(spec))
            names.append(spec.name)
        # A real controller streams only while its robot program runs: no stream expected idle.
        self.expect_stream = False
        self.names = names

    def _open_described(self) -> None:
        from drivers.protocols import JointLimits
        from drivers.registry import load_driver

        src = self.source
        driver = src.commander_driver
        if driver is None:
            raise ValueError("the cell's controller has no commander driver; allowed: sunrise (fri), kss (rsi)")
        cell = src.describe(driver, [])
        for line in cell.notes:
            log.info("cell: %s", line)
        cmd = load_driver(driver).from_url(cell.commander_url, limits=JointLimits.from_model(src.model),
                                           clock=cell.clock)
        cmd.name = "controller"
        self.commander = cmd
        cmd.connect()
        cmd.first_state(DEVICE_START_TIMEOUT_S)  # up = the first measured state has arrived
        self.expect_stream = True
        self.names = ["controller"] + [name for name, _driver, _url in src.devices()]

    def close(self) -> None:
        """Stop and close every device (idempotent)."""
        cmd, self.commander = self.commander, None
        if cmd is not None:
            try:
                cmd.close()
            except (OSError, DriverError) as exc:
                log.warning("closing %s: %s", getattr(cmd, "name", "commander"), exc)
        for s in self.sensors:
            try:
                s.close()
            except (OSError, DriverError) as exc:
                log.warning("closing %s: %s", getattr(s, "name", "sensor"), exc)
        self.sensors = []
        self.expect_stream = False
