"""The FRI client's exchange loop, run in the exchange process (``drivers.exchange``).

One loop receives a monitoring message, decodes it, lets the ``FriClientSession`` (which lives
in this process) compute the answer, sends it, then publishes the session's snapshot, the held
command, the counters and the latency ring to the shared state, and reads the main process's
requests after the answer is out.

Requests (tuples over the request socket): ``("move", id, trajectory, dt, max_step_rad, limits_scaled,
planned_s, hold_rad)`` — a move the main process checked and planned from ``hold_rad``;
``("stop",)``; ``("close",)``.

Events: ``("done", id, error)`` when a move ends (error None, ``MotionStoppedError`` after a
stop, or the fault that ended it); ``("io_table", generation, ((name, type, direction), …))``
when the IOs the robot application shares change (their values go through the shared state,
tagged with that generation).

The main process dying (``ChildLink.parent_gone``): a running motion is decelerated within its
limits, the position is held for ``orphan_hold_s``, then the client stops answering, as the
SDK's client does when its application disconnects: Sunrise sees the answer windows go
missing, ends commanding and drops the session to monitoring; the process exits.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from typing import Callable, Optional

import numpy as np

from drivers.errors import DeviceFaultError, ProtocolError
from drivers.kuka_fri.messages import (
    MONITORING_MESSAGE_ID,
    IOValue,
    ConnectionInfo,
    ConnectionQuality,
    DriveState,
    FriLayout,
    FRIMonitoringMessage,
    IpoData,
    MessageHeader,
    MonitorData,
    RobotInfo,
    SafetyState,
    SessionState,
    TimeStamp,
    decode_monitoring,
    encode_command,
    encode_monitoring,
)
from drivers.kuka_fri.session import FriClientSession, Motion, SessionCounters, SessionSnapshot
from drivers.protocols import JointLimits
from drivers.kuka_fri.framing import frame, unframe
from drivers.udp import enable_rx_timestamps, recv_stamped

#: Most joint values a snapshot field carries (a controller may send a wrong count: kept to refuse).
MAX_VALUES = 16
#: Most controller IOs the shared state carries (an application shares a handful).
MAX_IO = 32
COUNTERS = ("received", "answered", "step_clamps", "restarts", "faults")
LINK = ("count", "late", "gaps", "malformed", "foreign")
SNAP = ("has_snap", "session_state", "quality", "n_joints", "safety", "n_drives", "device_time", "host_time",
        "period", "seq", "layout_major", "layout_eom", "has_hold", "busy", "n_io", "io_gen")
_ARRAYS = ("measured", "commanded", "ipo")


def layout(window: int) -> dict[str, tuple]:
    """Fields of the shared state: the latest snapshot (NaN for an absent value; ``n_<array>``
    = -1 when the array is absent), the held command (rad), session and link counters, and the
    rings of answer latency ``lat`` and arrival time ``rx`` (client clock, s)."""
    out = {k: () for k in SNAP + COUNTERS + LINK}
    out.update(drives=(MAX_VALUES,), hold=(7,), lat=(window,), rx=(window,), io_digital=(MAX_IO,), io_analog=(MAX_IO,))
    for a in _ARRAYS:
        out[a] = (MAX_VALUES,)
        out["n_" + a] = ()
    return out


def layout_arrays() -> tuple[str, ...]:
    """The array fields ``snapshot_from`` needs besides ``SNAP``."""
    return ("drives", "io_digital", "io_analog") + _ARRAYS + tuple("n_" + a for a in _ARRAYS)


def snapshot_from(st: dict, io_tables: Optional[dict] = None) -> Optional[SessionSnapshot]:
    """The ``SessionSnapshot`` a copy of the shared state holds (None before the first message).
    ``io_tables``: generation → ((name, type, direction), …) from the ``io_table`` events; the
    IO values are left out (``io == ()``) until the table of their generation has arrived."""
    if not st["has_snap"][0]:
        return None

    def opt(key):
        v = float(st[key][0])
        return None if math.isnan(v) else v

    def arr(key):
        n = int(st["n_" + key][0])
        return None if n < 0 else st[key][:n].copy()

    major = int(st["layout_major"][0])
    n_joints, safety = opt("n_joints"), opt("safety")
    return SessionSnapshot(
        session_state=SessionState(int(st["session_state"][0])),
        quality=int(st["quality"][0]),
        number_of_joints=None if n_joints is None else int(n_joints),
        safety_state=None if safety is None else int(safety),
        drive_state=tuple(int(x) for x in st["drives"][: int(st["n_drives"][0])]),
        measured_rad=arr("measured"),
        commanded_rad=arr("commanded"),
        ipo_rad=arr("ipo"),
        device_time=float(st["device_time"][0]),
        host_time=float(st["host_time"][0]),
        receive_period_s=opt("period"),
        sequence_counter=int(st["seq"][0]),
        layout=None if major == 0 else FriLayout(major, bool(st["layout_eom"][0])),
        io=_io_from(st, io_tables or {}),
    )


def io_pending(st: dict, io_tables: dict) -> bool:
    """The shared state holds IO values whose table (names) has not arrived yet."""
    return bool(st["has_snap"][0]) and int(st["n_io"][0]) > 0 and int(st["io_gen"][0]) not in io_tables


def _io_from(st: dict, io_tables: dict) -> tuple[IOValue, ...]:
    table = io_tables.get(int(st["io_gen"][0]))
    n = int(st["n_io"][0])
    if table is None or len(table) != n:
        return ()
    out = []
    for (name, kind, direction), d, a in zip(table, st["io_digital"][:n], st["io_analog"][:n]):
        out.append(IOValue(name, kind, direction, None if math.isnan(d) else int(d), None if math.isnan(a) else float(a)))
    return tuple(out)


def counters_from(st: dict) -> SessionCounters:
    return SessionCounters(**{k: int(st[k][0]) for k in COUNTERS})


def _warm_up_message(seq: int, q: np.ndarray) -> FRIMonitoringMessage:
    """A COMMANDING_ACTIVE monitoring message at joint position ``q`` (rad), 5 ms period."""
    values = tuple(float(x) for x in q)
    return FRIMonitoringMessage(
        MessageHeader(MONITORING_MESSAGE_ID, seq, max(seq - 1, 0)),
        RobotInfo(7, SafetyState.NORMAL_OPERATION, (DriveState.ACTIVE,) * 7, 2, 0),
        MonitorData(values, (0.0,) * 7, values, timestamp=TimeStamp.from_seconds(seq * 0.005)),
        ConnectionInfo(SessionState.COMMANDING_ACTIVE, ConnectionQuality.EXCELLENT, 5, 1),
        IpoData(values, 1, 1),
    )


class _LinkLogHandler(logging.Handler):
    """Hands the session's log records to the main process (its device logger logs them)."""

    def __init__(self, link) -> None:
        super().__init__()
        self.link = link

    def emit(self, record: logging.LogRecord) -> None:
        self.link.log(record.levelno, "%s", record.getMessage())


