"""The FRI client's cyclic core: one monitoring message in, at most one command message out.

``FriClientSession`` holds no socket and no thread; ``FriCommander`` runs it in its real-time
thread, and the property tests feed it message streams directly. Everything on the path of
``on_monitoring`` is short and bounded: decode is done by the caller, a trajectory sample is a
few array operations, a stop plan (once per stop) about 0.1 ms.

What the client answers, per session state (the vendor SDK's ``ClientApplication`` /
``LBRClient`` do the same; see ``PROTOCOL.md``):

- IDLE: nothing.
- MONITORING_WAIT / MONITORING_READY: a command echoing the controller's *commanded* joint
  position (FRI 1.x), else the measured one (FRI 2.x sends no commanded position). Sunrise derives the
  connection quality from these answers, so they are needed to reach MONITORING_READY; the
  echo moves nothing.
- COMMANDING_WAIT: a command echoing the controller's interpolated (ipo) joint position.
- COMMANDING_ACTIVE: our joint-position command. On entry the held position is the ipo
  position (the measured one when there is none), checked against the measured position
  before any move; a move plans from the held position along a ``JointTrajectory``, one receive
  period per answer, each step bounded by the speed limit.

Answers go to every ``receiveMultiplier``-th message received, with our own counter and the
controller's counter reflected.

FRI versions: the layout is read off every message (``layout_of``: 1.x when the commanded
position is there, 2.x when not; 2.7 sends no end-of-message). ``expect_major`` (1 or 2, from
the commander's URL) makes a controller of the other major version refuse moves with a reason.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from drivers.errors import DeviceFaultError, DeviceTimeoutError, DriverError, LimitError, NotReadyError
from drivers.kuka_fri.messages import (
    COMMAND_MESSAGE_ID,
    CommandData,
    DriveState,
    FRICommandMessage,
    FRIMonitoringMessage,
    FriLayout,
    IOValue,
    MessageHeader,
    SafetyState,
    SessionState,
    layout_of,
)
from drivers.protocols import JointLimits, JointState
from drivers.trajectory import JointTrajectory, scaled_limits

N_JOINTS = 7


class MotionStoppedError(DriverError, RuntimeError):
    """A move was ended by ``stop()`` before it reached its target (the robot decelerated)."""


@dataclass(frozen=True)
class SessionSnapshot:
    """What the latest monitoring message said, as the commander checks it before a move.

    measured_rad / commanded_rad / ipo_rad: shape (n,), radians (None when absent).
    host_time: the client clock when it arrived; receive_period_s: send period × multiplier.
    io: the controller IOs the robot application shares (``MonitorData.io``).
    """

    session_state: SessionState
    quality: int
    number_of_joints: Optional[int]
    safety_state: Optional[int]
    drive_state: tuple[int, ...]
    measured_rad: Optional[np.ndarray]
    commanded_rad: Optional[np.ndarray]
    ipo_rad: Optional[np.ndarray]
    device_time: float
    host_time: float
    receive_period_s: Optional[float]
    sequence_counter: int
    layout: Optional[FriLayout] = None
    io: tuple[IOValue, ...] = ()


@dataclass
class Motion:
    """A trajectory being streamed: sampled at ``k * dt`` for the k-th answer since its start."""

    trajectory: JointTrajectory
    dt: float
    max_step_rad: np.ndarray  # shape (n,): per-answer bound, rad
    limits_scaled: tuple  # (v, a, j) of this motion, for the stop plan
    k: int = 0
    planned_s: float = 0.0  # duration of the move as planned (the trajectory becomes the stop's)
    stopping: bool = False
    stop_requested: bool = False
    done: threading.Event = field(default_factory=threading.Event)
    error: Optional[BaseException] = None


@dataclass
class SessionCounters:
    received: int = 0
    answered: int = 0
    step_clamps: int = 0
    restarts: int = 0
    faults: int = 0


class FriClientSession:
    """The per-message logic of the FRI client (thread-safe with one RT caller).

    limits: the model's joint limits, shape (7,) arrays.
    start_tolerance_rad: how far the measured position may be from the held one when a move
        starts, and from the ipo position when commanding begins.
    """

    def __init__(self, limits: JointLimits, *, start_tolerance_rad: float = math.radians(2.0),
                 expect_major: Optional[int] = None, logger: Optional[logging.Logger] = None) -> None:
        if limits.n_axes != N_JOINTS:
            raise ValueError(f"an LBR iiwa has {N_JOINTS} joints; the limits have {limits.n_axes}")
        if expect_major not in (None, 1, 2):
            raise ValueError(f"expect_major must be 1, 2 or None, got {expect_major!r}")
        self.expect_major = expect_major
        self.limits = limits
        self.start_tolerance_rad = float(start_tolerance_rad)
        self.log = logger or logging.getLogger("remaster.device.fri")
        self.counters = SessionCounters()
        self._lock = threading.Lock()
        self._snapshot: Optional[SessionSnapshot] = None
        self._client_seq = 0
        self._recv_count = 0
        self._last_seq: Optional[int] = None
        self._hold: Optional[np.ndarray] = None  # held command in COMMANDING_ACTIVE, rad
        self._last_sent: Optional[np.ndarray] = None
        self._motion: Optional[Motion] = None
        self._commanding_fault: Optional[str] = None

    # ------------------------------------------------------------------ user-thread side

    def snapshot(self) -> Optional[SessionSnapshot]:
        with self._lock:
            return self._snapshot

    @property
    def session_state(self) -> Optional[SessionState]:
        snap = self.snapshot()
        return None if snap is None else snap.session_state

    def held_position(self) -> Optional[np.ndarray]:
        with self._lock:
            return None if self._hold is None else self._hold.copy()

    def motion_active(self) -> bool:
        with self._lock:
            return self._motion is not None

    def begin_move(self, target_rad: np.ndarray, speed: float, name: str) -> Motion:
        """Check everything a move needs, plan it and hand it to the RT side.

        Raises LimitError (nothing moved) when the session, robot or state does not allow it.
        """
        snap = self.snapshot()
        with self._lock:
            hold = None if self._hold is None else self._hold.copy()
            busy = self._motion is not None
        motion = plan_move(snap, hold, busy, target_rad, speed, limits=self.limits,
                           start_tolerance_rad=self.start_tolerance_rad, expect_major=self.expect_major, name=name)
        self.adopt(motion, hold, name)
        return motion

    def adopt(self, motion: Motion, hold: np.ndarray, name: str) -> None:
        """Start streaming ``motion``, planned from the held position ``hold``, if nothing
        changed meanwhile. DeviceFaultError (transient, nothing moved) when the session left
        COMMANDING_ACTIVE or the held position changed; LimitError when a move is running."""
        with self._lock:
            if self._motion is not None:
                raise NotReadyError(f"{name}: a move is already in progress; stop() it first")
            # both transient (nothing moved): device faults the run waits out and retries
            if self._snapshot is None or self._snapshot.session_state != SessionState.COMMANDING_ACTIVE:
                raise DeviceFaultError(f"{name}: the session left COMMANDING_ACTIVE while planning")
            if self._hold is None or not np.array_equal(self._hold, hold):
                raise DeviceFaultError(f"{name}: the held position changed while planning; retry")
            self._motion = motion

    def request_stop(self) -> Optional[Motion]:
        """Ask the RT side to decelerate the current motion; returns it (None if idle)."""
        with self._lock:
            m = self._motion
            if m is not None:
                m.stop_requested = True
            return m

    def abort(self, error: BaseException) -> None:
        """End the current motion (if any) with ``error``; the held command stays."""
        with self._lock:
            if self._motion is not None:
                self._fail(error)

    def check_silence(self, now: float, timeout_s: float) -> None:
        """Called by the RT thread when no message came: fail the motion after ``timeout_s``."""
        with self._lock:
            snap, m = self._snapshot, self._motion
            if m is None or snap is None or now - snap.host_time <= timeout_s:
                return
            self._fail(
                DeviceTimeoutError(
                    f"controller stopped sending: no monitoring message for "
                    f"{(now - snap.host_time) * 1e3:.0f} ms (allowed {timeout_s * 1e3:.0f} ms)"
                )
            )

    # ------------------------------------------------------------------ RT side (lock inside)

    def _fail(self, error: BaseException) -> None:
        """End the current motion with ``error`` (lock held)."""
        m = self._motion
        self.counters.faults += 1
        self.log.error("FRI motion ended: %s", error)
        if m is not None:
            m.error = error
            self._motion = None
            m.done.set()

    def on_monitoring(self, msg: FRIMonitoringMessage, now: float) -> Optional[FRICommandMessage]:
        """Digest one monitoring message received at client time ``now``; return the answer
        to send (None: nothing to send this cycle)."""
        with self._lock:
            return self._on_monitoring(msg, now)

    def _on_monitoring(self, msg: FRIMonitoringMessage, now: float) -> Optional[FRICommandMessage]:
        self.counters.received += 1
        seq = msg.header.sequence_counter
        if seq == self._last_seq:
            return None  # a duplicate datagram: already answered
        if self._last_seq is not None and seq < self._last_seq and self._last_seq - seq < (1 << 31):
            self.counters.restarts += 1
            self.log.warning(
                "FRI: controller counter went back from %d to %d: controller restarted", self._last_seq, seq
            )
            self._recv_count = 0
            self._hold = None
            if self._motion is not None:
                self._fail(DeviceFaultError(f"controller restarted (counter {self._last_seq} -> {seq})"))
        self._last_seq = seq
        snap = _snapshot_of(msg, now)
        old = self._snapshot
        self._snapshot = snap
        state = snap.session_state
        if old is None or old.layout != snap.layout:
            self.log.info("FRI: controller speaks %s", snap.layout)
        if old is None or old.session_state != state:
            self.log.info(
                "FRI session %s -> %s (quality %s)",
                "-" if old is None else old.session_state.name, state.name, snap.quality,
            )
        if state != SessionState.COMMANDING_ACTIVE:
            self._hold = None
            if self._motion is not None:
                self._fail(
                    DeviceFaultError(
                        f"session left COMMANDING_ACTIVE (now {state.name}, quality "
                        f"{snap.quality}); the controller ended the motion"
                    )
                )
        elif self._motion is not None:
            fault = _robot_fault(snap)
            if fault:
                self._hold = None if snap.measured_rad is None else snap.measured_rad.copy()
                self._fail(DeviceFaultError(fault))
            elif snap.receive_period_s != self._motion.dt:
                self._fail(
                    DeviceFaultError(
                        f"receive period changed from {self._motion.dt} s to {snap.receive_period_s} s mid-motion"
                    )
                )
        if state == SessionState.IDLE:
            self._recv_count = 0
            return None
        self._recv_count += 1
        mult = msg.connection_info.receive_multiplier if msg.connection_info else None
        if self._recv_count < (mult or 1):
            return None
        self._recv_count = 0
        q = self._command_for(snap)
        if q is None:
            return None  # no position to echo: a broken controller message; say nothing
        out = FRICommandMessage(
            header=MessageHeader(COMMAND_MESSAGE_ID, self._client_seq, seq),
            command_data=CommandData(joint_position=tuple(q.tolist())),
        )
        self._client_seq = (self._client_seq + 1) & 0xFFFF_FFFF
        self.counters.answered += 1
        return out

    def _command_for(self, snap: SessionSnapshot) -> Optional[np.ndarray]:
        state = snap.session_state
        if state in (SessionState.MONITORING_WAIT, SessionState.MONITORING_READY):
            return snap.commanded_rad if snap.commanded_rad is not None else snap.measured_rad
        if state == SessionState.COMMANDING_WAIT:
            for q in (snap.ipo_rad, snap.commanded_rad, snap.measured_rad):
                if q is not None:
                    return q
            return None
        # COMMANDING_ACTIVE
        if self._hold is None:
            # Commands start from the interpolator's position when the controller reports it (as
            # the FRI SDK's LBRClient::command() does: setJointPosition(getIpoJointPosition()),
            # FRI 1.x C++ client, LBRClient.cpp): under joint impedance — someone holding the arm
            # — the measured position is off the set-point, and starting there would be a jump.
            start = snap.ipo_rad if snap.ipo_rad is not None and snap.ipo_rad.shape == (N_JOINTS,) else snap.measured_rad
            if start is None or start.shape != (N_JOINTS,):
                return None
            self._hold = start.copy()
            self._last_sent = self._hold.copy()
            return self._hold.copy()
        m = self._motion
        if m is not None:
            q = self._advance(m)
        else:
            q = self._hold
        if self._last_sent is not None and m is not None:
            step = q - self._last_sent
            clipped = np.clip(step, -m.max_step_rad, m.max_step_rad)
            if not np.array_equal(clipped, step):
                self.counters.step_clamps += 1
                q = self._last_sent + clipped
        self._last_sent = q.copy()
        if m is not None:
            self._hold = q.copy()
        return q

    def _advance(self, m: Motion) -> np.ndarray:
        """Next commanded position of motion ``m`` (lock held); finishes it at its end."""
        if m.stop_requested and not m.stopping:
            pos, vel, acc = m.trajectory.sample(m.k * m.dt)
            v, a, j = m.limits_scaled
            m.trajectory = JointTrajectory.stop(pos, vel, acc, v, a, j)
            m.k = 0
            m.stopping = True
        m.k += 1
        t = m.k * m.dt
        if t >= m.trajectory.duration:
            q = np.array(m.trajectory.end_rad, dtype=float)
            self._motion = None
            if m.stopping:
                m.error = MotionStoppedError("move stopped before its target; the robot decelerated and holds")
            m.done.set()
            return q
        return np.asarray(m.trajectory.sample(t)[0], dtype=float)


def plan_move(snap: Optional[SessionSnapshot], hold: Optional[np.ndarray], busy: bool, target_rad: np.ndarray,
              speed: float, *, limits: JointLimits, start_tolerance_rad: float, expect_major: Optional[int],
              name: str) -> Motion:
    """Check a move against the latest monitoring message ``snap`` and the held command
    ``hold`` (shape (7,), rad; None when nothing is held yet) and plan it; ``busy``: a move is
    running. LimitError (nothing moved) when it is not allowed. Pure: touches no session."""
    if snap is None:
        raise NotReadyError(f"{name}: no monitoring message received yet; is the controller sending?")
    check_ready(snap, limits, expect_major, name)
    if busy:
        raise NotReadyError(f"{name}: a move is already in progress; stop() it first")
    if hold is None:
        raise NotReadyError(f"{name}: no command held yet in COMMANDING_ACTIVE; wait one cycle")
    gap = float(np.max(np.abs(snap.measured_rad - hold)))
    if gap > start_tolerance_rad:
        raise NotReadyError(
            f"{name}: measured position is {math.degrees(gap):.3f}° from the commanded one "
            f"(allowed {math.degrees(start_tolerance_rad):.3f}°); wait until settled"
        )
    v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed)
    traj = JointTrajectory.plan(hold, target_rad, v, a, j)
    dt = snap.receive_period_s
    return Motion(traj, dt, v * dt * (1 + 1e-9) + 1e-12, (v, a, j), planned_s=traj.duration)


def check_ready(snap: SessionSnapshot, limits: JointLimits, expect_major: Optional[int], name: str) -> None:
    """Refuse a move (LimitError) the latest monitoring message ``snap`` does not allow: a
    NotReadyError for what may clear by itself (session not commanding, safety stop, drives off)."""
    if snap.session_state != SessionState.COMMANDING_ACTIVE:
        raise NotReadyError(
            f"{name}: session is {snap.session_state.name}; a move needs COMMANDING_ACTIVE "
            "(start the FRI joint-position overlay in the robot application)"
        )
    if snap.number_of_joints is not None and snap.number_of_joints != N_JOINTS:
        raise LimitError(f"{name}: controller reports {snap.number_of_joints} joints, expected {N_JOINTS}")
    if expect_major is not None and snap.layout is not None and snap.layout.major != expect_major:
        raise LimitError(
            f"{name}: the controller sends {snap.layout} messages but fri_version in the URL says "
            f"{expect_major}.x; fix the URL (or leave fri_version out to follow the controller)"
        )
    if snap.measured_rad is None:
        raise LimitError(f"{name}: controller sends no measured joint position")
    # FRI 2.x sends no commanded position: the held command is our own, so nothing is lost.
    for what, arr in (("measured", snap.measured_rad), ("commanded", snap.commanded_rad)):
        if arr is None:
            continue
        if arr.shape != (limits.n_axes,):
            raise LimitError(
                f"{name}: controller reports {arr.shape[0]} {what} joint values, "
                f"the robot model has {limits.n_axes}"
            )
        if not np.all(np.isfinite(arr)):
            raise LimitError(f"{name}: {what} joint position is not finite: {arr}")
    if snap.safety_state is not None and snap.safety_state != SafetyState.NORMAL_OPERATION:
        raise NotReadyError(f"{name}: safety state is {_name(SafetyState, snap.safety_state)}")
    bad = [i + 1 for i, d in enumerate(snap.drive_state) if d != DriveState.ACTIVE]
    if bad or len(snap.drive_state) not in (0, N_JOINTS):
        raise NotReadyError(f"{name}: drives not ACTIVE on axes {bad or snap.drive_state}")
    if snap.receive_period_s is None:
        raise LimitError(f"{name}: controller reports no sendPeriod/receiveMultiplier")


def _name(cls, value) -> str:
    try:
        return cls(value).name
    except ValueError:
        return str(value)


def _robot_fault(snap: SessionSnapshot) -> Optional[str]:
    if snap.safety_state is not None and snap.safety_state != SafetyState.NORMAL_OPERATION:
        return f"controller reports safety state {_name(SafetyState, snap.safety_state)}"
    bad = [i + 1 for i, d in enumerate(snap.drive_state) if d != DriveState.ACTIVE]
    if bad:
        states = {_name(DriveState, snap.drive_state[i - 1]) for i in bad}
        return f"drives not ACTIVE on axes {bad} ({', '.join(sorted(states))})"
    if snap.measured_rad is None or snap.measured_rad.shape != (N_JOINTS,):
        return "controller stopped reporting 7 measured joint positions"
    return None


def _arr(values) -> Optional[np.ndarray]:
    return None if values is None else np.asarray(values, dtype=float)


def _snapshot_of(msg: FRIMonitoringMessage, now: float) -> SessionSnapshot:
    ci, ri, md, ipo = msg.connection_info, msg.robot_info, msg.monitor_data, msg.ipo_data
    if ci is None:
        state = SessionState.IDLE  # no connection info: treat as a session not open
        quality, period = 0, None
    else:
        state = ci.session_state
        quality = int(ci.quality)
        period = (
            ci.send_period * (ci.receive_multiplier or 1) / 1000.0
            if ci.send_period
            else None
        )
    return SessionSnapshot(
        session_state=state,
        quality=quality,
        number_of_joints=None if ri is None else ri.number_of_joints,
        safety_state=None if ri is None else ri.safety_state,
        drive_state=() if ri is None else ri.drive_state,
        measured_rad=None if md is None else _arr(md.measured_joint_position),
        commanded_rad=None if md is None else _arr(md.commanded_joint_position),
        ipo_rad=None if ipo is None else _arr(ipo.joint_position),
        device_time=(md.timestamp.seconds if md is not None and md.timestamp is not None else math.nan),
        host_time=now,
        receive_period_s=period,
        sequence_counter=msg.header.sequence_counter,
        layout=layout_of(msg),
        io=() if md is None else md.io,
    )


def joint_state_of(snap: SessionSnapshot) -> JointState:
    """The ``JointState`` a snapshot reports (measured position, shape (n,), radians)."""
    return JointState(
        position_rad=snap.measured_rad.copy(),
        device_time=snap.device_time,
        host_time=snap.host_time,
        commanded_rad=None if snap.commanded_rad is None else snap.commanded_rad.copy(),
    )
