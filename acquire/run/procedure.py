"""The per-configuration procedure of a run: move, settle, measure, record — with retries, the
lost-target suspension and the registration estimate that aims a tracker back at its reflector.

``ConfigurationRunner.measure(cfg)`` returns what became of one configuration: ``measured``
(one sample record in the log), ``skipped`` (the plan's or the operator's decision), ``failed``
(a move refused for its target, a device fault that outlasted the plan's allowance, faults that
kept passing at once more than ``retries`` times) or ``abort`` (the run is stopping; the
configuration is not done, a resume measures it). A device fault suspends the run and is waited
out (``acquire.run.suspenders.DeviceFaultSuspender``); then the configuration starts again at its move.

The first registration for re-acquisition is the same for every cell (``initial_registration``):
the plan's approximate sensor placement where it gives one; from three measured configurations
on, a least-squares registration of the samples so far (``acquire.run.suspenders.ReflectorPredictor``);
before that, with no placement, a lost beam is found by the tracker's spiral search.
"""

from __future__ import annotations

import logging
import time
from typing import Optional

import numpy as np

from acquire.run.sequencer import ConfigProcedure, SensorSpec, is_joint_sensor
from acquire.run.suspenders import DeviceFaultSuspender, LostTargetSuspender, Probe, ReflectorPredictor
from drivers.errors import DriverError, LimitError, NotReadyError, TargetLostError

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
    predictor: ``ReflectorPredictor``; view: ``acquire.record.foxglove_view.RobotView`` (or None);
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
        self.faults = DeviceFaultSuspender(clock=clock, sleep=sleep, event=pub.event,
                                           stopping=lambda: self.aborting)
        self.proc = ConfigProcedure(commander, sensors, settings, clock=clock, sleep=sleep, event=pub.event,
                                    on_reading=pub.reading)
        self.last_record: Optional[dict] = None  # the last sample record written
        self._lost = 0  # lost-target suspensions at the current configuration

    @property
    def aborting(self) -> bool:
        return self.state.aborting.is_set()

    def measure(self, cfg) -> str:
        """Move, settle, measure, record ``cfg``; returns measured | skipped | failed | abort.

        A device fault anywhere on the way (``DriverError`` other than a refusal for the target
        and a lost target) suspends the run: it waits for the devices within the plan's
        allowances (``DeviceFaultSuspender``), then goes back to this configuration's move, which
        checks the robot's state again before anything moves."""
        t_start = time.time()
        self._lost = 0
        first_fault: Optional[float] = None
        passed = 0  # faults over by the first probe: retried ``retries`` times, and for as long as an allowance
        while True:
            if self.aborting:
                return "abort"
            step = ["move"]
            try:
                return self._visit(cfg, t_start, step)
            except DriverError as exc:
                if self.aborting:
                    return "abort"
                if isinstance(exc, LimitError) and not isinstance(exc, NotReadyError):
                    return self.skip(cfg, f"{step[0]} refused: {exc}", kind="failed")
                first_fault = self.clock() if first_fault is None else first_fault
                action = self._wait_out(cfg, step[0], exc, first_fault)
                if action == "retry":  # over before the first probe: retried while within an allowance
                    passed += 1
                    if passed > self.settings.retries and self.clock() - first_fault >= self._allowance_s():
                        return self.skip(cfg, f"{step[0]} failed {passed} times in {self.clock() - first_fault:.1f} s: "
                                         f"{exc}", kind="failed")
                    self.pub.event("retry", config_id=cfg.config_id, step=step[0], reason=str(exc))
                elif action != "resume":
                    return action

    # ------------------------------------------------------------------ steps
    def _visit(self, cfg, t_start: float, step: list[str]) -> str:
        """One try at ``cfg``: move, settle, measure, record; ``step[0]`` says where it is.
        Raises the DriverError of a device fault (``measure`` waits it out)."""
        self.proc.move(cfg)
        step[0] = "settle"
        record = self._settle_and_measure(cfg, t_start)
        if isinstance(record, str):
            return record
        self._record(cfg, record)
        for mk in record["markers"]:
            self.predictor.add(mk["sensor"], mk["marker"], np.radians(record["q_measured_deg"]), mk["mean_mm"])
        self.show_registration()
        return "measured"

    def _settle_and_measure(self, cfg, t_start: float):
        """The sample record of ``cfg``, or the outcome (str) when a lost target ended it."""
        s = self.settings
        attempts = 0
        while True:
            if self.aborting:
                return "abort"
            attempts += 1
            try:
                return self.proc.settle_and_measure(cfg, attempts, t_start)
            except TargetLostError as exc:
                self._lost += 1
                if self._lost > s.retries + 1:
                    return self.skip(cfg, f"target lost {self._lost} times at this configuration: {exc}")
                action = self._recover(cfg, exc)
                if action != "resume":
                    return action

    def _allowance_s(self) -> float:
        """The longest device-fault allowance of the plan (s)."""
        return max(self.settings.robot_fault_wait_s, self.settings.sensor_fault_wait_s)

    def probes(self) -> list[Probe]:
        """What ``DeviceFaultSuspender`` checks: the commander (``ready()``: a move could start)
        and every position sensor (it answers a read), each with the plan's allowance."""
        s, cmd = self.settings, self.commander
        ready = getattr(cmd, "ready", None) or cmd.joint_state
        out = [Probe(getattr(cmd, "name", "commander"), ready, s.robot_fault_wait_s)]
        for sp in self.sensors:
            if not is_joint_sensor(sp.sensor):
                out.append(Probe(sp.sensor.name, _answers(sp.sensor), s.sensor_fault_wait_s))
        return out

    def _wait_out(self, cfg, step: str, exc: DriverError, since: float) -> str:
        """Wait out a device fault at ``cfg``: resume | retry | failed | abort (see ``measure``)."""
        reason = f"{step}: {exc}"
        suspended = []

        def suspend() -> None:
            suspended.append(True)
            self.state.set("suspended", f"{cfg.config_id}: {reason}")

        rec = self.faults.recover(cfg.config_id, reason, self.probes(), since, on_suspend=suspend)
        if self.aborting:
            return "abort"
        if suspended:
            self.state.set("running")
        if rec.action == "fail":
            return self.skip(cfg, rec.reason, kind="failed")
        return rec.action

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

    def _record(self, cfg, record: dict) -> None:
        """Write the sample record.

        RECORDING ERRORS: a ``acquire.record.logstorage.StorageError`` (disk full, I/O error; the log is
        sealed at its last complete record) is not caught here: it ends the loop with the robot
        held where it settled, and ``RunController`` fails the run with its one line.
        """
        self.pub.sample(record)
        self.last_record = record  # an adaptive run's design reads it (acquire.run.adaptive)

    # ------------------------------------------------------------------ helpers
    def show_registration(self) -> None:
        """Foxglove view: ``base → sensor`` from the current registration estimate of every
        sensor, and the model's nominal markers on the flange (again after every sample, so a
        viewer that connects mid-run sees them)."""
        if self.view is None or self.pub.runlog is None:
            return
        from acquire.record.foxglove_view import nominal_markers_scene

        try:  # the view must never stop a run
            for spec in self.lp.plan.sensors:
                self.view.set_registration(spec.name, self.predictor.base2sensor(spec.name)[0])
            markers = {m.name: m.xyz for m in self.lp.model.tool.markers}
            self.pub.runlog.record_scene(nominal_markers_scene(markers, time.time_ns()))
        except (OSError, ValueError, RuntimeError) as exc:
            log.warning("Foxglove view not updated: %s", exc)

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


#: How long a sensor probe waits for a reading (s, the run's clock).
PROBE_READ_S = 0.5


def _answers(sensor):
    """A probe that passes when ``sensor`` answers a read (visible or not: a lost target is the
    lost-target suspender's); DriverError (timeout, closed connection) while it does not."""
    def check() -> None:
        sensor.read(PROBE_READ_S)
    return check
