"""``RunController``: one measurement run, from a loaded plan to a closed log and a fitted result.

Used by ``acquire run`` and by the daemon. ``start()`` runs the whole job in a background
thread; ``pause`` / ``resume`` / ``abort`` / ``status`` / ``wait`` are thread-safe.

The job:

1. resolve the plan's configurations; with ``resume`` read the earlier log (``read_run``) and
   keep only configurations it has no sample (nor skip / failure) for — the interrupted one is
   measured again, nothing is measured twice;
2. open the devices: the plan's drivers at the plan's URLs, or under ``fake`` the simulated
   cell's fakes (``drivers.sim.launch.SimLaunch``) on loopback with the plan's URLs pointed at
   them — the same code path afterwards. Under ``fake`` every device and the sequencer run on
   the cell's ``SimClock`` (``fake.time_scale`` simulated seconds per wall second): the fake
   controller sends its cycles faster than real time and the commanders advance their
   trajectories one controller cycle per packet, so no safety check is loosened;
3. order the remaining configurations for minimum motion time from where the robot is;
4. per configuration: move, settle, measure (``acquire.sequencer.ConfigProcedure``); a lost
   target suspends the run there (``acquire.suspenders.LostTargetSuspender``) and the
   configuration is measured again after a recovery; every step is an event in the log and on
   the bus, every measured configuration one sample record;
5. close the log; when finished, fit it and write ``result.json`` and ``report.html`` beside it.
   A run asked for a result that has none (nothing measured, too few configurations for the
   fit, the fit failed) ends ``failed`` with the reason, not ``finished``.

Before any of this, ``start()`` checks that the output folder takes a new file
(``check_output``): an unwritable folder is refused before a device is opened.

States: idle → starting → running ⇄ paused / suspended → stopping → finished | aborted | failed.
"""

from __future__ import annotations

import inspect
import logging
import math
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from acquire.sequencer import (
    ConfigProcedure,
    SensorSpec,
    SequencingSettings,
    estimate_measure_s,
    estimate_settle_s,
    move_times,
    order_configurations,
)
from acquire.logstorage import StorageError
from acquire.suspenders import LostTargetSuspender, ReflectorPredictor
from drivers.errors import DeviceFaultError, DeviceTimeoutError, DriverError, LimitError, TargetLostError
from drivers.protocols import JointLimits
from acquire.plan import JOINT_SENSOR_DRIVERS
from drivers.registry import load_driver

log = logging.getLogger(__name__)

STATES = ("idle", "starting", "running", "paused", "suspended", "stopping", "finished", "aborted", "failed")
TERMINAL = ("finished", "aborted", "failed")

#: Default simulated-time scale under ``--fake`` when the plan's ``fake`` section gives none.
DEFAULT_TIME_SCALE = 4.0
#: Shortest wall time of one fake controller cycle under ``--fake`` (see ``FakeCell``).
MIN_WALL_PERIOD_S = 0.002
#: Configurations failing in a row after which the run stops as failed (the cell is not usable).
MAX_CONSECUTIVE_FAILURES = 3
#: Wall seconds the run waits after connecting for the controller's first joint state.
FIRST_STATE_TIMEOUT_S = 15.0
#: Expected sample rate (Hz) per sensor driver, for the cell-time estimate only.
SENSOR_RATE_HZ = {"natnet": 120.0, "tracker": 1000.0, "emscon": 1000.0}


class RunError(RuntimeError):
    """The run cannot start (bad resume log, fake cell not matching the plan, …)."""


@dataclass
class RunSummary:
    """How a run ended. Times in wall seconds; ``cell_seconds`` in the commanders' clock
    (simulated seconds under ``--fake``)."""

    run_id: str
    state: str
    log_path: Optional[Path]
    total: int
    done: int
    measured: int
    skipped: int
    failed: int
    reason: str = ""
    wall_seconds: float = 0.0
    cell_seconds: float = 0.0
    result_path: Optional[Path] = None
    report_path: Optional[Path] = None
    fit: Optional[dict] = None
    truth_offsets_deg: Optional[list] = None
    truth_mean_sag_deg: Optional[list] = None
    skipped_reasons: dict = field(default_factory=dict)

    @property
    def exit_code(self) -> int:
        """0 finished; 1 failed; 130 aborted (as after Ctrl-C)."""
        return {"finished": 0, "aborted": 130}.get(self.state, 1)


# ------------------------------------------------------------------------------ helpers
def plan_settings(plan) -> SequencingSettings:
    s = plan.sequencing
    return SequencingSettings(
        speed=float(s.speed),
        settle_window_s=float(s.settle_window_s),
        settle_tolerance_rad=math.radians(float(s.settle_tolerance_deg)),
        sensor_stable_mm=float(s.sensor_stable_mm),
        samples=int(s.samples),
        move_timeout_s=float(s.move_timeout_s),
        measure_timeout_s=float(s.measure_timeout_s),
        retries=int(s.retries),
    )


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


def make_run_id(cell: str, now: datetime | None = None) -> str:
    now = now or datetime.now(timezone.utc)
    return f"{cell}-{now.strftime('%Y%m%dT%H%M%S')}-{int(now.microsecond / 1000):03d}"


def _tty_ask(question: str) -> str:
    """Ask the operator (``ask`` policy) on the controlling terminal."""
    sys.stderr.write(question + " [retry/skip/abort] ")
    sys.stderr.flush()
    answer = sys.stdin.readline().strip().lower()
    return answer if answer in ("retry", "skip", "abort") else "skip"


