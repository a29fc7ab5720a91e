"""``acquire run``: the measurement run — plan → order → move, settle, measure → MCAP log → fit.

Examples::

    acquire run fixtures/plans/example.yaml --fake          # against the simulated cell (a checkout)
    acquire run example --fake                              # the packaged example, results in ./runs
    acquire run plan.yaml --dry-run                         # what would happen; connects to nothing
    acquire run plan.yaml --resume runs/<id>/<id>.mcap      # continue a killed or aborted run
    acquire run plan.yaml --fake -v                         # device INFO logs on the console too
    acquire run plan.yaml --live                            # watch it in Foxglove: ws://127.0.0.1:8765

On a terminal the run shows a live bar (done/total, measured/skipped/failed, ETA, the
configuration being measured) and only warnings; ``-v`` adds INFO, ``-vv`` DEBUG. Every record
of INFO and up goes to ``<run-id>.log`` beside the run's MCAP log, and off a terminal (journald,
CI) INFO goes to stderr as one plain line each. The run publishes on the Zenoh bus (``--listen``,
default tcp/127.0.0.1:7447): ``acquire watch`` in another terminal finds it by itself.

Exit codes: 0 a result was written (or ``--no-fit`` and the run finished); 2 a bad plan, a
plan with fewer configurations than the fit needs (``--dry-run`` warns) or an output folder
that cannot be written, before anything connects or moves; 130 Ctrl-C
(SIGINT) or SIGTERM: the robot stops safely (the commander decelerates) and the log is closed
complete and resumable; 1 a failed run — including one that visited every configuration but
produced no result (too few measured for the fit, or the fit failed). ``--fake`` starts the
simulated cell of the plan's ``fake`` section (``acquire.commands.fake``) and runs against its
description, as against any cell; the summary then puts the fitted offsets next to the
simulated cell's true ones (asked of the cell after the run).
"""

from __future__ import annotations

import logging
import signal
import threading
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from calib.io.resources import foxglove_layout_hint
from acquire.live.console import display_path

log = logging.getLogger(__name__)

#: Default bus endpoint of a run (acquire.live.bus.DEFAULT_ENDPOINT; not imported: zenoh loads on use).
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def _describer(configs):
    """``config_id -> "pose p03  branch …  q [..]°"`` for the progress display's current line."""
    by_id = {c.config_id: c for c in configs}

    def describe(config_id: str) -> str:
        c = by_id.get(config_id)
        if c is None:
            return ""
        q = " ".join(f"{v:.1f}" for v in np.degrees(c.q_rad))
        return f"pose {c.pose}  branch {c.branch}  target [{q}]°"

    return describe


def plan_argument(plan: Path) -> tuple[Path, bool]:
    """The plan file ``acquire run PLAN`` means, and whether it is a packaged example.

    A path to a file is taken as it is; otherwise a bare name (``example``, ``paper.yaml``) is
    looked up among the plans shipped in the package (``acquire examples``). A packaged plan's
    results go to ``./runs`` (the current folder), never into the installed package. Exits 2
    naming the packaged examples when neither exists.
    """
    from calib.io.resources import find, is_packaged, packaged

    if plan.is_file():
        return plan, is_packaged(plan)
    found = find("plans", str(plan)) if not plan.exists() else None
    if found is not None:
        return found, True
    names = ", ".join(p.stem for p in packaged("plans"))
    typer.echo(f"error: {plan}: no such plan file (given {str(plan)!r}; allowed: a plan YAML file, or the name of a "
               f"packaged example: {names} — see `acquire examples`)", err=True)
    raise typer.Exit(2)


def _load(plan: Path, fake: bool = False):
    """The plan and its configurations, resolved once for the whole command (exit 2 on a bad
    plan; with ``fake`` its ``fake`` section is checked too)."""
    from acquire.plan.schema import load_plan, resolve_configurations

    try:
        lp = load_plan(plan)
        if fake:
            from acquire.commands.fake import check_fake_section

            check_fake_section(lp)
        configs = resolve_configurations(lp)
    except (ValueError, OSError) as exc:  # ConfigError is a ValueError
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    if not configs:
        typer.echo(f"error: {plan}: the plan resolves to no configurations", err=True)
        raise typer.Exit(2)
    return lp, configs


