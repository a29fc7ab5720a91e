"""``RunController``: one measurement run, from a loaded plan to a closed log and a fitted result.

Used by ``acquire run`` and by the daemon. ``start()`` runs the whole job in a background
thread; ``pause`` / ``resume`` / ``abort`` / ``confirm`` / ``status`` / ``wait`` are thread-safe.

The job (each step in a module of its own):

1. the plan's configurations (resolved once, by the caller or here); with ``resume`` the
   earlier log's (``read_run``) are dropped — the interrupted one is measured again, nothing is
   measured twice (``prepare.remaining``);
2. open the devices through the cell's description (``devices.RunDevices``): the commander at
   the cell's commander URL, each plan sensor at its URL, all on the cell's clock. The run
   does not know whether the cell is real (``devices.plan_cell``) or simulated
   (``drivers.sim.running``, started by ``acquire run --fake``);
3. order the remaining configurations for minimum motion time from where the robot is;
4. per configuration (``procedure.ConfigurationRunner``): move, settle, measure, record; a lost
   target suspends the run there and the configuration is measured again after a recovery;
   every step is an event in the log and on the bus (``publish.RunPublisher``);
5. close the log; when finished, fit it and write ``result.json`` and ``report.html`` beside it
   (``ending.finish``, ``fitting.fit_run_log``).

Before any of this, ``start()`` checks that the output folder takes a new file
(``check_output``): an unwritable folder is refused before a device is opened. The state
machine and its counters: ``state.RunState``.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from acquire.live.console import FORESEEN
from acquire.record.logstorage import StorageError
from acquire.run import prepare
from acquire.run.devices import RunDevices, plan_cell
from acquire.run.ending import finish
from acquire.run.fitting import preload_fit
from acquire.run.procedure import ConfigurationRunner, make_predictor
from acquire.run.publish import RunPublisher
from acquire.run.state import RunState
from acquire.run.summary import RunError, RunSummary
from acquire.run.tap import JointStateTap
from acquire.run.sequencer import estimate_measure_s, estimate_settle_s, move_times, order_configurations
from drivers.cell import CellDescription
from drivers.errors import DriverError

log = logging.getLogger("acquire.run")  # the run's own lines under the package name (journald, tests)

#: Configurations failing in a row after which the run stops as failed (the cell is not usable).
MAX_CONSECUTIVE_FAILURES = 3
#: Wall seconds the run waits after connecting for the controller's first joint state.
FIRST_STATE_TIMEOUT_S = 15.0


def _tty_ask(question: str) -> str:
    """Ask the operator (``ask`` policy) on the controlling terminal."""
    sys.stderr.write(question + " [retry/skip/abort] ")
    sys.stderr.flush()
    answer = sys.stdin.readline().strip().lower()
    return answer if answer in ("retry", "skip", "abort") else "skip"


class RunController:
    """One measurement run (see the module docstring). Thread-safe.

    lp: the loaded plan (``acquire.plan.schema.load_plan``). cell: the cell's description (default: the
    plan's own URLs, ``plan_cell``). configs: the plan's resolved configurations when the caller
    has them (else resolved here, once). resume: a run log to continue. out_dir: the runs
    folder (default the plan's ``output.folder``). fit: fit at the end. skip_failed: on resume,
    do not measure failed configurations again. live: an ``acquire.live.foxglove_server.LiveServer``.
    """

    def __init__(self, lp, *, cell: CellDescription | None = None, configs=None, resume: Path | None = None,
                 bus=None, out_dir: Path | None = None, on_progress: Optional[Callable[[dict], None]] = None,
                 ask: Optional[Callable[[str], str]] = None, fit: bool = True, skip_failed: bool = False,
                 live=None) -> None:
        self.lp, self.plan = lp, lp.plan
        self.cell = cell if cell is not None else plan_cell(lp)
        self.configs = list(configs) if configs is not None else None
        self.skip_failed = skip_failed
        self.live = live  # every logged message is also served to Foxglove
        self.resume_path = Path(resume) if resume is not None else None
        self.fit_enabled = fit
        self.ask = ask if ask is not None else (_tty_ask if sys.stdin.isatty() else None)
        self.settings = prepare.plan_settings(self.plan)
        self.cell_id = self.plan.cell
        folder = out_dir if out_dir is not None else Path(self.plan.output.folder)
        if not Path(folder).is_absolute() and out_dir is None:
            folder = Path(lp.path).parent / folder
        self.out_dir = Path(os.path.abspath(folder))  # no "plans/../../runs" in what is printed or logged
        self.pub = RunPublisher(self.cell_id, bus, on_progress)
        self.state = RunState(self.pub, self.cell.time_scale)
        self.devices: RunDevices | None = None
        self._tap: JointStateTap | None = None
        self._resumed = None
        self._thread: Optional[threading.Thread] = None
        self._done_evt = threading.Event()
        self._summary: Optional[RunSummary] = None
        self.adaptive_summary: Optional[dict] = None  # an adaptive run's stop reason, history, time saved
        #: The end-of-run fit's imports, made while the robot moves (``fitting.preload_fit``); None without a fit.
        self.fit_preload: Optional[threading.Thread] = None
        #: Set once the run measures no more (its devices and log closed), before its fit: whoever
        #: started the cell's simulation may stop it then (``acquire run --fake``).
        self.measurements_over = threading.Event()

    # ------------------------------------------------------------------ what callers read and set
    bus = property(lambda self: self.pub.bus, lambda self, v: setattr(self.pub, "bus", v))
    on_progress = property(lambda self: self.pub.on_progress, lambda self, v: setattr(self.pub, "on_progress", v))
    run_id = property(lambda self: self.state.run_id)
    log_path = property(lambda self: self.state.log_path)

    @property
    def commander(self):
        """The run's open commander (None before the devices are open and after the end)."""
        return self.devices.commander if self.devices is not None else None

    def use_cell(self, cell: CellDescription) -> None:
        """Run in ``cell`` (before ``start``): e.g. a cell started after ``check_output``."""
        with self.state.lock:
            if self.state.state != "idle":
                raise RuntimeError(f"run already {self.state.state}; the cell is chosen before it starts")
            self.cell = cell
            self.state.time_scale = float(cell.time_scale)

    # ------------------------------------------------------------------ control surface
    def check_output(self) -> None:
        """Refuse a run whose log cannot be written (``prepare.check_output``), before any device."""
        prepare.check_output(self.out_dir, self.resume_path)

    def start(self) -> str:
        """Check the output folder, then start the run in a background thread; returns its run
        id. Raises RunError before anything connects when the run's log cannot be written."""
        st = self.state
        with st.lock:
            if st.state != "idle":
                raise RuntimeError(f"run already {st.state}")
            self.check_output()
            st.state = "starting"
            if self.resume_path is not None:
                from acquire.record.recorder import read_run

                self._resumed = read_run(self.resume_path)
                st.run_id = self._resumed.run_id
            else:
                st.run_id = prepare.make_run_id(self.cell_id)
            self.pub.run_id = st.run_id
            st.wall0 = time.monotonic()
        self._thread = threading.Thread(target=self._main, name=f"run-{st.run_id}", daemon=True)
        self._thread.start()
        return st.run_id

    def pause(self) -> None:
        """Finish the current configuration, then hold."""
        if self.state.request_pause():
            self.pub.event("pause_requested")

    def resume(self) -> None:
        self.state.unpaused.set()

    def abort(self, reason: str = "aborted") -> None:
        """Stop safely: the robot decelerates (``commander.stop``), the log is closed."""
        if not self.state.request_abort(reason):
            return
        cmd = self.commander
        if cmd is not None:
            try:
                cmd.stop()
            except DriverError as exc:
                log.warning("stop on abort: %s", exc)

    def confirm(self) -> list[str]:
        """The operator says the ball sits in the socket: every joint sensor waiting for it
        records now. Returns what was being waited for (empty: nothing was)."""
        waiting = []
        for sp in list(self.devices.sensors if self.devices is not None else []):
            if callable(getattr(sp.sensor, "confirm", None)):
                what = getattr(sp.sensor, "waiting_for", None)
                if what:
                    waiting.append(f"{sp.sensor.name}: {what}")
                sp.sensor.confirm()
        self.pub.event("confirmed", waiting=waiting)
        return waiting

    def wait(self, timeout: float | None = None) -> RunSummary:
        if not self._done_evt.wait(timeout):
            raise TimeoutError(f"run {self.run_id} still {self.state.state} after {timeout} s")
        assert self._summary is not None
        return self._summary

    def status(self) -> dict:
        return self.state.status()

    # ------------------------------------------------------------------ the job
    def _main(self) -> None:
        summary = None
        try:
            summary = self._run()
        except StorageError as exc:  # disk full / I/O error: the log is sealed; stop here, the robot holds
            log.error("run %s stopped: %s", self.run_id, exc)
            runlog, self.pub.runlog = self.pub.runlog, None  # nothing more can be written to it
            if runlog is not None:
                runlog.close()
            self.state.fail(str(exc))
        except (RunError, DriverError) as exc:  # foreseen: one line on a console, the traceback in the text log
            log.error("run %s failed: %s", self.run_id, exc, exc_info=exc, extra=FORESEEN)
            self.state.fail(f"{type(exc).__name__}: {exc}")
        except BaseException as exc:  # noqa: BLE001 - the thread must always report how it ended
            log.exception("run %s failed", self.run_id)
            self.state.fail(f"{type(exc).__name__}: {exc}")
        finally:
            self.teardown()
            self.measurements_over.set()
            self.pub.release_bus()
            if summary is None:
                summary = self.state.summary()
            self._summary = summary
            try:  # the last progress before wait() returns: the caller may close the bus right after
                self.state.progress()
            finally:
                self._done_evt.set()

    def teardown(self) -> None:
        """Close the devices, the joint-state tap and the log (idempotent)."""
        if self.devices is not None:
            self.devices.close()
        if self._tap is not None:
            self._tap.stop()
            self._tap = None
        self.pub.close_log()

    def _run(self) -> RunSummary:
        from acquire.plan.schema import resolve_configurations

        lp, s, st, cell = self.lp, self.settings, self.state, self.cell
        configs = self.configs if self.configs is not None else resolve_configurations(lp)
        pool = candidate_pool(lp)  # an adaptive run's generated candidates beyond the plan ([] without)
        todo, ended, (measured, skipped, failed) = prepare.remaining(
            configs + pool, self._resumed, plan_text=lp.text, resume_path=self.resume_path,
            skip_failed=self.skip_failed)
        plan_ids = {c.config_id for c in configs}
        todo = [c for c in todo if c.config_id in plan_ids]  # the fixed order: the plan's own
        with st.lock:
            st.total, st.done = len(configs), len(ended)
            st.measured, st.skipped, st.failed = measured, skipped, failed
        self.devices = RunDevices(lp, cell)
        cmd, sensors = self.devices.open()
        if st.aborting.is_set():
            return finish(self, 0.0)
        start_q = np.asarray(cmd.first_state(FIRST_STATE_TIMEOUT_S).position_rad, dtype=float)
        rates = [prepare.SENSOR_RATE_HZ.get(sp.driver, 100.0) for sp in self.plan.sensors]
        per_config = estimate_settle_s(s.settle_window_s) + estimate_measure_s(s.samples, rates)
        adaptive = None
        if self.plan.adaptive is not None:  # the order is chosen as the run goes (acquire.run.adaptive)
            from acquire.run.adaptive import AdaptiveRun

            adaptive = AdaptiveRun(lp, configs, cmd, s.speed, per_config, self._resumed, ended, start_q, pool,
                                   lookahead="process")  # the next choice computed while the robot moves
            order = adaptive.predicted
        else:
            order = order_configurations(todo, start_q, cmd.limits, s.speed)
        with st.lock:
            st.remaining_est = list(move_times(order, start_q, cmd.limits, s.speed) + per_config)
        self.pub.runlog, path = prepare.open_run_log(
            lp, run_id=st.run_id, out_dir=self.out_dir, resumed_path=self.resume_path if self._resumed else None,
            n_configs=len(configs), cell_metadata=cell.metadata, live=self.live)
        with st.lock:
            st.log_path = path
        runner = self._runner(cmd, sensors)
        self.pub.event("run_started", resumed=self._resumed is not None, todo=len(todo), total=len(configs),
                       order=[c.config_id for c in order] if adaptive is None else [])
        if adaptive is not None:
            self.pub.event("adaptive_started", **adaptive.started_fields())
        st.set("running")
        if self.fit_enabled:
            self.fit_preload = preload_fit(lp)
        t_cell0 = cell.clock()
        st.loop_wall0 = time.monotonic()
        try:
            self._loop(order if adaptive is None else adaptive.choices(self.pub.event), runner, adaptive)
        finally:
            if adaptive is not None:
                adaptive.close()  # its look-ahead worker
        if adaptive is not None:
            self.adaptive_summary = adaptive.summary()
            self.pub.event("adaptive_stop", **self.adaptive_summary)
        return finish(self, cell.clock() - t_cell0)

    def _loop(self, configs, runner: ConfigurationRunner, adaptive) -> None:
        """Measure ``configs`` (a list, or an adaptive run's choices) until done, paused into an
        abort, or too many failures in a row (RunError)."""
        st, streak = self.state, 0
        for cfg in configs:
            if not st.checkpoint():
                break
            st.begin(cfg.config_id)
            outcome = runner.measure(cfg)
            if adaptive is not None:
                adaptive.outcome(cfg, outcome, runner.last_record)
            if outcome == "abort":  # the interrupted configuration is not done: a resume measures it
                st.aborting.set()
                break
            streak = streak + 1 if outcome == "failed" else 0
            st.count(cfg.config_id, outcome)
            if streak >= MAX_CONSECUTIVE_FAILURES:
                raise RunError(f"{streak} configurations failed in a row (last: {st.skip_reasons.get(cfg.config_id)}); "
                               "the cell is not usable — fix it and resume the run")

    def _runner(self, cmd, sensors) -> ConfigurationRunner:
        """The per-configuration procedure, its registration estimate and the robot's view."""
        from acquire.record.foxglove_view import RobotView
        from calib.robot.kinematics import Chain

        chain = Chain(self.lp.model)
        view = RobotView(chain)
        runner = ConfigurationRunner(
            self.lp, self.state, self.pub, cmd, sensors, self.settings, clock=self.cell.clock,
            sleep=self.cell.sleep, predictor=make_predictor(self.lp, chain, self._resumed), view=view,
            ask=self.ask, abort=self.abort)
        runner.show_registration()
        self._tap = JointStateTap(cmd, self.pub.runlog, self.bus, self.cell_id, self.lp.model.axis_names,
                                  period_s=0.04, view=view).start()
        return runner


def candidate_pool(lp) -> list:
    """The generated candidates an adaptive plan's design may choose beyond the plan's own
    (``adaptive.candidates``; ``acquire.plan.schema.resolve_candidate_pool``), [] for any other plan."""
    if lp.plan.adaptive is None or lp.plan.adaptive.candidates is None:
        return []
    from acquire.plan.schema import resolve_candidate_pool

    return resolve_candidate_pool(lp)
