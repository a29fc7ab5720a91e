"""``--fake``: the simulated cell a plan's ``fake`` section names, started for a run.

``acquire run PLAN --fake`` is "start the simulated cell, then run": ``check_fake_section``
refuses (before anything starts) a ``fake`` section whose cell file is missing, holds another
robot, or lacks a plan sensor — pointing at the plan's line; ``simulated_cell(lp)`` builds the
``drivers.sim.running.SimulatedCell``; after ``start()``, ``describe_for(sim, lp)`` is the
``CellDescription`` the run gets — the same kind a real cell gives. Only ``acquire/commands/``
imports ``drivers.sim``: the run itself never knows its cell is simulated.
"""

from __future__ import annotations

from calib.robot.model import load_robot_model
from calib.io.yamlfile import ConfigError, error_line, locate
from drivers.cell import CellDescription
from drivers.sim.config import DEFAULT_CONFIG_PATH, load_sim_config
from drivers.sim.running import DEFAULT_TIME_SCALE, OPERATOR_DRIVERS, SimulatedCell


def fake_section_errors(lp) -> list[tuple[tuple, str]]:
    """Problems of running ``lp`` against the simulated cell of its ``fake`` section, as
    (field path, message) — none when it can."""
    plan, model = lp.plan, lp.model
    fake = plan.fake
    loc = ("fake", "sim_config")
    path = lp.sim_config_path
    if not path.is_file():
        given = fake.sim_config if fake is not None else None
        return [(loc, f"file not found (given {given!r} → {path}; allowed: a simulated cell YAML, "
                      f"relative to the plan's folder {lp.folder})")]
    try:
        cfg = load_sim_config(path)
        sim_model = load_robot_model(cfg.robot)
    except ConfigError as exc:
        return [(loc, f"the simulated cell is not usable: {exc}")]
    errors: list[tuple[tuple, str]] = []
    if sim_model.name != model.name:
        errors.append((loc, f"the simulated cell has another robot (given a cell with {sim_model.name!r}; "
                            f"allowed: a cell with {model.name!r})"))
    for i, s in enumerate(plan.sensors):
        if s.driver in OPERATOR_DRIVERS:
            if cfg.sockets is None:
                errors.append((("sensors", i, "driver"), f"the simulated cell {path.name} has no sockets for a "
                                                         f"{s.driver} sensor (given {s.driver!r}; allowed: a cell with "
                                                         "a sockets section, e.g. ../sim/socket.yaml)"))
            continue
        if s.name not in cfg.sensor_names:
            errors.append((("sensors", i, "name"), f"no sensor of that name in the simulated cell {path.name} "
                                                   f"(given {s.name!r}; allowed {', '.join(cfg.sensor_names)})"))
    return errors


def check_fake_section(lp) -> None:
    """Raise ``ConfigError`` (``file:line:col: field: …`` one a line) when ``lp`` cannot run
    against its simulated cell."""
    errors = fake_section_errors(lp)
    if errors:
        located = sorted(((locate(tuple(loc), lp.marks) or (0, 0)), error_line(lp.path, lp.marks, loc, msg))
                         for loc, msg in errors)
        raise ConfigError("\n".join(msg for _, msg in located))


def simulated_cell(lp, *, max_runtime_s: float = 3600.0, process: bool = True) -> SimulatedCell:
    """The (not yet started) simulated cell of ``lp``'s ``fake`` section (the packaged default
    cell at ``DEFAULT_TIME_SCALE`` without one), its devices in a real-time process of their own
    (``process=False``: threads of this one). ValueError when its robot is not the plan's."""
    fake = lp.plan.fake
    scale = fake.time_scale if fake is not None else DEFAULT_TIME_SCALE
    seed = fake.seed if fake is not None else None
    sim = SimulatedCell(lp.sim_config_path, seed=seed, time_scale=scale, max_runtime_s=max_runtime_s,
                        sensors=[(s.name, s.driver) for s in lp.plan.sensors], process=process)
    problem = sim.robot_mismatch(lp.model.n_joints, lp.model.controller, f"the plan's robot {lp.model.name}")
    if problem:
        raise ValueError(problem + " (fake.sim_config)")
    return sim


def describe_for(sim: SimulatedCell, lp) -> CellDescription:
    """What a run of ``lp`` gets from the started ``sim``: its devices for the plan's devices."""
    return sim.describe(lp.plan.commander.driver, [(s.name, s.driver, s.url) for s in lp.plan.sensors])


#: Wall seconds the fake controller of a daemon's simulated cell keeps sending (a month).
DAEMON_CELL_RUNTIME_S = 30 * 24 * 3600.0


def daemon_cell(fake_cfg) -> SimulatedCell:
    """The (not yet started) simulated cell of a daemon configuration's ``fake`` section
    (``acquire.daemon.config.FakeCell``): it lives as long as the daemon, and every run the
    daemon starts is described by it (``acquire.daemon.devices.cell_for_plan``)."""
    return SimulatedCell(fake_cfg.sim_config or DEFAULT_CONFIG_PATH, seed=fake_cfg.seed,
                         time_scale=fake_cfg.time_scale, max_runtime_s=DAEMON_CELL_RUNTIME_S)