def too_few_for_the_fit(lp, configs) -> str | None:
    """Why the plan's configurations cannot give a fitted result even if every one is measured
    (``calib.fit.offsets.min_configurations``), as a ``file:line:col: field: …`` line; None if they can."""
    from calib.fit.offsets import min_configurations

    fit = lp.plan.fit
    if getattr(lp.plan, "socket", None) is not None:
        # every socket gets ≥ 4 configurations (the plan's schema); calib.fit.socket needs no more
        return None
    n_fit = len(fit.joints) if fit.joints else lp.model.n_joints
    need = min_configurations(n_fit, [len(s.markers) for s in lp.plan.sensors], fix_registration=fit.fix_registration)
    if len(configs) >= need:
        return None
    loc = ("selection", "m") if lp.plan.selection is not None else ("poses",)
    return str(lp.error(loc, f"{len(configs)} configuration(s) cannot give a result: the fit of {n_fit} offset(s) "
                             f"with {len(lp.plan.sensors)} sensor registration(s) needs at least {need} (given "
                             f"{len(configs)}; allowed ≥ {need}: more poses or a larger selection, or --no-fit to "
                             "only measure)"))


def dry_run_text(lp, configs) -> str:
    """What ``--dry-run`` prints: configurations in order and the estimated cell time."""
    from acquire.run import SENSOR_RATE_HZ, plan_settings
    from acquire.run.sequencer import estimate_measure_s, estimate_settle_s, move_times, order_configurations
    from drivers.protocols import JointLimits

    plan = lp.plan
    s = plan_settings(plan)
    limits = JointLimits.from_model(lp.model)
    fake = getattr(plan, "fake", None)
    start = _initial_q(lp, fake)
    order = order_configurations(configs, start, limits, s.speed)
    moves = move_times(order, start, limits, s.speed)
    settle = estimate_settle_s(s.settle_window_s)
    measure = estimate_measure_s(s.samples, [SENSOR_RATE_HZ.get(x.driver, 100.0) for x in plan.sensors])
    names = limits.names or tuple(f"J{i + 1}" for i in range(limits.n_axes))
    lines = [
        f"plan: {lp.path}  cell {plan.cell}  robot {lp.model.name}",
        f"commander: {plan.commander.driver} {plan.commander.url}",
    ]
    lines += [f"sensor: {x.name} ({x.driver}) {x.url} markers {sorted(x.markers)}" for x in plan.sensors]
    lines.append(f"start (deg): {np.round(np.degrees(start), 3).tolist()}")
    lines.append(f"{len(order)} configurations in run order (speed {s.speed:g}):")
    lines.append(f"{'#':>4} {'config':<14} {'pose':<8} {'branch':<24} {'move s':>7}  " + " ".join(f"{n:>8}" for n in names))
    for i, (c, t) in enumerate(zip(order, moves)):
        q = " ".join(f"{v:8.2f}" for v in np.degrees(c.q_rad))
        lines.append(f"{i + 1:>4} {c.config_id:<14} {c.pose:<8} {c.branch:<24} {t:7.2f}  {q}")
    total = float(moves.sum() + len(order) * (settle + measure))
    lines.append(
        f"estimated cell time: {total:.0f} s ({total / 60:.1f} min) = motion {moves.sum():.0f} s + "
        f"settle {len(order) * settle:.0f} s ({settle:.2f} s each) + measure {len(order) * measure:.0f} s "
        f"({measure:.2f} s each)"
    )
    if plan.adaptive is not None:
        lines += adaptive_dry_run_lines(lp, configs, limits, s.speed, settle + measure, start)
    return "\n".join(lines)