# ------------------------------------------------------------------------------ fake cell
class FakeCell:
    """The simulated cell for ``--fake``: ``SimCell`` + ``SimLaunch`` around the plan's devices."""

    def __init__(self, lp) -> None:
        from drivers.sim.cell import SimCell
        from drivers.sim.clock import SimClock

        fake = getattr(lp.plan, "fake", None)
        sim_config = getattr(fake, "sim_config", None) if fake is not None else None
        if sim_config is None:
            from drivers.sim.config import DEFAULT_CONFIG_PATH

            sim_config = DEFAULT_CONFIG_PATH
        sim_config = Path(sim_config)
        if not sim_config.is_absolute():
            sim_config = (Path(lp.path).parent / sim_config).resolve()
        seed = getattr(fake, "seed", None) if fake is not None else None
        scale = getattr(fake, "time_scale", None) if fake is not None else None
        self.time_scale = float(scale or DEFAULT_TIME_SCALE)
        self.clock = SimClock(self.time_scale)
        self.cell = SimCell.from_yaml(sim_config, seed=seed, clock=self.clock)
        self.sim_config = sim_config
        if self.cell.model.n_joints != lp.model.n_joints or self.cell.model.controller != lp.model.controller:
            raise RunError(
                f"the simulated cell {sim_config} has a {self.cell.model.name} ({self.cell.model.n_joints} axes, "
                f"{self.cell.model.controller}); the plan's robot is {lp.model.name} ({lp.model.n_joints} axes, "
                f"{lp.model.controller}); set fake.sim_config to a matching cell"
            )
        self.launch = None

    def fri_send_period_ms(self) -> int:
        """The fake Sunrise's send period (simulated ms): FRI allows 1–100 ms; we keep one cycle
        at least ``MIN_WALL_PERIOD_S`` of wall time so a faster-than-real-time cell does not ask
        Python for sub-millisecond exchanges. The commander steps its trajectory by the period
        the controller reports, so the motion and every per-cycle limit check stay exact."""
        return int(min(100, max(5, math.ceil(MIN_WALL_PERIOD_S * 1000.0 * self.time_scale))))

    def tracker_protocols(self, sensors) -> dict[str, tuple[str, ...]]:
        """Which protocols each tracker of the cell must speak for the plan's ``sensors``: the
        line protocol for ``tracker`` drivers, emScon for ``emscon`` drivers (a plan sensor
        uses the cell's tracker of its name, else the cell's first tracker)."""
        trackers = [s.name for s in self.cell.config.sensors if s.kind == "tracker"]
        out: dict[str, list[str]] = {}
        for spec in sensors:
            proto = {"tracker": "line", "emscon": "emscon"}.get(spec.driver)
            if proto is None or not trackers:
                continue
            target = spec.name if spec.name in trackers else trackers[0]
            if proto not in out.setdefault(target, []):
                out[target].append(proto)
        return {k: tuple(v) for k, v in out.items()}

    def start(self, controller_port: int | None, sensors=()):
        from drivers.sim.launch import SimLaunch

        kw = {}
        if controller_port is not None:
            kw = {"fri_port": controller_port, "rsi_port": controller_port}
        self.launch = SimLaunch(
            self.cell, controller=controller_port is not None, fri_send_period_ms=self.fri_send_period_ms(),
            tracker_protocols=self.tracker_protocols(sensors), **kw
        ).start()
        for line in self.launch.describe():
            log.info("fake: %s", line)
        return self.launch

    def sensor_url(self, spec) -> str:
        """The fake device address for a plan sensor: by name, else the cell's sensor of its kind."""
        from acquire.plan import JOINT_SENSOR_DRIVERS

        if spec.driver in JOINT_SENSOR_DRIVERS:
            # no device: the robot is the instrument, and the cell's operator guides it
            if not self.cell.config.sockets:
                raise RunError(f"sensor {spec.name!r} ({spec.driver}): the simulated cell {self.sim_config} has no "
                               "sockets section; use a cell with sockets (e.g. fixtures/sim/socket.yaml)")
            return spec.url
        addrs = self.launch.addresses
        kind = {"natnet": "natnet", "tracker": "tracker", "emscon": "emscon"}.get(spec.driver)
        if kind is None and spec.name in addrs:
            return addrs[spec.name].url
        for key in (spec.name, f"{spec.name}-emscon"):
            if key in addrs and addrs[key].kind == kind:
                return addrs[key].url
        for a in addrs.values():
            if a.kind == kind:
                return a.url
        raise RunError(f"sensor {spec.name!r} ({spec.driver}): the simulated cell has no such device; "
                       f"it has {sorted(addrs)}")

    def close(self) -> None:
        if self.launch is not None:
            self.launch.close()
            self.launch = None


