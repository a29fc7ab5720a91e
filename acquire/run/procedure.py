"""The per-configuration procedure of a run: move, settle, measure, record — with retries, the
lost-target suspension and the registration estimate that aims a tracker back at its reflector.

``ConfigurationRunner.measure(cfg)`` returns what became of one configuration: ``measured``
(one sample record in the log), ``skipped`` (the plan's or the operator's decision), ``failed``
(a refused or faulted move, repeated timeouts) or ``abort`` (the run is stopping; the
configuration is not done, a resume measures it).

The first registration for re-acquisition is the same for every cell (``initial_registration``):
the plan's approximate sensor placement where it gives one; from three measured configurations
on, a least-squares registration of the samples so far (``acquire.suspenders.ReflectorPredictor``);
before that, with no placement, a lost beam is found by the tracker's spiral search.
"""

from __future__ import annotations

import logging
import time
from typing import Optional

import numpy as np

from acquire.sequencer import ConfigProcedure, SensorSpec
from acquire.suspenders import LostTargetSuspender, ReflectorPredictor
from drivers.errors import DeviceFaultError, DeviceTimeoutError, DriverError, LimitError, TargetLostError

log = logging.getLogger(__name__)


def initial_registration(plan) -> dict[str, np.ndarray]:
    """base2sensor (4, 4) guesses from the plan's approximate sensor placements
    (``sensors[].placement``, sensor pose in the robot base frame), by sensor name."""
    out = {}
    for s in plan.sensors:
        placement = getattr(s, "placement", None)
        if placement is not None:
            out[s.name] = np.linalg.inv(placement.matrix())
    return out


def plan_markers(plan) -> list[str]:
    """Every marker the plan's sensors measure, once, in plan order."""
    out: list[str] = []
    for s in plan.sensors:
        out += [m for m in s.markers if m not in out]
    return out


def make_predictor(lp, chain, resumed=None) -> ReflectorPredictor:
    """The registration estimate: the plan's placements, then the samples (a resumed log's first)."""
    model = lp.model
    predictor = ReflectorPredictor(chain, {m: model.marker_index(m) for m in plan_markers(lp.plan)
                                           if m in model.marker_names}, initial_registration(lp.plan))
    if resumed is not None:
        for rec in resumed.samples:
            for mk in rec["markers"]:
                predictor.add(mk["sensor"], mk["marker"], np.radians(rec["q_measured_deg"]), mk["mean_mm"])
    return predictor