def adaptive_dry_run_lines(lp, configs, limits, speed: float, per_config_s: float, start) -> list[str]:
    """An adaptive plan's estimated cell-time range: the choices it would make if the noise is
    the plan's ``noise_mm`` (the earliest it can stop), and at most ``max_configurations`` or the
    whole plan. Raises ConfigError when the stop rule cannot be followed (min_configurations)."""
    from acquire.run.adaptive import AdaptiveOrder, simulate
    from acquire.run.controller import candidate_pool
    from calib.plan.adaptive import WORDING

    order = AdaptiveOrder(lp, configs, limits, speed, per_config_s, candidate_pool(lp))
    chosen, st = simulate(order, start)
    rule = order.design.rule
    low = order.visited_seconds(chosen, start)
    full = order.full_plan_seconds(start)
    most = rule.max_configurations or len(configs)
    high = order.visited_seconds(simulate(order, start, to_the_end=True)[0], start)
    d = order.design
    full_hw = max(d.half_widths_deg(d.covariance(range(len(configs)))).values(), default=0.0)
    stated = "; ".join(f"{WORDING[k][0]} ≤ {v:g}{WORDING[k][1]}" for k, v in rule.criteria.items())
    lines = ["", f"adaptive: the order is chosen as the run goes; stop rule: {stated}"
             f"; at least {rule.min_configurations}, at most {most} configurations",
             f"  determinable offsets: {', '.join(d.model.offset_names)}",
             f"  noise: the plan's {order.noise_mm:g} mm per reading, {order.samples} readings averaged: "
             f"σ {order.plan_sigma_mm:.4f} mm per configuration (the run measures it: the readings' spread, "
             "then the fit's σ and the model's misfit)",
             f"  if the noise is the plan's: stops after {len(chosen)} configurations, {low:.0f} s ({st.reason})",
             f"  predicted at that stop: largest half-width {st.max_half_width_deg:.4f}°, model error "
             f"{st.region_mm:.4f} mm (plan's region), {_mm(st.joint_space_mm)} (working joint space), held-out "
             f"{st.held_out_mm:.4f} mm",
             f"  the full plan would reach: largest half-width {full_hw:.4f}°, model error {st.full_region_mm:.4f} mm "
             f"(plan's region), {_mm(st.full_joint_space_mm)} (working joint space), held-out {st.full_held_out_mm:.4f} mm",
             f"estimated cell time range: {low:.0f}–{high:.0f} s ({low / 60:.1f}–{high / 60:.1f} min; the full plan "
             f"{full:.0f} s); more noise or misfit than the plan says means more configurations",
             "  first choices: " + " ".join(c.config_id for c in chosen[:12]) + (" …" if len(chosen) > 12 else "")]
    if len(order.configs) > len(configs):
        n_gen = sum(1 for c in chosen if c.config_id not in {p.config_id for p in configs})
        lines.insert(3, f"  candidates: the plan's {len(configs)} and {len(order.configs) - len(configs)} generated "
                        f"(adaptive.candidates; the full plan is the plan's); {n_gen} generated chosen")
    return lines


def _mm(value: float | None) -> str:
    return "–" if value is None else f"{value:.4f} mm"


def _initial_q(lp, fake) -> np.ndarray:
    """Where the robot starts for the estimate: the simulated cell's initial pose when the plan
    has a ``fake`` section with a config, else the middle of the joint ranges."""
    try:
        if fake is not None and getattr(fake, "sim_config", None) is not None:
            from drivers.sim.config import load_sim_config

            path = Path(fake.sim_config)
            if not path.is_absolute():
                path = Path(lp.path).parent / path
            q = load_sim_config(path).initial_joint_positions_deg
            if q is not None:
                return np.radians(np.asarray(q, dtype=float))
    except (ValueError, OSError) as exc:
        log.debug("no initial pose from the sim config: %s", exc)
    return 0.5 * (lp.model.lower_limits_rad + lp.model.upper_limits_rad)


