"""``JointStateTap``: the robot's measured joint state streamed into the run log and onto the bus."""

from __future__ import annotations

import logging
import threading
import time
from typing import Optional

import numpy as np

from drivers.errors import DriverError

log = logging.getLogger(__name__)


class JointStateTap:
    """Streams the commander's measured joint state into the log (``/joint_state``,
    ``RunLog.record_joint_state``; with a ``view``, the robot's frames on ``/tf``) and onto the bus
    (``remaster/<cell>/<commander>/joint_state``) every ``period_s`` wall seconds, on its own thread."""

    def __init__(self, commander, runlog, bus, cell: str, names, period_s: float = 0.04, view=None) -> None:
        self.commander, self.runlog, self.bus, self.cell = commander, runlog, bus, cell
        self.view = view  # acquire.record.foxglove_view.RobotView: /tf from each joint state
        self.names = list(names)
        self.period_s = period_s
        self.device = getattr(commander, "name", "robot")
        self._halt = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._key = None

    def start(self) -> "JointStateTap":
        if self.bus is not None:
            from acquire.live.bus import key

            same = getattr(self.bus, "cell", None) == self.cell
            self._key = self.bus.key(self.device, "joint_state") if same else key(self.cell, self.device, "joint_state")
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