# ------------------------------------------------------------------------------ the controller
class RunController:
    """One measurement run (see the module docstring). Thread-safe."""

    def __init__(
        self,
        lp,
        *,
        fake: bool = False,
        resume: Path | None = None,
        bus=None,
        out_dir: Path | None = None,
        on_progress: Optional[Callable[[dict], None]] = None,
        ask: Optional[Callable[[str], str]] = None,
        fit: bool = True,
        skip_failed: bool = False,
        live=None,
    ) -> None:
        self.lp = lp
        self.skip_failed = skip_failed
        self.live = live  # acquire.live.LiveServer: every logged message is also served to Foxglove
        self.plan = lp.plan
        self.fake = fake
        self.resume_path = Path(resume) if resume is not None else None
        self.bus = bus
        self.fit_enabled = fit
        self.on_progress = on_progress
        self.ask = ask if ask is not None else (_tty_ask if sys.stdin.isatty() else None)
        self.settings = plan_settings(self.plan)
        self.cell_id = self.plan.cell
        folder = out_dir if out_dir is not None else Path(self.plan.output.folder)
        if not Path(folder).is_absolute() and out_dir is None:
            folder = Path(lp.path).parent / folder
        self.out_dir = Path(os.path.abspath(folder))  # no "plans/../../runs" in what is printed or logged
        self._lock = threading.RLock()
        self._state = "idle"
        self._reason = ""
        self._abort = threading.Event()
        self._unpaused = threading.Event()
        self._unpaused.set()
        self._thread: Optional[threading.Thread] = None
        self._done_evt = threading.Event()
        self._summary: Optional[RunSummary] = None
        self.run_id = ""
        self.log_path: Optional[Path] = None
        self._total = 0
        self._done = 0
        self._measured = 0
        self._skipped = 0
        self._failed = 0
        self._current: Optional[str] = None
        self._remaining_est: list[float] = []
        self._wall0 = 0.0
        self._time_scale = 1.0
        self._skip_reasons: dict[str, str] = {}
        self.commander = None
        self._fake_cell: Optional[FakeCell] = None
        self._runlog = None

    # ------------------------------------------------------------------ public API
    def check_output(self) -> None:
        """Refuse, before any device is opened, a run whose log and results cannot be written:
        the output folder (created if missing) must take a new file, and a resumed log must be
        writable. Raises RunError saying which folder or file and what to do."""
        hint = "choose a writable folder with --out or the plan's output.folder"
        if self.resume_path is not None:
            target, hint = self.resume_path.parent, "copy the log to a writable folder and resume from there"
            if not os.access(self.resume_path, os.W_OK):
                raise RunError(f"--resume {self.resume_path}: the log is not writable; {hint}")
        else:
            target = self.out_dir
            try:
                target.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise RunError(f"output folder {target}: cannot create it ({exc.strerror or exc}); {hint}") from exc
        try:
            fd, probe = tempfile.mkstemp(prefix=".remaster-write-test-", dir=target)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise RunError(f"output folder {target}: cannot write in it ({exc.strerror or exc}); {hint}") from exc

    def start(self) -> str:
        """Check the output folder (``check_output``), then start the run in a background
        thread; returns its run id. Raises RunError before anything connects when the run's
        log cannot be written."""
        with self._lock:
            if self._state != "idle":
                raise RuntimeError(f"run already {self._state}")
            self.check_output()
            self._state = "starting"
            if self.resume_path is not None:
                from acquire.recorder import read_run

                self._resumed = read_run(self.resume_path)
                self.run_id = self._resumed.run_id
            else:
                self._resumed = None
                self.run_id = make_run_id(self.cell_id)
            self._wall0 = time.monotonic()
        self._thread = threading.Thread(target=self._main, name=f"run-{self.run_id}", daemon=True)
        self._thread.start()
        return self.run_id

    def pause(self) -> None:
        """Finish the current configuration, then hold."""
        with self._lock:
            if self._state in ("running", "starting", "suspended"):
                self._unpaused.clear()
                self._event_safe("pause_requested")

    def resume(self) -> None:
        with self._lock:
            self._unpaused.set()

    def abort(self, reason: str = "aborted") -> None:
        """Stop safely: the robot decelerates (``commander.stop``), the log is closed."""
        with self._lock:
            if self._state in TERMINAL or self._abort.is_set():
                return
            self._reason = reason
            self._abort.set()
            self._unpaused.set()
            if self._state != "idle":
                self._set_state("stopping")
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
        for sp in list(self._sensors):
            if callable(getattr(sp.sensor, "confirm", None)):
                what = getattr(sp.sensor, "waiting_for", None)
                if what:
                    waiting.append(f"{sp.sensor.name}: {what}")
                sp.sensor.confirm()
        self._event_safe("confirmed", waiting=waiting)
        return waiting

    def wait(self, timeout: float | None = None) -> RunSummary:
        if not self._done_evt.wait(timeout):
            raise TimeoutError(f"run {self.run_id} still {self._state} after {timeout} s")
        assert self._summary is not None
        return self._summary

    def status(self) -> dict:
        with self._lock:
            return {
                "state": self._state,
                "run_id": self.run_id,
                "done": self._done,
                "total": self._total,
                "measured": self._measured,
                "failed": self._failed,
                "skipped": self._skipped,
                "eta_s": self._eta(),
                "current": self._current,
                "log": str(self.log_path) if self.log_path else None,
                "reason": self._reason,
            }

    # ------------------------------------------------------------------ internals
    def _set_state(self, state: str, reason: str = "") -> None:
        with self._lock:
            if state == self._state:
                return
            self._state = state
            if reason or state == "running":
                self._reason = reason
        log.info("run %s: %s%s", self.run_id, state, f" ({reason})" if reason else "")
        self._event_safe("state", state=state, reason=reason)
        self._progress()

    def _progress(self) -> None:
        st = self.status()
        if self.on_progress is not None:
            try:
                self.on_progress(st)
            except (OSError, ValueError) as exc:  # a closed terminal must not stop the run
                log.debug("progress display: %s", exc)
        if self.bus is not None and self.run_id and not self._bus_released:
            try:  # what `acquire watch` shows: the same dict, on remaster/<cell>/run/<run-id>/status
                from acquire.bus import key

                self.bus.publish(key(self.cell_id, "run", self.run_id, "status"), st)
            except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
                log.debug("bus publish failed: %s", exc)

    def _eta(self) -> float | None:
        """Wall seconds left: the remaining estimated cell time, scaled by how the configurations
        done so far compared with their estimates (before any, by the fake's time scale)."""
        if not self._remaining_est:
            return 0.0 if self._total else None
        remaining = float(sum(self._remaining_est))
        if self._est_done > 0 and self._loop_wall0 is not None:
            return remaining * (time.monotonic() - self._loop_wall0) / self._est_done
        return remaining / self._time_scale

    def _event_safe(self, kind: str, **fields) -> None:
        fields = {k: v for k, v in fields.items() if v is not None}
        if self._runlog is not None:
            try:
                self._runlog.event(kind, **fields)
            except (OSError, ValueError, RuntimeError) as exc:
                log.warning("could not log event %s: %s", kind, exc)
        if self.bus is not None and self.run_id:
            try:
                from acquire.bus import key

                self.bus.publish(key(self.cell_id, "run", self.run_id, "event"), {"kind": kind, **fields})
            except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
                log.debug("bus publish failed: %s", exc)

    def _record_reading(self, sensor: str, samples: list) -> None:
        """One sensor reading (settle window) to the log's marker stream and the bus."""
        if not samples:
            return
        positions = {s.marker: (s.position_mm if s.visible else None) for s in samples}
        device_time = samples[-1].device_time
        device_time = float(device_time) if math.isfinite(device_time) else None
        if self._runlog is not None:
            try:
                self._runlog.record_markers(sensor, positions, device_time=device_time)
            except (OSError, ValueError, RuntimeError) as exc:
                log.debug("marker frame not logged: %s", exc)
        if self.bus is not None:
            try:
                from acquire.bus import key

                self.bus.publish(key(self.cell_id, sensor, "markers"), {
                    "device_time": device_time,
                    "markers": [{"name": m, "position_mm": None if p is None else np.asarray(p).tolist()}
                                for m, p in positions.items()]})
            except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
                log.debug("bus publish failed: %s", exc)

    def _publish_sample(self, record: dict) -> None:
        if self.bus is None:
            return
        try:
            from acquire.bus import key

            self.bus.publish(key(self.cell_id, "run", self.run_id, "sample"), record)
        except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
            log.debug("bus publish failed: %s", exc)

    def _main(self) -> None:
        summary = None
        try:
            summary = self._run()
        except StorageError as exc:  # disk full / I/O error: the log is sealed; stop here, the robot holds
            log.error("run %s stopped: %s", self.run_id, exc)
            runlog, self._runlog = self._runlog, None  # nothing more can be written to it
            if runlog is not None:
                runlog.close()
            with self._lock:
                self._reason = str(exc)
            self._set_state("failed", self._reason)
        except BaseException as exc:  # noqa: BLE001 - the thread must always report how it ended
            log.exception("run %s failed", self.run_id)
            with self._lock:
                self._reason = f"{type(exc).__name__}: {exc}"
            self._set_state("failed", self._reason)
        finally:
            self._teardown()
            self._release_bus()
            if summary is None:
                summary = self._make_summary()
            self._summary = summary
            try:  # the last progress before wait() returns: the caller may close the bus right after
                self._progress()
            finally:
                self._done_evt.set()

    def _release_bus(self) -> None:
        """Undeclare the run's own publishers (once): a long-lived daemon bus must not keep them."""
        if self.bus is None or not self.run_id or self._bus_released:
            return
        self._bus_released = True
        from acquire.bus import key

        try:
            self.bus.release(key(self.cell_id, "run", self.run_id))
        except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
            log.debug("releasing the run's publishers: %s", exc)

    def _make_summary(self) -> RunSummary:
        with self._lock:
            return RunSummary(
                run_id=self.run_id, state=self._state, log_path=self.log_path, total=self._total,
                done=self._done, measured=self._measured, skipped=self._skipped, failed=self._failed,
                reason=self._reason, wall_seconds=time.monotonic() - self._wall0,
                skipped_reasons=dict(self._skip_reasons),
            )

    def _teardown(self) -> None:
        cmd, self.commander = self.commander, None
        for sensor in getattr(self, "_sensors", []):
            try:
                sensor.sensor.close()
            except (OSError, DriverError) as exc:
                log.warning("closing %s: %s", getattr(sensor.sensor, "name", "sensor"), exc)
        self._sensors = []
        if cmd is not None:
            try:
                cmd.stop()
            except DriverError as exc:
                log.warning("stop at the end: %s", exc)
            try:
                cmd.close()
            except (OSError, DriverError) as exc:
                log.warning("closing the commander: %s", exc)
        if self._tap is not None:
            self._tap.stop()
            self._tap = None
        if self._runlog is not None:
            try:
                self._runlog.close()
            except (OSError, ValueError, RuntimeError) as exc:
                log.error("closing the run log: %s", exc)
            self._runlog = None
        if self._fake_cell is not None:
            self._fake_cell.close()
            self._fake_cell = None

    _tap = None
    _bus_released = False
    _view = None
    _sensors: list = []
    _est_done = 0.0
    _loop_wall0: Optional[float] = None
    _clock = staticmethod(time.monotonic)
    _sleep = staticmethod(time.sleep)

    # ------------------------------------------------------------------ the job
    def _open_devices(self):
        lp, plan = self.lp, self.plan
        limits = JointLimits.from_model(lp.model)
        extra = {}
        clock, sleep = time.monotonic, time.sleep
        if self.fake:
            fc = self._fake_cell = FakeCell(lp)
            clock, sleep = fc.clock.now, fc.clock.sleep
            self._time_scale = fc.time_scale
            extra = {"clock": clock, "sleep": sleep}
            driver = plan.commander.driver
            # The cell runs time_scale × faster than real time, and its fake controller is a
            # thread that a busy machine can stall: the commanders' silence and staleness limits
            # (simulated time) get 300 ms of wall time, not a real cell's 100 ms. The exchange
            # process keeps its real-time priority, as against a real controller.
            ms = 300.0 * fc.time_scale
            url = {"fri": f"fri://127.0.0.1:0?timeout_ms={ms:g}&max_state_age_ms={ms:g}",
                   "rsi": f"rsi://127.0.0.1:0?max_state_age_s={ms / 1000:g}"}.get(driver)
            if url is None:
                raise RunError(f"--fake has no fake controller for commander driver {driver!r} (fri, rsi)")
            cmd = open_commander(plan.commander, limits, url=url, **extra)
            port = cmd.bind()[1] if callable(getattr(cmd, "bind", None)) else (cmd.connect() or cmd.address[1])
            self.commander = cmd
            launch = fc.start(port, plan.sensors)
            cmd.connect()
            sensors = [
                SensorSpec(open_sensor(s, url=fc.sensor_url(s), commander=cmd, clock=clock,
                                       **({"sleep": sleep} if s.driver in JOINT_SENSOR_DRIVERS else {})),
                           list(s.markers), float(s.noise_mm))
                for s in plan.sensors
            ]
        else:
            cmd = open_commander(plan.commander, limits)
            self.commander = cmd
            cmd.connect()
            sensors = [SensorSpec(open_sensor(s, commander=cmd), list(s.markers), float(s.noise_mm)) for s in plan.sensors]
        self._sensors = sensors
        return cmd, sensors, clock, sleep

    def _initial_registration(self) -> dict:
        """Initial base2sensor guesses for re-acquisition: the simulated cell's sensor placement
        under ``--fake``; none otherwise (then the first re-acquisitions spiral-search)."""
        if self._fake_cell is None:
            return {}
        truth = self._fake_cell.cell.truth
        out = {}
        for s in self.plan.sensors:
            if s.name in truth.base2sensor:
                out[s.name] = truth.base2sensor[s.name]
            else:
                kind = {"natnet": "mocap", "tracker": "tracker", "emscon": "tracker"}.get(s.driver)
                for sc in self._fake_cell.cell.config.sensors:
                    if sc.kind == kind:
                        out[s.name] = truth.base2sensor[sc.name]
                        break
        return out

    def _todo(self, configs):
        """Drop configurations the resumed log already measured, and those it skipped (the
        operator's or the plan's decision). Failed ones (a refused or faulted move, timeouts)
        are measured again unless ``skip_failed``."""
        if self._resumed is None:
            return configs, set()
        rc = self._resumed
        if rc.plan_text != self.lp.text:
            raise RunError(f"{self.resume_path}: the log was recorded with a different plan; resume it with "
                           "the plan it was recorded with")
        done = {s["config_id"] for s in rc.samples}
        skipped = {e.get("config_id") for e in rc.events if e.get("kind") == "skipped"} - done
        failed = {e.get("config_id") for e in rc.events if e.get("kind") == "failed"} - done - skipped
        ended = skipped | failed if self.skip_failed else skipped
        if failed and not self.skip_failed:
            log.info("resume: measuring %d failed configuration(s) again: %s", len(failed), sorted(failed)[:10])
            failed = set()
        known = {c.config_id for c in configs}
        stray = done - known
        if stray:
            raise RunError(f"{self.resume_path}: samples for configurations the plan does not have: {sorted(stray)[:5]}")
        with self._lock:
            self._measured = len(done)
            self._skipped = len(skipped)
            self._failed = len(failed)
        return [c for c in configs if c.config_id not in done and c.config_id not in ended], done | ended

    def _run(self) -> RunSummary:
        from acquire.plan import resolve_configurations
        from acquire.recorder import RunLog

        lp, s = self.lp, self.settings
        configs = resolve_configurations(lp)
        self._planned_q = np.stack([c.q_rad for c in configs]) if configs else None
        todo, already = self._todo(configs)
        with self._lock:
            self._total = len(configs)
            self._done = len(already)
        cmd, sensors, clock, sleep = self._open_devices()
        self._clock, self._sleep = clock, sleep
        if self._abort.is_set():
            return self._finish(clock, 0.0)
        start_q = np.asarray(cmd.first_state(FIRST_STATE_TIMEOUT_S).position_rad, dtype=float)
        order = order_configurations(todo, start_q, cmd.limits, s.speed)
        settle_est = estimate_settle_s(s.settle_window_s)
        measure_est = estimate_measure_s(s.samples, [SENSOR_RATE_HZ.get(sp.driver, 100.0) for sp in self.plan.sensors])
        with self._lock:
            self._remaining_est = list(move_times(order, start_q, cmd.limits, s.speed) + settle_est + measure_est)

        self.out_dir.mkdir(parents=True, exist_ok=True)
        if self._resumed is not None:
            self._runlog = RunLog.append_to(self.resume_path, live=self.live)
            self.log_path = self.resume_path
        else:
            run_dir = self.out_dir / self.run_id
            run_dir.mkdir(parents=True, exist_ok=True)
            self.log_path = run_dir / f"{self.run_id}.mcap"
            meta = {
                "cell": self.cell_id, "robot": lp.model.name, "plan_path": str(lp.path),
                "model_path": str(lp.model_path), "fake": str(bool(self.fake)),
                "n_configurations": str(len(configs)),
            }
            if self._fake_cell is not None:
                meta["sim_seed"] = str(self._fake_cell.cell.config.seed)
                meta["time_scale"] = str(self._fake_cell.time_scale)
            self._runlog = RunLog.create(self.log_path, run_id=self.run_id, plan_text=lp.text,
                                         model_text=lp.model_text, metadata=meta, live=self.live)

        from acquire.foxglove_view import RobotView
        from calib.kinematics import Chain

        chain = Chain(lp.model)
        predictor = ReflectorPredictor(chain, {m: lp.model.marker_index(m) for m in _plan_markers(self.plan)
                                               if m in lp.model.marker_names},
                                       self._initial_registration())
        if self._resumed is not None:
            for rec in self._resumed.samples:
                for mk in rec["markers"]:
                    predictor.add(mk["sensor"], mk["marker"], np.radians(rec["q_measured_deg"]), mk["mean_mm"])
        self._view = RobotView(chain)
        self._show_registration(predictor)
        self._tap = JointStateTap(cmd, self._runlog, self.bus, self.cell_id, lp.model.axis_names, period_s=0.04,
                                  view=self._view).start()
        self._event_safe("run_started", resumed=self._resumed is not None, todo=len(order), total=len(configs),
                         order=[c.config_id for c in order])
        seq = self.plan.sequencing
        suspender = LostTargetSuspender(
            seq.on_lost_target, wait_s=float(seq.lost_target_wait_s), predictor=predictor, clock=clock,
            sleep=sleep, event=self._event_safe, ask=self.ask,
        )
        proc = ConfigProcedure(cmd, sensors, s, clock=clock, sleep=sleep, event=self._event_safe,
                               on_reading=self._record_reading)
        self._set_state("running")
        t_cell0 = clock()
        self._loop_wall0 = time.monotonic()
        streak = 0
        for cfg in order:
            if not self._checkpoint():
                break
            with self._lock:
                self._current = cfg.config_id
            self._progress()
            outcome = self._one(cfg, proc, suspender, predictor)
            if outcome == "abort":  # the interrupted configuration is not done: a resume measures it
                self._abort.set()
                break
            streak = streak + 1 if outcome == "failed" else 0
            with self._lock:
                self._done += 1
                if self._remaining_est:
                    self._est_done += self._remaining_est.pop(0)
                if outcome == "measured":
                    self._measured += 1
                elif outcome == "skipped":
                    self._skipped += 1
                elif outcome == "failed":
                    self._failed += 1
                self._current = None
            self._progress()
            if streak >= MAX_CONSECUTIVE_FAILURES:
                raise RunError(f"{streak} configurations failed in a row (last: {self._skip_reasons.get(cfg.config_id)}); "
                               "the cell is not usable — fix it and resume the run")
        return self._finish(clock, clock() - t_cell0)

    def _checkpoint(self) -> bool:
        """Between configurations: honour pause and abort. False to stop the loop."""
        if not self._unpaused.is_set() and not self._abort.is_set():
            self._set_state("paused")
            self._unpaused.wait()
            if not self._abort.is_set():
                self._set_state("running")
        return not self._abort.is_set()

    def _one(self, cfg, proc: ConfigProcedure, suspender: LostTargetSuspender, predictor) -> str:
        """Move, settle, measure one configuration; returns measured | skipped | failed | abort."""
        t_start = time.time()
        s = self.settings
        for attempt in range(s.retries + 1):
            try:
                proc.move(cfg)
                break
            except LimitError as exc:
                return self._skip(cfg, f"move refused: {exc}", kind="failed")
            except DriverError as exc:
                if self._abort.is_set():
                    return "abort"
                if attempt == s.retries:
                    return self._skip(cfg, f"move failed {attempt + 1} times: {exc}", kind="failed")
                self._event_safe("retry", config_id=cfg.config_id, step="move", reason=str(exc))
                if isinstance(exc, DeviceFaultError):  # e.g. the FRI session dropped: wait it out
                    self._set_state("suspended", f"{cfg.config_id}: {exc}")
                    self._wait_ready()
                    if self._abort.is_set():
                        return "abort"
                    self._set_state("running")
                else:
                    self._wait_ready()
        attempts = 0
        timeouts = 0
        suspensions = 0
        while True:
            if self._abort.is_set():
                return "abort"
            attempts += 1
            try:
                record = proc.settle_and_measure(cfg, attempts, t_start)
            except TargetLostError as exc:
                suspensions += 1
                if suspensions > s.retries + 1:
                    return self._skip(cfg, f"target lost {suspensions} times at this configuration: {exc}")
                self._set_state("suspended", str(exc))
                sensor = self._sensor_of(exc)
                marker = sensor.markers[0] if sensor is not None else ""
                try:
                    q = self.commander.joint_state().position_rad
                except DriverError:
                    q = np.asarray(cfg.q_rad, dtype=float)
                rec = suspender.recover(sensor.sensor if sensor else self._sensors[0].sensor, marker,
                                        cfg.config_id, q, str(exc))
                if self._abort.is_set():
                    return "abort"
                self._set_state("running")
                if rec.action == "resume":
                    continue
                if rec.action == "abort":
                    self.abort(f"operator aborted at {cfg.config_id}")
                    return "abort"
                return self._skip(cfg, rec.reason)
            except DeviceTimeoutError as exc:
                timeouts += 1
                if timeouts > s.retries:
                    return self._skip(cfg, f"gave up after {timeouts} timeouts: {exc}", kind="failed")
                self._event_safe("retry", config_id=cfg.config_id, step="settle", reason=str(exc))
                self._wait_ready()
                continue
            break
        self._runlog.sample(record)
        self._publish_sample(record)
        for mk in record["markers"]:
            predictor.add(mk["sensor"], mk["marker"], np.radians(record["q_measured_deg"]), mk["mean_mm"])
        self._show_registration(predictor)
        return "measured"

    def _show_registration(self, predictor) -> None:
        """Foxglove view: ``base → sensor`` from the current registration estimate of every
        sensor, and the model's nominal markers on the flange (again after every sample, so a
        viewer that connects mid-run sees them)."""
        from acquire.foxglove_view import nominal_markers_scene

        try:  # the view must never stop a run
            for spec in self.plan.sensors:
                self._view.set_registration(spec.name, predictor.base2sensor(spec.name)[0])
            markers = {m.name: m.xyz for m in self.lp.model.tool.markers}
            self._runlog.record_scene(nominal_markers_scene(markers, time.time_ns()))
        except (OSError, ValueError, RuntimeError) as exc:
            log.warning("Foxglove view not updated: %s", exc)

    def _wait_ready(self) -> None:
        """After a failed move: wait for the controller to stream again (a fresh joint state,
        up to ``move_timeout_s``) and the robot to come to rest before the next attempt."""
        s = self.settings
        clock, sleep = self._clock, self._sleep
        deadline = clock() + s.move_timeout_s
        while not self._abort.is_set():
            try:
                self.commander.joint_state()
                break
            except DriverError as exc:
                if clock() > deadline:
                    log.warning("controller not streaming after a failed move: %s", exc)
                    return
                sleep(0.05)
        try:
            self.commander.wait_settled(s.settle_tolerance_rad, s.settle_window_s, s.move_timeout_s)
        except DriverError as exc:
            log.warning("robot not at rest after a failed move: %s", exc)

    def _sensor_of(self, exc: BaseException) -> Optional[SensorSpec]:
        text = str(exc)
        for sp in self._sensors:
            if text.startswith(f"{sp.sensor.name}:"):
                return sp
        return self._sensors[0] if self._sensors else None

    def _skip(self, cfg, reason: str, kind: str = "skipped") -> str:
        log.warning("%s %s: %s", kind, cfg.config_id, reason)
        self._event_safe(kind, config_id=cfg.config_id, reason=reason)
        with self._lock:
            self._skip_reasons[cfg.config_id] = reason
        return kind

    def _log_link(self) -> None:
        """The real-time link over the run into the log (event ``link``): cycles, late answers,
        answer latency p50/p99/max (µs, over the last ``window`` cycles), missing and malformed
        packets, the exchange's scheduling — how the exchange kept its deadline on this PC."""
        stats = getattr(self.commander, "link_stats", None)
        if not callable(stats):
            return
        try:
            st = stats()
        except DriverError as exc:
            log.warning("link figures: %s", exc)
            return
        self._event_safe(
            "link", packets=st.packets, window=st.window, late_answers=st.late_answers,
            latency_p50_us=round(st.latency_p50_s * 1e6, 1), latency_p99_us=round(st.latency_p99_s * 1e6, 1),
            latency_max_us=round(st.latency_max_s * 1e6, 1), gaps=st.gaps, malformed=st.malformed,
            restarts=st.restarts, realtime=st.realtime, notes=list(st.notes),
        )
        if st.late_answers:
            log.warning("%s: %d late real-time answer(s) in this run (%s)", getattr(self.commander, "name", "commander"),
                        st.late_answers, "; ".join(st.report()[:2]))

    def _finish(self, clock, cell_seconds: float) -> RunSummary:
        aborted = self._abort.is_set()
        if aborted:
            self._set_state("stopping")
            if self.commander is not None:
                try:
                    self.commander.stop()
                except DriverError as exc:
                    log.warning("stop: %s", exc)
            self._log_link()
            self._event_safe("aborted", reason=self._reason)
        else:
            self._log_link()
            self._event_safe("run_finished", measured=self._measured, skipped=self._skipped, failed=self._failed)
        truth = sag = None
        if self._fake_cell is not None:
            truth = self._fake_cell.cell.truth.offsets_deg.tolist()
            if getattr(self, "_planned_q", None) is not None:
                # The cell's gravity sag per joint, averaged over the plan: a zero-offset fit
                # cannot tell its mean from an offset, so the summary shows it beside the truth.
                sag = np.degrees(self._fake_cell.cell.deflection(self._planned_q).mean(axis=0)).tolist()
        self._teardown()
        state = "aborted" if aborted else "finished"
        summary = self._make_summary()
        summary.cell_seconds = cell_seconds
        summary.truth_offsets_deg = truth
        summary.truth_mean_sag_deg = sag
        reason = self._reason if aborted else ""
        if not aborted and self.fit_enabled and self.log_path is not None:
            # A run that was asked for a result and has none has failed (exit 1), even when every
            # configuration was visited: the operator must not read "finished" as "calibrated".
            if self._measured == 0:
                reason = (f"no result: none of the {self._total} configurations was measured "
                          f"({self._skipped} skipped, {self._failed} failed)")
            else:
                try:
                    summary.fit, summary.result_path, summary.report_path = fit_run_log(self.log_path, self.lp)
                except (ValueError, RuntimeError, ArithmeticError) as exc:
                    reason = f"no result: the fit of {self._measured} measured configuration(s) failed: {exc}"
            if summary.fit is None:
                log.error("run %s: %s", self.run_id, reason)
                state = "failed"
        with self._lock:
            self._reason = reason if state == "failed" else self._reason
        self._set_state(state, reason)
        summary.state = state
        summary.reason = reason
        self._release_bus()  # after the final state went out on the bus
        return summary