def run(
    plan: Path = typer.Argument(..., help="The plan YAML file, or a packaged example's name (acquire examples)."),
    fake: bool = typer.Option(False, "--fake", help="Run against the simulated cell's fakes on loopback."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Print configurations, order and cell time; connect to nothing."),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Continue the run recorded in this MCAP log."),
    skip_failed: bool = typer.Option(
        False, "--skip-failed", help="With --resume: do not measure the configurations that failed again."
    ),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for the run (default: the plan's output.folder)."),
    no_fit: bool = typer.Option(False, "--no-fit", help="Do not fit at the end (use `acquire fit RUN.mcap` later)."),
    no_bus: bool = typer.Option(False, "--no-bus", help="Do not open the Zenoh bus (nothing published)."),
    listen: str = typer.Option(DEFAULT_LISTEN, "--listen",
                               help="Zenoh endpoint the run publishes on (loopback); `acquire watch --connect` it."),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True,
                                help="Console shows INFO (-v) or DEBUG (-vv) logs too; the run's .log file has them anyway."),
    live: bool = typer.Option(False, "--live", help="Serve the run live to Foxglove (WebSocket; layout: "
                              f"{foxglove_layout_hint()}, also listed by `acquire examples`)."),
    live_host: str = typer.Option("127.0.0.1", "--live-host", help="Interface of the live view (0.0.0.0: every network)."),
    live_port: int = typer.Option(8765, "--live-port", min=0, max=65535, help="TCP port of the live view."),
) -> None:
    """Run the measurement plan: move, settle, measure every configuration; log; fit.

    PLAN is a plan file or the name of a packaged example (`acquire examples`); a packaged
    example writes its run to ./runs unless --out says otherwise.
    """
    from acquire.live.console import configure_console

    console = configure_console(verbose)
    given = plan
    plan, is_example = plan_argument(plan)
    if out is None and is_example:
        out = Path.cwd() / "runs"
    lp, configs = _load(plan, fake)
    too_few = None if no_fit else too_few_for_the_fit(lp, configs)
    if dry_run:
        typer.echo(dry_run_text(lp, configs))
        if too_few:
            typer.echo(f"warning: {too_few}")
        return
    if too_few:  # the robot would move for nothing: refuse before anything connects
        typer.echo(f"error: {too_few}", err=True)
        raise typer.Exit(2)
    if resume is not None and not resume.is_file():
        typer.echo(f"error: --resume {resume}: no such file", err=True)
        raise typer.Exit(2)
    from acquire.live.console import RunLogFile
    from acquire.live.progress import make_progress
    from acquire.run import RunController, RunError

    controller = RunController(lp, configs=configs, resume=resume, bus=None, out_dir=out, fit=not no_fit,
                               skip_failed=skip_failed)
    try:
        controller.check_output()  # first: before the bus, the fakes or any device
    except RunError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    logfile = RunLogFile(logging.DEBUG if verbose >= 2 else logging.INFO)
    bus = None
    if not no_bus:
        from acquire.live.bus import Bus, BusConfigError

        try:
            if listen == DEFAULT_LISTEN:
                bus = Bus(lp.plan.cell)  # falls back to a free port (and says so) when 7447 is taken
            else:
                bus = Bus(lp.plan.cell, config={"listen": [listen]})
        except BusConfigError as exc:
            typer.echo(f"error: --listen {listen}: {exc}", err=True)
            raise typer.Exit(2) from exc
        except Exception as exc:  # noqa: BLE001 - a run without a bus still measures
            log.warning("no Zenoh bus (%s); the run is not published", exc)
            bus = None
    server = None
    if live:
        from acquire.live.foxglove_server import LiveServer, LiveServerError
        from acquire.record.recorder import advertise_run_channels

        try:
            server = LiveServer(live_host, live_port, name=f"remaster {lp.plan.cell}")
            advertise_run_channels(server, [spec.name for spec in lp.plan.sensors])
        except (LiveServerError, ValueError) as exc:
            if bus is not None:
                bus.close()
            typer.echo(f"error: --live: {exc}", err=True)
            raise typer.Exit(2) from exc
        typer.echo(f"live view: open {server.url} in Foxglove (Open connection → Foxglove WebSocket)", err=True)
    if bus is not None:
        log.info("publishing on %s as cell %s (acquire watch --connect %s)", ", ".join(bus.locators),
                 lp.plan.cell, bus.locators[0] if bus.locators else listen)
    progress = make_progress(describe=_describer(configs))

    def on_progress(st: dict) -> None:
        if st.get("log") and logfile.path is None:
            try:
                logfile.open(st["log"])
            except OSError as exc:
                log.warning("no text log beside %s: %s", st["log"], exc)
        progress.update(st)

    controller.bus = bus
    controller.on_progress = on_progress
    controller.live = server
    signals = StopSafelyOnSignals(controller).install()
    sim = None
    ended: list = []  # the simulated cell's (truth, sag), read as the run measures no more

    def end_simulation() -> None:
        """The cell's truth beside the fit (a property of the simulated cell), read once the run
        measures no more; then the cell stops, as a real cell's machines would not share this PC's
        cores with the end-of-run fit (its fakes ran real-time: 1.3 CPU-s of a 3.7 s fit)."""
        if sim is None or ended:
            return
        try:
            ended.append((sim.truth_offsets_deg(), sim.mean_sag_deg(np.stack([c.q_rad for c in configs]))))
        except RuntimeError as exc:  # (CellProcessError: its process is gone)
            log.warning("the simulated cell's truth is not in the summary: %s", exc)
            ended.append((None, None))
        sim.close()

    try:
        if fake:  # "start the simulated cell, then run": the run gets its description, as of any cell
            sim = _start_simulated_cell(lp, controller)
        controller.start()
        summary = wait_for_end(controller, on_measured=end_simulation)
        end_simulation()
        truth, sag = ended[0] if ended else (None, None)
    finally:
        signals.restore()
        progress.close()
        if sim is not None:
            sim.close()
        if bus is not None:
            bus.close()
        logfile.close(console.level)
        if server is not None:
            server.close()
    from acquire.commands.run_summary import format_run_summary

    typer.echo(format_run_summary(summary, lp, truth, sag))
    if logfile.path is not None:
        typer.echo(f"text log: {display_path(logfile.path)}")
    if summary.state != "finished":
        if summary.log_path is not None and (summary.done < summary.total or summary.failed):
            typer.echo(f"resume with: acquire run {given} --resume {display_path(summary.log_path)}"
                       + (" --fake" if fake else ""))
        elif summary.log_path is not None and summary.measured:
            typer.echo(f"every configuration was visited; measure more (a larger plan) or fit the log yourself: "
                       f"acquire fit {display_path(summary.log_path)} --robot {lp.model_path}")
        raise typer.Exit(summary.exit_code)