class ConfigurationRunner:
    """Measures one configuration at a time (see the module docstring).

    state: the run's ``RunState``; pub: its ``RunPublisher``; commander / sensors (``SensorSpec``
    list): the open devices; settings: ``SequencingSettings``; clock / sleep: the cell's time;
    predictor: ``ReflectorPredictor``; view: ``acquire.foxglove_view.RobotView`` (or None);
    ask: the operator's terminal (``ask`` policy) or None; abort: the run's ``abort(reason)``.
    """

    def __init__(self, lp, state, pub, commander, sensors: list[SensorSpec], settings, *, clock, sleep,
                 predictor: ReflectorPredictor, view=None, ask=None, abort=None) -> None:
        self.lp, self.state, self.pub = lp, state, pub
        self.commander, self.sensors, self.settings = commander, sensors, settings
        self.clock, self.sleep = clock, sleep
        self.predictor, self.view = predictor, view
        self.abort = abort or (lambda reason: state.request_abort(reason))
        seq = lp.plan.sequencing
        self.suspender = LostTargetSuspender(
            seq.on_lost_target, wait_s=float(seq.lost_target_wait_s), predictor=predictor, clock=clock,
            sleep=sleep, event=pub.event, ask=ask,
        )
        self.proc = ConfigProcedure(commander, sensors, settings, clock=clock, sleep=sleep, event=pub.event,
                                    on_reading=pub.reading)
        self.last_record: Optional[dict] = None  # the last sample record written

    @property
    def aborting(self) -> bool:
        return self.state.aborting.is_set()

    def measure(self, cfg) -> str:
        """Move, settle, measure, record ``cfg``; returns measured | skipped | failed | abort."""
        t_start = time.time()
        moved = self._move(cfg)
        if moved is not None:
            return moved
        record = self._settle_and_measure(cfg, t_start)
        if isinstance(record, str):
            return record
        written = self._record(cfg, record)
        if written is not None:
            return written
        for mk in record["markers"]:
            self.predictor.add(mk["sensor"], mk["marker"], np.radians(record["q_measured_deg"]), mk["mean_mm"])
        self.show_registration()
        return "measured"

    # ------------------------------------------------------------------ steps
    def _move(self, cfg) -> Optional[str]:
        """Move to ``cfg`` with the plan's retries; None when there, else the outcome."""
        s = self.settings
        for attempt in range(s.retries + 1):
            try:
                self.proc.move(cfg)
                return None
            except LimitError as exc:
                return self.skip(cfg, f"move refused: {exc}", kind="failed")
            except DriverError as exc:
                if self.aborting:
                    return "abort"
                if attempt == s.retries:
                    return self.skip(cfg, f"move failed {attempt + 1} times: {exc}", kind="failed")
                self.pub.event("retry", config_id=cfg.config_id, step="move", reason=str(exc))
                if isinstance(exc, DeviceFaultError):  # e.g. the FRI session dropped: wait it out
                    self.state.set("suspended", f"{cfg.config_id}: {exc}")
                    self.wait_ready()
                    if self.aborting:
                        return "abort"
                    self.state.set("running")
                else:
                    self.wait_ready()
        return None

    def _settle_and_measure(self, cfg, t_start: float):
        """The sample record of ``cfg``, or the outcome (str) when there is none."""
        s = self.settings
        attempts = timeouts = suspensions = 0
        while True:
            if self.aborting:
                return "abort"
            attempts += 1
            try:
                return self.proc.settle_and_measure(cfg, attempts, t_start)
            except TargetLostError as exc:
                suspensions += 1
                if suspensions > s.retries + 1:
                    return self.skip(cfg, f"target lost {suspensions} times at this configuration: {exc}")
                action = self._recover(cfg, exc)
                if action != "resume":
                    return action
            except DeviceTimeoutError as exc:
                timeouts += 1
                if timeouts > s.retries:
                    return self.skip(cfg, f"gave up after {timeouts} timeouts: {exc}", kind="failed")
                self.pub.event("retry", config_id=cfg.config_id, step="settle", reason=str(exc))
                self.wait_ready()

    def _recover(self, cfg, exc: TargetLostError) -> str:
        """Suspend on a lost target and follow the suspender: resume | skipped | abort."""
        self.state.set("suspended", str(exc))
        sensor = self.sensor_of(exc)
        marker = sensor.markers[0] if sensor is not None else ""
        try:
            q = self.commander.joint_state().position_rad
        except DriverError:
            q = np.asarray(cfg.q_rad, dtype=float)
        rec = self.suspender.recover(sensor.sensor if sensor else self.sensors[0].sensor, marker,
                                     cfg.config_id, q, str(exc))
        if self.aborting:
            return "abort"
        self.state.set("running")
        if rec.action == "resume":
            return "resume"
        if rec.action == "abort":
            self.abort(f"operator aborted at {cfg.config_id}")
            return "abort"
        return self.skip(cfg, rec.reason)

    def _record(self, cfg, record: dict) -> Optional[str]:
        """Write the sample record; None when written.

        RECORDING ERRORS: a ``acquire.logstorage.StorageError`` (disk full, I/O error; the log is
        sealed at its last complete record) is not caught here: it ends the loop with the robot
        held where it settled, and ``RunController`` fails the run with its one line.
        """
        self.pub.sample(record)
        self.last_record = record  # an adaptive run's design reads it (acquire.run.adaptive)
        return None

    # ------------------------------------------------------------------ helpers
    def show_registration(self) -> None:
        """Foxglove view: ``base → sensor`` from the current registration estimate of every
        sensor, and the model's nominal markers on the flange (again after every sample, so a
        viewer that connects mid-run sees them)."""
        if self.view is None or self.pub.runlog is None:
            return
        from acquire.foxglove_view import nominal_markers_scene

        try:  # the view must never stop a run
            for spec in self.lp.plan.sensors:
                self.view.set_registration(spec.name, self.predictor.base2sensor(spec.name)[0])
            markers = {m.name: m.xyz for m in self.lp.model.tool.markers}
            self.pub.runlog.record_scene(nominal_markers_scene(markers, time.time_ns()))
        except (OSError, ValueError, RuntimeError) as exc:
            log.warning("Foxglove view not updated: %s", exc)

    def wait_ready(self) -> None:
        """After a failed move: wait for the controller to stream again (a fresh joint state,
        up to ``move_timeout_s``) and the robot to come to rest before the next attempt."""
        s = self.settings
        deadline = self.clock() + s.move_timeout_s
        while not self.aborting:
            try:
                self.commander.joint_state()
                break
            except DriverError as exc:
                if self.clock() > deadline:
                    log.warning("controller not streaming after a failed move: %s", exc)
                    return
                self.sleep(0.05)
        try:
            self.commander.wait_settled(s.settle_tolerance_rad, s.settle_window_s, s.move_timeout_s)
        except DriverError as exc:
            log.warning("robot not at rest after a failed move: %s", exc)

    def sensor_of(self, exc: BaseException) -> Optional[SensorSpec]:
        text = str(exc)
        for sp in self.sensors:
            if text.startswith(f"{sp.sensor.name}:"):
                return sp
        return self.sensors[0] if self.sensors else None

    def skip(self, cfg, reason: str, kind: str = "skipped") -> str:
        log.warning("%s %s: %s", kind, cfg.config_id, reason)
        self.pub.event(kind, config_id=cfg.config_id, reason=reason)
        with self.state.lock:
            self.state.skip_reasons[cfg.config_id] = reason
        return kind