def _plan_markers(plan) -> list[str]:
    out: list[str] = []
    for s in plan.sensors:
        out += [m for m in s.markers if m not in out]
    return out


class JointStateTap:
    """Streams the commander's measured joint state into the log (``/joint_state``,
    ``RunLog.record_joint_state``; with a ``view``, the robot's frames on ``/tf``) and onto the bus
    (``remaster/<cell>/<commander>/joint_state``) every ``period_s`` wall seconds, on its own thread."""

    def __init__(self, commander, runlog, bus, cell: str, names, period_s: float = 0.04, view=None) -> None:
        self.commander, self.runlog, self.bus, self.cell = commander, runlog, bus, cell
        self.view = view  # acquire.foxglove_view.RobotView: /tf from each joint state
        self.names = list(names)
        self.period_s = period_s
        self.device = getattr(commander, "name", "robot")
        self._halt = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._key = None

    def start(self) -> "JointStateTap":
        if self.bus is not None:
            from acquire.bus import key

            self._key = key(self.cell, self.device, "joint_state")
        self._thread = threading.Thread(target=self._loop, name="joint-state-tap", daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        skipped = 0  # ticks whose state could not be recorded (reported once, then every 100th)
        while not self._halt.wait(self.period_s):
            try:
                st = self.commander.joint_state()
            except (DriverError, AttributeError):
                continue
            try:
                self._tick(st)
            except (OSError, ValueError, RuntimeError, AttributeError) as exc:
                if getattr(self.runlog, "closed", False):
                    return  # the log is closing: the run is over
                skipped += 1
                if skipped == 1 or skipped % 100 == 0:
                    log.warning("joint state not recorded (%d tick(s) so far): %s", skipped, exc)

    def _tick(self, st) -> None:
        """Record one joint state (and its frames) in the log and publish it on the bus."""
        t_ns = time.time_ns()
        self.runlog.record_joint_state(self.device, st.position_rad, names=self.names,
                                       device_time=float(st.device_time), log_time_ns=t_ns)
        if self.view is not None:
            try:
                tf = self.view.transforms(st.position_rad, t_ns)
            except ValueError as exc:  # e.g. a non-finite joint reading: no frames this tick
                log.debug("no frame transforms: %s", exc)
            else:
                self.runlog.record_transforms(tf, log_time_ns=t_ns)
        if self._key is not None:
            try:
                self.bus.publish(self._key, {"name": self.names, "position_deg": np.degrees(st.position_rad).tolist(),
                                             "device_time": float(st.device_time)})
            except Exception as exc:  # noqa: BLE001 - the bus must never stop a run
                log.debug("bus publish failed: %s", exc)

    def stop(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)


# ------------------------------------------------------------------------------ hand-off
def _link_tolerance(fit) -> tuple[float, float] | None:
    """The plan's link-parameter prior (mm, deg), or None for the paper's model."""
    mm, deg = getattr(fit, "link_tolerance_mm", 0.2), getattr(fit, "link_tolerance_deg", 0.02)
    return None if mm is None or deg is None else (float(mm), float(deg))


def fit_run_log(log_path: Path, lp, *, n_random: int = 500) -> tuple[dict, Path, Path | None]:
    """Fit the zero-offsets from a run log; write ``result.json`` and ``report.html`` beside it.

    Returns (result document, result path, report path). The plan's ``fit`` section chooses
    the method, joints, error model, registration handling and validation fraction.
    """
    if getattr(lp.plan, "socket", None) is not None:
        return fit_socket_run_log(log_path, lp)
    from acquire.recorder import dataset_from_run
    from calib.controller import apply_guards, controller_values
    from calib.fit import FitOptions, fit_offsets
    from calib.kinematics import Chain
    from calib.metrics import accuracy_metrics
    from calib.result import result_dict, write_result

    model = lp.model
    ds = dataset_from_run(Path(log_path), model)
    fit = lp.plan.fit
    frac = getattr(fit, "validate_fraction", None) or 0.0
    if frac > 0:
        configs = np.unique(ds.config)
        rng = np.random.default_rng(0)
        n_val = int(round(frac * len(configs)))
        val_ids = set(rng.choice(configs, size=n_val, replace=False).tolist()) if n_val else set()
        is_val = np.array([c in val_ids for c in ds.config])
        ds = ds.with_split("cal")
        ds.split[is_val] = "val"
    cal = ds.calibration()
    val = ds.validation() if np.any(ds.split == "val") else None
    joints = getattr(fit, "joints", None)
    options = FitOptions(
        method=getattr(fit, "method", "fast") or "fast",
        joints=tuple(joints) if joints else None,
        fix_registration=bool(getattr(fit, "fix_registration", False)),
        error=getattr(fit, "error", "gaussian") or "gaussian",
        link_tolerance=_link_tolerance(fit),
        compliance=bool(getattr(fit, "compliance", False)),
        tool_prior_mm=float(getattr(fit, "tool_prior_mm", 10.0)),
    )
    base = Path(log_path)
    if options.method == "auto":
        return _fit_run_auto(base, model, cal, val, options, fit, n_random)
    result = fit_offsets(model, cal, options)
    metrics = accuracy_metrics(Chain(model), cal, result.applied_offsets_rad, result.offset_samples_rad,
                               result.applied_sigma_mm, validation=val, n_random=n_random, seed=0,
                               markers_mm=result.fitted_markers_mm)
    doc = result_dict(result, cal, metrics=metrics)
    apply_guards(doc)
    values = controller_values(model, doc["joint_offsets"])
    doc["controller"] = values.to_dict()
    result_path = base.with_name("result.json")
    write_result(result_path, doc)
    report_path = None
    try:
        from calib.report import write_report

        report_path = base.with_name("report.html")
        write_report(report_path, result, cal, doc, values.format())
    except (ImportError, ValueError, RuntimeError, OSError) as exc:
        log.warning("report not written (use `acquire fit %s`): %s", log_path, exc)
        report_path = None
    return doc, result_path, report_path


def _fit_run_auto(base: Path, model, cal, val, options, fit, n_random: int) -> tuple[dict, Path, Path | None]:
    """The plan's ``fit.method: auto``: ``calib.auto_fit`` (the data choose among the offsets models;
    a link scale set in the plan is used instead of the empirical Bayes one; ``fit.compliance``:
    only the candidates with compliance)."""
    from dataclasses import replace

    from calib.auto_fit import auto_fit
    from calib.result import write_result

    given = getattr(fit, "model_fields_set", set()) & {"link_tolerance_mm", "link_tolerance_deg"}
    done = auto_fit(model, cal, val, replace(options, method="laplace", compliance=False),
                    link_tolerance=_link_tolerance(fit) if given else None, n_random=n_random, include_full=False,
                    compliance_only=bool(getattr(fit, "compliance", False)) and model.has_dynamics)
    result_path = base.with_name("result.json")
    write_result(result_path, done.doc)
    report_path = None
    try:
        from calib.report import write_report

        report_path = base.with_name("report.html")
        write_report(report_path, done.result, cal, done.doc, done.controller_text)
    except (ImportError, ValueError, RuntimeError, OSError) as exc:
        log.warning("report not written (use `acquire fit %s`): %s", base, exc)
        report_path = None
    return done.doc, result_path, report_path


def fit_socket_run_log(log_path: Path, lp) -> tuple[dict, Path, None]:
    """Fit a socket run (``calib.socket.fit_socket``; held-out placements with three or more):
    ``result.json`` and the corrected model ``model.yaml`` beside the log. The plan's
    ``fit.method`` fast uses the link prior (``link_tolerance_*``), paper identifies without it."""
    from acquire.commands.socket_fit import read_socket_run, socket_result_dict, write_socket_model
    from calib.result import write_result
    from calib.socket import fit_socket, leave_one_placement_out

    model, fit = lp.model, lp.plan.fit
    ds = read_socket_run(Path(log_path), model.n_joints, distance_mm=lp.plan.socket.distance_mm)
    if ds is None:
        raise ValueError(f"{log_path}: no socket records to fit")
    method = "fast" if getattr(fit, "method", "fast") == "fast" else "full"
    tolerance = _link_tolerance(fit) if method == "fast" else None
    compliance = bool(getattr(fit, "compliance", False))
    result = fit_socket(model, ds, tolerance=tolerance, compliance=compliance)
    folds = leave_one_placement_out(model, ds, tolerance=tolerance, compliance=compliance) \
        if len(ds.placements) >= 3 else []
    doc = socket_result_dict(model, ds, result, folds, method)
    base = Path(log_path)
    doc["model_file"] = str(write_socket_model(model, result, base.with_name("model.yaml")))
    result_path = base.with_name("result.json")
    write_result(result_path, doc)
    return doc, result_path, None
