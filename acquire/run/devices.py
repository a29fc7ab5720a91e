"""Opening and closing a run's devices, through the cell's description.

``plan_cell(lp)`` is a real cell's ``drivers.cell.CellDescription``: the plan's own URLs and the
host's clock. ``RunDevices(lp, cell).open()`` builds the plan's commander (its driver, options
and joint limits) at ``cell.commander_url`` and every plan sensor at ``cell.sensor_url(name)``,
all on the cell's clock — the same code whether the cell is real or simulated (a simulated
cell describes itself: ``drivers.sim.running``). ``close()`` stops and closes them.
"""

from __future__ import annotations

import inspect
import logging

from acquire.plan.schema import JOINT_SENSOR_DRIVERS
from acquire.run.summary import RunError
from acquire.run.sequencer import SensorSpec
from drivers.cell import CellDescription
from drivers.errors import DriverError
from drivers.protocols import JointLimits
from drivers.registry import load_driver

log = logging.getLogger(__name__)


def plan_cell(lp) -> CellDescription:
    """A cell as its plan describes it: the plan's device URLs, the host's monotonic clock."""
    plan = lp.plan
    return CellDescription(commander_url=plan.commander.url, sensor_urls={s.name: s.url for s in plan.sensors},
                           metadata={"cell_source": "plan"})


def _accepts(fn, name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


def open_commander(spec, limits: JointLimits, *, url: str | None = None, **extra):
    """Build (not connect) the plan's commander: ``load_driver(driver).from_url(url, limits=…)``.

    ``extra`` (e.g. ``clock``/``sleep``) is passed only when the driver accepts it.
    """
    cls = load_driver(spec.driver)
    kwargs = dict(getattr(spec, "options", None) or {})
    for k, v in extra.items():
        if _accepts(cls.__init__, k):
            kwargs[k] = v
    return cls.from_url(url or spec.url, limits=limits, **kwargs)


def open_sensor(spec, *, url: str | None = None, commander=None, **extra):
    """Build and connect one plan sensor. A driver whose ``from_url`` takes ``markers`` gets
    the plan's mapping (plan name → selector); one taking ``marker`` gets the single plan name.
    A joint sensor (``attach``, e.g. the socket sensor) is attached to ``commander``."""
    cls = load_driver(spec.driver)
    kwargs = dict(getattr(spec, "options", None) or {})
    for k, v in extra.items():
        if _accepts(cls.__init__, k):
            kwargs[k] = v
    markers = dict(spec.markers)
    for key in ("environment", "reflector"):  # laser trackers: the same plan values reach every tracker driver
        value = getattr(spec, key, None)
        if value is None:
            continue
        if not _accepts(cls.__init__, key):
            raise ValueError(f"sensor {spec.name!r}: driver {spec.driver!r} takes no {key}")
        kwargs[key] = value.driver_value() if key == "environment" else value.model_dump()
    if _accepts(cls.from_url, "markers") and "markers" in inspect.signature(cls.from_url).parameters:
        sensor = cls.from_url(url or spec.url, markers=markers, **kwargs)
    elif "marker" in inspect.signature(cls.from_url).parameters:
        if len(markers) != 1:
            raise ValueError(f"sensor {spec.name!r}: driver {spec.driver!r} measures one marker; "
                             f"the plan lists {sorted(markers)}")
        sensor = cls.from_url(url or spec.url, marker=next(iter(markers)), **kwargs)
    else:
        sensor = cls.from_url(url or spec.url, **kwargs)
    if _accepts(cls.__init__, "name") or hasattr(sensor, "name"):
        sensor.name = spec.name
    if callable(getattr(sensor, "attach", None)):
        if commander is None:
            raise ValueError(f"sensor {spec.name!r}: driver {spec.driver!r} reads the robot's joint states; "
                             "open the commander first")
        sensor.attach(commander)
    sensor.connect()
    return sensor


class RunDevices:
    """The run's commander and sensors (``acquire.run.sequencer.SensorSpec`` each), opened at the
    cell's URLs on the cell's clock. ``open()`` returns (commander, sensors); ``close()`` stops
    the commander (it decelerates) and closes everything, idempotently."""

    def __init__(self, lp, cell: CellDescription) -> None:
        self.lp = lp
        self.cell = cell
        self.commander = None
        self.sensors: list[SensorSpec] = []

    def open(self):
        plan, cell = self.lp.plan, self.cell
        for line in cell.notes:
            log.info("cell: %s", line)
        extra = {"clock": cell.clock, "sleep": cell.sleep}
        cmd = open_commander(plan.commander, JointLimits.from_model(self.lp.model), url=cell.commander_url, **extra)
        self.commander = cmd
        cmd.connect()
        for s in plan.sensors:
            kw = {"clock": cell.clock, **({"sleep": cell.sleep} if s.driver in JOINT_SENSOR_DRIVERS else {})}
            try:
                url = cell.sensor_url(s.name)
            except KeyError as exc:
                raise RunError(f"sensor {s.name!r}: {exc.args[0]}") from None
            self.sensors.append(SensorSpec(open_sensor(s, url=url, commander=cmd, **kw), list(s.markers),
                                           float(s.noise_mm)))
        return cmd, self.sensors

    def close(self) -> None:
        cmd, self.commander = self.commander, None
        for sensor in self.sensors:
            try:
                sensor.sensor.close()
            except (OSError, DriverError) as exc:
                log.warning("closing %s: %s", getattr(sensor.sensor, "name", "sensor"), exc)
        self.sensors = []
        if cmd is not None:
            try:
                cmd.stop()
            except DriverError as exc:
                log.warning("stop at the end: %s", exc)
            try:
                cmd.close()
            except (OSError, DriverError) as exc:
                log.warning("closing the commander: %s", exc)