class StopSafelyOnSignals:
    """While installed, SIGINT and SIGTERM stop ``controller``'s run safely (the robot decelerates,
    the log is closed): the first one aborts it, a second one only says it is still stopping."""

    def __init__(self, controller) -> None:
        self.controller = controller
        self.interrupted = threading.Event()
        self._old: dict = {}

    def _on_signal(self, signum, frame) -> None:  # noqa: ARG002
        name = signal.Signals(signum).name
        if self.interrupted.is_set():
            log.warning("%s again: still stopping safely", name)
            return
        self.interrupted.set()
        log.warning("%s: stopping safely (the robot decelerates, the log is closed)", name)
        threading.Thread(target=self.controller.abort, args=(f"interrupted ({name})",), daemon=True).start()

    def install(self) -> "StopSafelyOnSignals":
        self._old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def restore(self) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old = {}


def wait_for_end(controller, on_measured=None):
    """The run's ``RunSummary`` once it has ended (waiting in short steps: a signal is handled at
    once). ``on_measured()``: called here once the run measures no more (``measurements_over``),
    while it fits."""
    while True:
        if on_measured is not None and controller.measurements_over.is_set():
            on_measured()
            on_measured = None
        try:
            return controller.wait(0.2)
        except TimeoutError:
            continue


def _start_simulated_cell(lp, controller):
    """Start the plan's simulated cell and hand its description to ``controller``; exit 2 when
    it cannot start (its robot is not the plan's, a port is taken)."""
    from acquire.commands.fake import describe_for, simulated_cell

    try:
        sim = simulated_cell(lp).start()
    except (ValueError, OSError) as exc:
        typer.echo(f"error: --fake: cannot start the simulated cell: {exc}", err=True)
        raise typer.Exit(2) from exc
    try:
        controller.use_cell(describe_for(sim, lp))
    except ValueError as exc:
        sim.close()
        typer.echo(f"error: --fake: {exc}", err=True)
        raise typer.Exit(2) from exc
    return sim


def register(app: typer.Typer) -> None:
    """Add the ``run`` sub-command to ``app``."""
    app.command("run")(run)