class FriLoop:
    """The exchange loop (child side). Options: see ``FriCommander``."""

    def __init__(self, link, sock: socket.socket, state, *, limits: JointLimits, start_tolerance_rad: float,
                 expect_major: Optional[int], controller_host: Optional[str], receive_timeout_s: float,
                 clock: Callable[[], float], window: int, orphan_hold_s: float = 0.5) -> None:
        self.link, self.sock, self.state = link, sock, state
        self.name = link.name
        log = logging.getLogger(f"remaster.device.{self.name}.exchange")
        log.propagate = False
        log.setLevel(logging.INFO)
        log.addHandler(_LinkLogHandler(link))
        self.log = log
        self.session = FriClientSession(limits, start_tolerance_rad=start_tolerance_rad,
                                        expect_major=expect_major, logger=log)
        self.controller_host = controller_host
        self.receive_timeout_s = float(receive_timeout_s)
        self.clock = clock
        self.W = int(window)
        self.orphan_hold_s = float(orphan_hold_s)
        self._tracked: Optional[tuple[int, Motion]] = None
        self._seen_seq: Optional[int] = None
        self._link_counts = dict.fromkeys(LINK, 0)
        self._closing = False
        self._orphan_since: Optional[float] = None
        self._held_since: Optional[float] = None
        self._last_warning = -math.inf
        self._stamped = False
        self._io_key: tuple = ()
        self._io_gen = 0

    def warm_up(self) -> None:
        """Run every code path of a cycle, a move and a stop once on a throw-away session (wire
        round trip included), so first-call costs happen before the first real message."""
        quiet = logging.getLogger(f"remaster.device.{self.name}.warm_up")
        quiet.propagate = False
        quiet.addHandler(logging.NullHandler())
        lim = self.session.limits
        dry = FriClientSession(lim, expect_major=None, logger=quiet)
        q = (np.asarray(lim.lower_rad) + np.asarray(lim.upper_rad)) / 2
        for seq in range(12):
            data = frame(encode_monitoring(_warm_up_message(seq, q)))
            reply = dry.on_monitoring(decode_monitoring(unframe(data)[0]), seq * 0.005)
            if seq == 2:
                dry.begin_move(q + 0.01, 1.0, "warm-up")
            if seq == 6:
                dry.request_stop()
            if reply is not None:
                frame(encode_command(reply))
                q = np.asarray(reply.command_data.joint_position)
        dry.check_silence(1.0, 0.1)
        self._publish()

    # -- requests and events ------------------------------------------------------------------

    def _handle_requests(self) -> None:
        for req in self.link.requests():
            kind = req[0]
            if kind == "move" and self._orphan_since is not None:
                self.link.send("done", req[1], DeviceFaultError(f"{self.name}: the FRI exchange is ending; not moving"))
            elif kind == "move":
                _, id_, traj, dt, max_step, limits_scaled, planned_s, hold = req
                motion = Motion(traj, dt, max_step, limits_scaled, planned_s=planned_s)
                try:
                    self.session.adopt(motion, hold, self.name)
                except Exception as exc:  # noqa: BLE001 - LimitError / DeviceFaultError go back as they are
                    self.link.send("done", id_, exc)
                    continue
                self._tracked = (id_, motion)
            elif kind == "stop":
                self.session.request_stop()
            elif kind == "close":
                self._closing = True
        if self._orphan_since is None and self.link.parent_gone():
            self._orphan_since = time.monotonic()
            self.log.warning("%s: on its own (the main process is gone or SIGTERM came); stopping the robot, "
                             "then ending the FRI exchange", self.name)
            self.session.request_stop()

    def _report_done(self) -> None:
        """Send ``done`` for the tracked motion once the session ended it (after publishing)."""
        t = self._tracked
        if t is not None and t[1].done.is_set():
            self._tracked = None
            self.link.send("done", t[0], t[1].error)

    def _warn(self, text: str) -> None:
        """Rate-limited warning: at most one per second from the exchange loop."""
        t = time.monotonic()
        if t - self._last_warning >= 1.0:
            self._last_warning = t
            self.log.warning("%s", text)

    # -- the loop -----------------------------------------------------------------------------

    def run(self) -> None:
        self._drain()
        self.sock.settimeout(min(0.02, self.receive_timeout_s / 2))
        self._stamped = enable_rx_timestamps(self.sock)
        while not self._closing:
            if self._orphan_since is not None and self._orphan_should_exit():
                return
            self._cycle()
            self._publish()
            self._report_done()
            self._handle_requests()

    def _drain(self) -> None:
        """Discard messages queued before the loop ran (while this process started): their
        answer windows are over; the next message starts the exchange."""
        self.sock.setblocking(False)
        try:
            while True:
                self.sock.recvfrom(4096)
        except (BlockingIOError, InterruptedError):
            pass

    def _orphan_should_exit(self) -> bool:
        """Orphaned: at rest and held for ``orphan_hold_s`` (or no controller to stop): exit."""
        now = time.monotonic()
        if self.session.motion_active():
            return now - self._orphan_since > 30.0  # a stop needing that long: the link is gone
        if self._held_since is None:
            self._held_since = now
        return now - self._held_since >= self.orphan_hold_s

    def _cycle(self) -> None:
        sock, session = self.sock, self.session
        try:
            data, addr, arrived = recv_stamped(sock, 4096, self._stamped)
        except socket.timeout:
            session.check_silence(self.clock(), self.receive_timeout_s)
            return
        except OSError as exc:
            if not self._closing:
                self._warn(f"receive failed: {exc}")
            return
        now = self.clock()
        if self.controller_host is not None and addr[0] != self.controller_host:
            self._link_counts["foreign"] += 1
            session.check_silence(now, self.receive_timeout_s)
            return
        try:
            body, framed = unframe(data)  # FRI 2.7 frames every datagram; 1.x and 2.5 do not
            msg = decode_monitoring(body)
        except ProtocolError as exc:
            self._link_counts["malformed"] += 1
            self._warn(f"malformed monitoring message ({len(data)} bytes) from {addr[0]}:{addr[1]}: {exc}")
            session.check_silence(now, self.receive_timeout_s)
            return
        self._count_cycle(msg.header.sequence_counter, now)
        try:
            reply = session.on_monitoring(msg, now)
        except Exception as exc:  # noqa: BLE001 - the exchange must survive a bug
            self.log.exception("FRI cycle failed; ending any motion")
            session.abort(DeviceFaultError(f"{self.name}: FRI cycle failed: {exc!r}"))
            return
        if reply is not None:
            try:
                out = encode_command(reply)
                sock.sendto(frame(out) if framed else out, addr)  # answer as the controller speaks
            except OSError as exc:
                self._warn(f"send to {addr[0]}:{addr[1]} failed: {exc}")
            self._count_answer(arrived)

    def _count_cycle(self, seq: int, now: float) -> None:
        prev, self._seen_seq = self._seen_seq, seq
        c = self._link_counts
        if prev is not None and seq > prev + 1 and seq - prev < (1 << 31):
            c["gaps"] += seq - prev - 1
        i = c["count"] % self.W
        self.state["rx"][i] = now  # (ring slots are only read up to ``count``, published after)
        self.state["lat"][i] = 0.0
        c["count"] += 1

    def _count_answer(self, arrived: float) -> None:
        """The answer to the message that reached the host at wall time ``arrived`` (kernel
        stamp) is sent: its latency, in wall seconds, includes this process's wake-up. Late:
        above the receive period (client clock; a faster-than-real-time clock makes it lenient)."""
        latency = time.time() - arrived
        c = self._link_counts
        self.state["lat"][(c["count"] - 1) % self.W] = latency
        snap = self.session.snapshot()
        if snap is not None and snap.receive_period_s and latency > snap.receive_period_s:
            c["late"] += 1

    def _publish(self) -> None:
        session = self.session
        snap = session.snapshot()
        hold = session.held_position()
        st = self.state
        with st.write():
            for k, v in self._link_counts.items():
                st[k][0] = v
            for k in COUNTERS:
                st[k][0] = getattr(session.counters, k)
            st["busy"][0] = session.motion_active()
            st["has_hold"][0] = hold is not None
            if hold is not None:
                st["hold"][:] = hold
            if snap is None:
                return
            st["has_snap"][0] = 1
            st["session_state"][0] = int(snap.session_state)
            st["quality"][0] = snap.quality
            st["n_joints"][0] = math.nan if snap.number_of_joints is None else snap.number_of_joints
            st["safety"][0] = math.nan if snap.safety_state is None else snap.safety_state
            drives = snap.drive_state[:MAX_VALUES]
            st["n_drives"][0] = len(drives)
            st["drives"][: len(drives)] = drives
            for a in _ARRAYS:
                v = getattr(snap, a + "_rad")
                if v is None:
                    st["n_" + a][0] = -1
                else:
                    v = v[:MAX_VALUES]
                    st["n_" + a][0] = len(v)
                    st[a][: len(v)] = v
            st["device_time"][0] = snap.device_time
            st["host_time"][0] = snap.host_time
            st["period"][0] = math.nan if snap.receive_period_s is None else snap.receive_period_s
            st["seq"][0] = snap.sequence_counter
            st["layout_major"][0] = 0 if snap.layout is None else snap.layout.major
            st["layout_eom"][0] = bool(snap.layout is not None and snap.layout.end_of_message)
            self._publish_io(snap.io[:MAX_IO])

    def _publish_io(self, ios) -> None:
        """IO values into the shared state (inside ``_publish``'s write); a changed set of IOs
        goes to the main process as a new ``io_table`` first (rare: the application's config)."""
        st = self.state
        if self._io_table_changed(ios):
            self._io_key = tuple((io.name, int(io.type), int(io.direction)) for io in ios)
            self._io_gen += 1
            self.link.send("io_table", self._io_gen, self._io_key)
        st["io_gen"][0] = self._io_gen
        st["n_io"][0] = len(ios)
        for i, io in enumerate(ios):
            st["io_digital"][i] = math.nan if io.digital_value is None else io.digital_value
            st["io_analog"][i] = math.nan if io.analog_value is None else io.analog_value

    def _io_table_changed(self, ios) -> bool:
        """Whether the IOs' names, types or directions differ from the last table sent — compared
        in place, without building a new table every cycle (the hot path)."""
        key = self._io_key
        if len(ios) != len(key):
            return True
        for io, (name, io_type, direction) in zip(ios, key):
            if io.name != name or io.type != io_type or io.direction != direction:
                return True
        return False
