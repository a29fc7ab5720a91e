"""Suspend and resume as objects (bluesky's suspenders, adapted to a lost target).

A run suspends only at a checkpoint — the configuration being settled or measured — when a
sensor reports its target lost (``TargetLostError``). ``LostTargetSuspender.recover`` then
tries to get the target back and says what the run does next:

1. a tracker-like sensor (one with ``aim`` and ``search``) is aimed at where the model predicts
   the reflector is (``ReflectorPredictor``: nominal kinematics at the measured joints through
   the current least-squares registration of the samples so far; before three samples the
   plan's rough sensor placement; without one, no aim), then spiral-searched around
   the aim direction;
2. if that fails (or the sensor cannot re-acquire), the plan's policy decides:
   ``wait`` — wait up to ``lost_target_wait_s`` for the target to come back by itself;
   ``reacquire`` — as 1 with a wider search, then wait, aiming and searching again; ``ask`` — ask the operator on a TTY
   (retry / skip / abort), without a TTY treated as ``skip`` with the reason logged;
   ``skip`` — wait up to ``lost_target_wait_s`` for the target to come back by itself (someone
   walked through the line of sight; nothing is aimed or searched), then skip the configuration
   with the reason (``lost_target_wait_s: 0`` skips at once).

After a recovery the suspender waits ``settle_after_s`` (the resume settle delay) before the
run re-measures the configuration. Every step is reported through ``event(kind, **fields)``.

A device fault (``DeviceFaultSuspender``) — drives off, a session that dropped, a controller
that restarted, a stale joint state, a sensor that stopped answering or closed its connection —
suspends the run the same way, with one line, and waits for every device to be ready again
(``ready`` probes: the commander's ``ready()``, each sensor answering a read) within the plan's
allowance for the device that faulted (``robot_fault_wait_s`` / ``sensor_fault_wait_s``, counted
from the first fault at the configuration); once they are, and again after ``settle_after_s``,
the run goes back to the configuration's move. A fault that outlasts its allowance fails the
configuration; one that was over before the first probe is retried (the plan's ``retries``, and
for as long as the longest allowance lasts since the first fault at the configuration).

Units: mm (tracker frame), s (injected clock).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from calib.fit.registration import register_least_squares
from drivers.errors import DeviceTimeoutError, DriverError, TargetLostError

log = logging.getLogger(__name__)

POLICIES = ("wait", "reacquire", "ask", "skip")


@dataclass(frozen=True)
class Recovery:
    """What the run does after a suspension: ``action`` is "resume", "skip" or "abort"."""

    action: str
    reason: str
    seconds: float


class ReflectorPredictor:
    """Predicts where a sensor sees a marker at joint angles q, from the samples so far.

    chain: ``calib.robot.kinematics.Chain`` of the nominal model; marker_index: plan marker name →
    index into the chain's markers. initial: sensor name → (4, 4) base2sensor guess (or absent).
    ``add`` one measured (q (n,) rad, xyz (3,) mm sensor frame) per sample; from three
    non-collinear points on a least-squares registration replaces the guess.
    """

    def __init__(self, chain, marker_index: dict[str, int], initial: dict[str, np.ndarray] | None = None) -> None:
        self.chain = chain
        self.marker_index = dict(marker_index)
        self.initial = {k: np.asarray(v, dtype=float) for k, v in (initial or {}).items()}
        self._points: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {}
        self._fit: dict[str, np.ndarray] = {}

    def nominal_base(self, marker: str, q_rad) -> np.ndarray:
        """Nominal marker position (3,) mm in the robot base frame."""
        return self.chain.marker_positions(np.asarray(q_rad, dtype=float))[self.marker_index[marker]]

    def add(self, sensor: str, marker: str, q_rad, xyz_mm) -> None:
        if marker not in self.marker_index:
            return
        base, meas = self._points.setdefault(sensor, ([], []))
        base.append(self.nominal_base(marker, q_rad))
        meas.append(np.asarray(xyz_mm, dtype=float))
        if len(base) >= 3:
            try:
                self._fit[sensor] = register_least_squares(np.array(base), np.array(meas)).base2sensor
            except ValueError as exc:  # collinear so far: keep the previous estimate
                log.debug("registration of %s not yet determined: %s", sensor, exc)

    def base2sensor(self, sensor: str) -> tuple[np.ndarray | None, str]:
        """The current registration estimate and where it comes from."""
        if sensor in self._fit:
            return self._fit[sensor], f"least-squares registration of {len(self._points[sensor][0])} samples"
        if sensor in self.initial:
            return self.initial[sensor], "initial guess"
        return None, "no registration yet"

    def predict(self, sensor: str, marker: str, q_rad) -> tuple[np.ndarray | None, str]:
        """Predicted (3,) mm in the sensor frame (None when nothing is known) and its source."""
        t, source = self.base2sensor(sensor)
        if t is None or marker not in self.marker_index:
            return None, source
        p = self.nominal_base(marker, q_rad)
        return t[:3, :3] @ p + t[:3, 3], source


class LostTargetSuspender:
    """Suspend on a lost target; try to re-acquire; otherwise follow the plan's policy.

    policy: one of ``POLICIES``. wait_s: how long ``wait`` and ``skip`` wait (s, ≥ 0). search_radius_mm:
    spiral radius after an aim (> 0). settle_after_s: delay after a recovery (≥ 0).
    ask: callable(question) → "retry" | "skip" | "abort", or None when there is no TTY.
    """

    def __init__(
        self,
        policy: str,
        *,
        wait_s: float,
        predictor: ReflectorPredictor | None,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        event: Callable[..., None],
        search_radius_mm: float = 50.0,
        search_timeout_s: float = 30.0,
        settle_after_s: float = 0.1,
        ask: Optional[Callable[[str], str]] = None,
    ) -> None:
        if policy not in POLICIES:
            raise ValueError(f"on_lost_target must be one of {', '.join(POLICIES)}, got {policy!r}")
        for name, v, low_ok in (("wait_s", wait_s, True), ("search_radius_mm", search_radius_mm, False),
                                ("search_timeout_s", search_timeout_s, False), ("settle_after_s", settle_after_s, True)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and (v >= 0 if low_ok else v > 0)):
                raise ValueError(f"{name} must be a {'non-negative' if low_ok else 'positive'} number, got {v!r}")
        self.policy = policy
        self.wait_s = float(wait_s)
        self.predictor = predictor
        self.clock = clock
        self.sleep = sleep
        self.event = event
        self.search_radius_mm = float(search_radius_mm)
        self.search_timeout_s = float(search_timeout_s)
        self.settle_after_s = float(settle_after_s)
        self.ask = ask
        self._retried = False  # the last wait ended in a re-acquisition

    @staticmethod
    def can_reacquire(sensor) -> bool:
        return callable(getattr(sensor, "aim", None)) and callable(getattr(sensor, "search", None))

    def recover(self, sensor, marker: str, config_id: str, q_rad, reason: str) -> Recovery:
        """Handle one lost target at configuration ``config_id`` (robot standing at ``q_rad``)."""
        t0 = self.clock()
        self.event("suspended", config_id=config_id, cause="lost_target", sensor=sensor.name, marker=marker,
                   reason=reason, policy=self.policy)
        waits = f"; waiting up to {self.wait_s:g} s" if self.policy != "ask" and self.wait_s > 0 else ""
        log.warning("suspended at %s: %s (policy %s%s)", config_id, reason, self.policy, waits)
        retry = None
        if self.can_reacquire(sensor) and self.policy != "skip":
            radius = self.search_radius_mm * (2.0 if self.policy == "reacquire" else 1.0)
            if self._reacquire(sensor, marker, config_id, q_rad, radius):
                return self._resumed(config_id, sensor, "re-acquired", t0)
            if self.policy == "reacquire":  # a tracker never re-locks by itself: aim (and search) again
                deadline = self.clock() + self.wait_s  # while waiting, within the wait

                def retry() -> bool:
                    return self._reacquire(sensor, marker, config_id, q_rad, radius,
                                           timeout=max(deadline - self.clock(), 0.1))
        if self.policy in ("wait", "reacquire", "skip"):
            if self.wait_s > 0 and self._wait_visible(sensor, marker, config_id, retry):
                how = "re-acquired" if retry is not None and self._retried else "target visible again"
                return self._resumed(config_id, sensor, how, t0)
            return self._give_up("skip", config_id, sensor,
                                 f"{reason}; not back within {self.wait_s:g} s ({self.policy})", t0)
        if self.policy == "ask":
            if self.ask is None:
                return self._give_up("skip", config_id, sensor, f"{reason}; no terminal to ask (ask → skip)", t0)
            answer = self.ask(f"{sensor.name} lost {marker!r} at configuration {config_id}: {reason}. "
                              "retry, skip or abort?")
            if answer == "retry":
                return self._resumed(config_id, sensor, "operator retried", t0)
            if answer == "abort":
                return self._give_up("abort", config_id, sensor, f"{reason}; operator aborted", t0)
            return self._give_up("skip", config_id, sensor, f"{reason}; operator skipped", t0)
        raise AssertionError(f"policy {self.policy!r} not handled")  # pragma: no cover - checked in __init__

    # ------------------------------------------------------------------ steps
    def _reacquire(self, sensor, marker: str, config_id: str, q_rad, radius: float,
                   timeout: float | None = None) -> bool:
        """Aim at the predicted reflector, then spiral-search (for at most ``timeout`` s, default
        ``search_timeout_s``): a search that passed the reflector while the beam was blocked missed it."""
        timeout = self.search_timeout_s if timeout is None else min(timeout, self.search_timeout_s)
        aim_at, source = (None, "no predictor") if self.predictor is None else \
            self.predictor.predict(sensor.name, marker, q_rad)
        try:
            if aim_at is not None:
                try:
                    sensor.aim(aim_at, timeout=timeout)
                    self.event("aimed", config_id=config_id, sensor=sensor.name, locked=True,
                               aim_mm=np.round(aim_at, 3).tolist(), source=source)
                    return True
                except TargetLostError as exc:
                    self.event("aimed", config_id=config_id, sensor=sensor.name, locked=False,
                               aim_mm=np.round(aim_at, 3).tolist(), source=source, detail=str(exc))
            reply = sensor.search(radius, timeout)
            self.event("searched", config_id=config_id, sensor=sensor.name, found=True, radius_mm=radius,
                       elapsed_s=float(getattr(reply, "elapsed_s", math.nan)))
            return True
        except TargetLostError as exc:
            self.event("searched", config_id=config_id, sensor=sensor.name, found=False, radius_mm=radius,
                       detail=str(exc))
        except DeviceTimeoutError as exc:
            self.event("searched", config_id=config_id, sensor=sensor.name, found=False, radius_mm=radius,
                       detail=f"timeout: {exc}")
        return False

    def _wait_visible(self, sensor, marker: str, config_id: str, retry=None) -> bool:
        """Poll until ``marker`` is visible again, up to ``wait_s``; ``retry()`` (an aim at the
        prediction, then a search; True when it locked) is tried every ``wait_s / 5`` (at most 2 s) meanwhile: a
        beam that was blocked when the first aim went out stays lost until aimed again."""
        deadline = self.clock() + self.wait_s
        period = min(2.0, self.wait_s / 5)
        next_retry = self.clock() + period
        self._retried = False
        while self.clock() < deadline:
            try:
                for s in sensor.read(min(1.0, max(deadline - self.clock(), 1e-3))):
                    if s.marker == marker and s.visible:
                        return True
            except DeviceTimeoutError:
                pass
            if retry is not None and self.clock() >= next_retry:
                next_retry = self.clock() + period
                if retry():
                    self._retried = True
                    return True
            self.sleep(min(0.05, self.wait_s / 10))
        return False

    def _resumed(self, config_id: str, sensor, how: str, t0: float) -> Recovery:
        if self.settle_after_s:
            self.sleep(self.settle_after_s)
        dt = self.clock() - t0
        self.event("resumed", config_id=config_id, cause="lost_target", sensor=sensor.name, how=how,
                   seconds=round(dt, 4))
        log.info("resumed at %s: %s after %.2f s", config_id, how, dt)
        return Recovery("resume", how, dt)

    def _give_up(self, action: str, config_id: str, sensor, reason: str, t0: float) -> Recovery:
        dt = self.clock() - t0
        log.warning("%s at %s: %s", action, config_id, reason)
        return Recovery(action, reason, dt)


@dataclass(frozen=True)
class Probe:
    """One device's readiness check: ``check()`` returns when ready and raises DriverError saying
    why not; ``allowance_s``: how long the plan waits for this device (s ≥ 0, the run's clock)."""

    device: str
    check: Callable[[], object]
    allowance_s: float


class DeviceFaultSuspender:
    """Suspend on a device fault; wait for the devices to be ready; resume or fail.

    clock / sleep: the run's time (simulated seconds under ``--fake``); event: the run's event
    sink; settle_after_s: how long the devices must stay ready before the run moves again (≥ 0,
    they are checked again after it); poll_s: time between probes (> 0); stopping: True once
    the run is aborting (the wait ends at once with ``Recovery("abort", …)``).
    """

    def __init__(self, *, clock: Callable[[], float], sleep: Callable[[float], None], event: Callable[..., None],
                 settle_after_s: float = 0.2, poll_s: float = 0.05,
                 stopping: Callable[[], bool] = lambda: False) -> None:
        for name, v, low_ok in (("settle_after_s", settle_after_s, True), ("poll_s", poll_s, False)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and (v >= 0 if low_ok else v > 0)):
                raise ValueError(f"{name} must be a {'non-negative' if low_ok else 'positive'} number, got {v!r}")
        self.clock, self.sleep, self.event = clock, sleep, event
        self.settle_after_s = float(settle_after_s)
        self.poll_s = float(poll_s)
        self.stopping = stopping

    @staticmethod
    def not_ready(probes: list[Probe]) -> list[tuple[Probe, str]]:
        """The probes that fail now, each with its reason (prefixed with the device's name
        unless the driver's message already starts with it)."""
        out = []
        for p in probes:
            try:
                p.check()
            except DriverError as exc:
                text = str(exc)
                out.append((p, text if text.startswith(f"{p.device}:") else f"{p.device}: {text}"))
        return out

    def recover(self, config_id: str, reason: str, probes: list[Probe], since: float | None = None,
                on_suspend: Callable[[], None] | None = None) -> Recovery:
        """Handle one device fault (``reason``) at ``config_id``.

        since: clock time of the first fault at this configuration (None: now); each device's
        allowance runs from there. Returns ``Recovery("resume" | "retry" | "fail", reason, s)``:
        resume — a device was not ready and is again (verified twice, ``settle_after_s`` apart);
        retry — every device was ready at once (the fault had passed: the caller counts retries);
        fail — a device was still not ready when its allowance ended. ``on_suspend()`` is called
        once a device is found not ready, before the wait.
        """
        t0 = self.clock()
        since = t0 if since is None else since
        down = self.not_ready(probes)
        if not down:
            return Recovery("retry", f"{reason}; every device ready again at once", 0.0)
        allowance = max(p.allowance_s for p, _ in down)
        deadline = since + allowance
        names = ", ".join(dict.fromkeys(p.device for p, _ in down))
        if on_suspend is not None:
            on_suspend()
        self.event("suspended", config_id=config_id, cause="device_fault", device=names, reason=reason,
                   not_ready=[why for _, why in down], allowance_s=allowance)
        waiting_for = "; ".join(p.device if why[:25] in reason else why for p, why in down)  # no reason twice
        log.warning("suspended at %s: %s — waiting up to %.0f s for %s", config_id, reason,
                    max(deadline - t0, 0.0), waiting_for)
        last = down
        while True:
            while last and self.clock() < deadline:
                if self.stopping():
                    return Recovery("abort", f"{reason}; the run is stopping", self.clock() - t0)
                self.sleep(self.poll_s)
                last = self.not_ready(probes)
            if not last and self.settle_after_s:
                self.sleep(self.settle_after_s)  # ready for a while, then verified again
                last = self.not_ready(probes)
            if not last:
                dt = self.clock() - t0
                self.event("resumed", config_id=config_id, cause="device_fault", device=names,
                           how="devices ready", seconds=round(dt, 4))
                log.info("resumed at %s: %s ready again after %.2f s", config_id, names, dt)
                return Recovery("resume", "devices ready", dt)
            if self.clock() >= deadline:
                why = "; ".join(w for _, w in last)
                dt = self.clock() - t0
                return Recovery("fail", f"{reason}; still not ready after {self.clock() - since:.1f} s "
                                f"(allowed {allowance:g} s): {why}", dt)
