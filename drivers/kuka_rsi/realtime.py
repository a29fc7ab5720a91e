"""The RSI answering loop, run in the exchange process (``drivers.exchange``).

One loop does only this: receive a ``<Rob>`` packet (with the kernel's arrival stamp), parse
it (regex), take the next row of the precomputed correction table (or hold), check the row
against the per-cycle limits (position, velocity and acceleration per cycle; a violating row
is clamped and the motion stopped), format (``%`` template), send to the packet's source.
Requests from the main process are read after the answer is out.

Requests (tuples over the request socket): ``("move", id, rows_deg, traj, session)`` — rows of shape
(m, n) in degrees, the AK values of the next m cycles, ``traj`` sampled at ``(k + 1) · dt`` for
row k (to plan a stop from the current state); ``("stop",)``; ``("end_session",)`` (the Stop
flag goes out with the next answer); ``("close",)``.

Events: ``("first",)`` with the first packet, ``("axis_error", text)``, ``("done", id, error)``
(error None or a ``DriverError``), ``("fault", error)`` for a fault no motion carried,
``("stop_sent",)``.

The main process dying (``ChildLink.parent_gone``): a running motion becomes a jerk-limited
stop within the limits, the position is held for ``orphan_hold_s``, then the Stop flag the
shipped controller configuration maps (``drivers/kuka_rsi/controller/``) ends the RSI program,
and the process exits.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from drivers.errors import (
    ConnectionLostError,
    DeviceFaultError,
    DeviceTimeoutError,
    DriverError,
    LimitError,
    ProtocolError,
)
from drivers.kuka_rsi.codec import SenFormatter, parse_rob
from drivers.udp import enable_rx_timestamps, recv_stamped
from drivers.trajectory import JointTrajectory

#: Relative slack of the per-cycle guard: a row may exceed a limit by this fraction only
#: (covers the rounding of the 7-decimal wire format, never a real excess).
GUARD_SLACK = 1e-6

#: Scalars of the shared state (see ``layout``).
SCALARS = ("t_rx", "ipoc", "has_state", "count", "late", "gaps", "malformed", "restarts", "clamps",
           "delay", "has_delay", "session", "session_ended", "busy")


def layout(n_axes: int, window: int) -> dict[str, tuple]:
    """Fields of the shared state: the latest packet (host time ``t_rx`` from
    ``time.monotonic``, ``actual``/``cmd``/``ref`` shape (n,), degrees), counters, and the rings
    of answer latency ``lat`` (s) and arrival time ``rx`` (wall s) of the last ``window`` cycles."""
    out = {k: () for k in SCALARS}
    out.update(actual=(n_axes,), cmd=(n_axes,), ref=(n_axes,), lat=(window,), rx=(window,))
    return out


class _Motion:
    __slots__ = ("id", "rows_deg", "k", "traj", "session", "is_stop", "error")

    def __init__(self, id_, rows_deg, traj, session, is_stop=False) -> None:
        self.id = id_
        self.rows_deg = rows_deg
        self.k = 0
        self.traj = traj
        self.session = session
        self.is_stop = is_stop
        self.error: DriverError | None = None


class RsiLoop:
    """The exchange loop (child side). Options: see ``RsiCommander``; limits in radians."""

    def __init__(self, link, sock, state, *, n_axes, dt, timeout_cycles, delay_limit, delay_window, sen_type,
                 lower_rad, upper_rad, max_velocity_rad_s, max_acceleration_rad_s2, max_jerk_rad_s3,
                 window, orphan_hold_s=0.5) -> None:
        self.link, self.sock, self.state = link, sock, state
        self.name = link.name
        self.n = n_axes
        self.dt = dt
        self.timeout_cycles = timeout_cycles
        self.delay_limit, self.delay_window = delay_limit, delay_window
        self.sen_type = sen_type
        v = np.asarray(max_velocity_rad_s, dtype=float)
        a = np.asarray(max_acceleration_rad_s2, dtype=float)
        self.vmax, self.amax = v, a
        self.jmax = np.maximum(np.asarray(max_jerk_rad_s3, dtype=float), 1e-9)
        self._g_step = np.degrees(v) * dt * (1 + GUARD_SLACK) + 1e-7
        self._g_acc = np.degrees(a) * dt**2 * (1 + GUARD_SLACK) + 2e-7
        self._lo_deg = np.degrees(np.asarray(lower_rad, dtype=float))
        self._hi_deg = np.degrees(np.asarray(upper_rad, dtype=float))
        self.W = int(window)
        self.orphan_hold_s = float(orphan_hold_s)
        self._hold = np.zeros(n_axes)
        self._prev = np.zeros(n_axes)
        self._prev2 = np.zeros(n_axes)
        self._ref_deg: np.ndarray | None = None
        self._session = 0
        self._formatter: SenFormatter | None = None
        self._motion: _Motion | None = None
        self._pending: _Motion | None = None
        self._stop_req = False
        self._stop_flag = False
        self._session_ended = False
        self._fault_open = False  # a fault was recorded and not yet carried to the parent
        self._delay_ring = np.zeros(delay_window, dtype=np.int64)
        self._delay_n = 0
        self._last_delay: int | None = None
        self._ipoc_step: int | None = None
        self._counts = dict.fromkeys(("count", "late", "gaps", "malformed", "restarts", "clamps"), 0)
        self._first_sent = False
        self._axis_error_sent = False
        self._closing = False
        self._orphan_since: float | None = None
        self._held_since: float | None = None

    # -- set-up -------------------------------------------------------------------------------

    def warm_up(self) -> None:
        """Run every code path of a cycle and of a stop once, so first-call costs happen now."""
        n = self.n
        f = SenFormatter(min(n, 6), max(n - 6, 0), self.sen_type)
        parse_rob(b'<Rob Type="KUKA"><AIPos A1="0.0"/><ASPos A1="0.0"/><Delay D="0"/><IPOC>1</IPOC></Rob>')
        f.format(np.zeros(n), False, 1)
        lo = np.radians(self._lo_deg)
        stop = JointTrajectory.stop(lo, self.vmax * 0.5, self.amax * 0.0, self.vmax, self.amax, self.jmax)
        stop.sample(self.dt * np.arange(1, 4))
        self._publish(0.0, 0, (0.0,) * n, np.zeros(n), has_state=False)

    def _drain(self) -> None:
        """Discard packets queued before the loop ran: their cycle is over."""
        sock = self.sock
        sock.setblocking(False)
        try:
            while True:
                sock.recvfrom(4096)
        except (BlockingIOError, InterruptedError):
            pass
        finally:
            sock.settimeout(self.dt)

    # -- requests and events ------------------------------------------------------------------

    def _handle_requests(self) -> None:
        for req in self.link.requests():
            kind = req[0]
            if kind == "move" and self._orphan_since is not None:
                self.link.send("done", req[1], DeviceFaultError(f"{self.name}: the RSI exchange is ending; not moving"))
            elif kind == "move":
                _, id_, rows, traj, session = req
                self._pending = _Motion(id_, rows, traj, session)
                self._fault_open = False  # the parent raised it before planning this move
            elif kind == "stop":
                p, self._pending = self._pending, None
                if p is not None:
                    self._send_done(p.id, None)  # not started: ends without moving
                if self._motion is not None:
                    self._stop_req = True
            elif kind == "end_session":
                self._stop_flag = True
            elif kind == "close":
                self._closing = True
        if self._orphan_since is None and self.link.parent_gone():
            self._orphan_since = time.monotonic()
            self.link.log(logging.WARNING, "%s: on its own (the main process is gone or SIGTERM came); "
                          "stopping the robot and ending RSI", self.name)
            p, self._pending = self._pending, None
            if self._motion is not None:
                self._stop_req = True

    def _abort(self, error: DriverError) -> None:
        """Record a fault; a running motion ends with it (its waiter is told now) and becomes a stop."""
        carried = False
        m = self._motion
        if m is not None and m.error is None:
            m.error = error
            self._stop_req = True
            self._send_done(m.id, error)
            carried = True
        p, self._pending = self._pending, None
        if p is not None:
            self._send_done(p.id, error)
            carried = True
        if not carried and not self._fault_open:
            self._fault_open = True
            self.link.send("fault", error)

    def _finish(self, m: _Motion) -> None:
        self._motion = None
        if m.is_stop:
            self._stop_req = False
        if m.error is None:  # an errored motion was reported when the error happened
            self._send_done(m.id, None)

    def _send_done(self, motion_id: int, error) -> None:
        """Tell the parent a motion is over, after the shared ``busy`` flag says so (a move
        the parent starts right after must not see the old motion)."""
        st = self.state
        with st.write():
            st["busy"][0] = self._motion is not None or self._pending is not None
        self.link.send("done", motion_id, error)

    # -- the loop -----------------------------------------------------------------------------

    def run(self) -> None:
        self._drain()
        try:
            self._loop()
        except OSError as exc:
            if not self._closing:
                self.link.log(logging.ERROR, "%s: RSI socket failed: %s", self.name, exc)
                self._abort(ConnectionLostError(f"{self.name}: RSI socket failed: {exc}"))

    def _orphan_done(self, now: float) -> bool:
        """Orphaned: True when it is time to exit (Stop flag sent, or no controller to send it to)."""
        if self._session_ended:
            return True
        return now - self._orphan_since > self.orphan_hold_s + self.timeout_cycles * self.dt + 1.0

    def _loop(self) -> None:  # noqa: C901 - one flat real-time loop on purpose
        sock = self.sock
        stamped = enable_rx_timestamps(sock)
        silence_limit = self.timeout_cycles * self.dt
        last_rx = time.monotonic()
        last_ipoc = -1
        step_deg, acc_deg = self._g_step, self._g_acc
        W = self.W
        lat_ring, rx_ring = self.state["lat"], self.state["rx"]
        while not self._closing:
            if self._orphan_since is not None and self._orphan_done(time.monotonic()):
                return
            try:
                data, addr, arrived = recv_stamped(sock, 4096, stamped)
            except TimeoutError:
                if self._ref_deg is not None and time.monotonic() - last_rx > silence_limit:
                    if self._motion is not None or self._pending is not None:
                        self._abort(
                            DeviceTimeoutError(
                                f"{self.name}: no packet from the controller for "
                                f"{(time.monotonic() - last_rx) * 1e3:.0f} ms (limit {self.timeout_cycles} "
                                f"cycles); the controller stopped RSI (last Delay {self._last_delay})"
                            )
                        )
                self._handle_requests()
                continue
            t_rx = time.monotonic()
            try:
                rob = parse_rob(data)
            except ProtocolError:
                self._counts["malformed"] += 1
                self._handle_requests()
                continue
            actual = rob.axis_actual_deg + rob.external_actual_deg
            ipoc = rob.ipoc
            # -- session bookkeeping: first packet, restart, gaps
            restarted = False
            if self._ref_deg is None:
                if not self._start_session(rob, actual):
                    self._handle_requests()
                    continue
            else:
                new_ref = rob.axis_setpoint_deg
                if ipoc == last_ipoc and len(actual) == len(self._ref_deg):
                    # the controller repeated a packet (it got no answer): same answer again
                    sock.sendto(self._formatter.format(self._prev, self._stop_flag, ipoc), addr)
                    self._publish(t_rx, ipoc, actual, self._prev)
                    continue
                if (
                    ipoc < last_ipoc
                    or len(actual) != len(self._ref_deg)
                    or (new_ref is not None and any(abs(x - y) > 1e-6 for x, y in zip(new_ref, self._ref_deg)))
                ):
                    restarted = True
            if restarted:
                self._counts["restarts"] += 1
                m = self._motion
                if m is not None:
                    self._motion = None
                    if m.error is None:
                        m.error = DeviceFaultError(
                            f"{self.name}: the controller restarted RSI during a motion (IPOC {last_ipoc} → {ipoc}); "
                            "motion abandoned, corrections reset"
                        )
                        self._send_done(m.id, m.error)
                    self._stop_req = False
                self._ipoc_step = None
                if not self._start_session(rob, actual):
                    self._abort(LimitError(self._axis_error_text(rob)))
                    self._handle_requests()
                    continue
            elif last_ipoc >= 0:
                diff = ipoc - last_ipoc
                if self._ipoc_step is None or diff < self._ipoc_step:
                    self._ipoc_step = diff
                elif diff > self._ipoc_step:
                    self._counts["gaps"] += diff // self._ipoc_step - 1
            last_ipoc = ipoc
            last_rx = t_rx
            # -- controller-reported lateness
            if rob.delay is not None:
                ring = self._delay_ring
                i = self._delay_n % self.delay_window
                # growth within the window; the count at the session's first packet is the
                # baseline (lateness from before we listened is not ours)
                past = ring[i] if self._delay_n >= self.delay_window else (ring[0] if self._delay_n else rob.delay)
                ring[i] = rob.delay
                self._delay_n += 1
                self._last_delay = rob.delay
                if rob.delay - past > self.delay_limit and not self._fault_open and self._motion_error() is None:
                    self._abort(
                        DeviceFaultError(
                            f"{self.name}: the controller counted {rob.delay - past} late answers in the last "
                            f"{min(self._delay_n, self.delay_window)} cycles (Delay D={rob.delay}, "
                            f"limit {self.delay_limit}); motion stopped"
                        )
                    )
            # -- next command
            m = self._motion
            if m is None and self._pending is not None:
                p, self._pending = self._pending, None
                if p.session != self._session:
                    self._send_done(p.id, DeviceFaultError(
                        f"{self.name}: RSI restarted before the motion began; re-plan"))
                elif not self._stop_req:
                    self._motion = m = p
                else:
                    self._send_done(p.id, None)  # a stop came first: ends without moving
            if m is not None and self._stop_req and not m.is_stop:
                m = self._plan_stop(m)
            if self._stop_req and m is None:
                self._stop_req = False
            if m is not None:
                cmd = m.rows_deg[m.k]
                m.k += 1
            else:
                cmd = self._hold
            # -- per-cycle guard: position, velocity and acceleration per cycle
            prev = self._prev
            d1 = cmd - prev
            d2 = d1 - (prev - self._prev2)
            pos = self._ref_deg + cmd
            if (np.abs(d1) > step_deg).any() or (np.abs(d2) > acc_deg).any() or (pos < self._lo_deg).any() or (
                pos > self._hi_deg
            ).any():
                cmd = self._clamp(cmd)
                self._counts["clamps"] += 1
                if m is not None and m.error is None:
                    m.traj = None  # the stream left the plan: stop from what was actually sent
                    self._abort(
                        LimitError(f"{self.name}: a command exceeded the per-cycle limits; clamped and stopped")
                    )
            # the Stop flag goes out only with the robot at rest
            stop_flag = self._stop_flag and m is None
            reply = self._formatter.format(cmd, stop_flag, ipoc)
            sock.sendto(reply, addr)
            t_tx = time.time()
            # -- bookkeeping after the answer is out
            if stop_flag and not self._session_ended:
                self._session_ended = True
                self.link.send("stop_sent")
            self._prev2 = prev
            self._prev = cmd
            self._hold = cmd
            if m is not None and m.k >= len(m.rows_deg):
                self._finish(m)
            c = self._counts["count"] % W
            self._counts["count"] += 1
            if t_tx - arrived > self.dt:
                self._counts["late"] += 1
            self._publish(t_rx, ipoc, actual, cmd, lat=(c, t_tx - arrived, arrived))
            if not self._first_sent:
                self._first_sent = True
                self.link.send("first")
            self._handle_requests()
            if self._orphan_since is not None and self._motion is None and not self._stop_flag:
                now = time.monotonic()
                if self._held_since is None:
                    self._held_since = now
                elif now - self._held_since >= self.orphan_hold_s:
                    self._stop_flag = True  # at rest and held: end the RSI program

    def _motion_error(self):
        m = self._motion
        return None if m is None else m.error

    def _publish(self, t_rx, ipoc, actual, cmd, *, has_state=True, lat=None) -> None:
        st = self.state
        with st.write():
            st["t_rx"][0] = t_rx
            st["ipoc"][0] = ipoc
            st["actual"][:] = actual
            st["cmd"][:] = cmd
            if self._ref_deg is not None:
                st["ref"][:] = self._ref_deg
            st["has_state"][0] = 1.0 if has_state else 0.0
            for k, v in self._counts.items():
                st[k][0] = v
            st["delay"][0] = self._last_delay or 0
            st["has_delay"][0] = self._last_delay is not None
            st["session"][0] = self._session
            st["session_ended"][0] = self._session_ended
            st["busy"][0] = self._motion is not None or self._pending is not None
            if lat is not None:
                c, latency, arrived = lat
                st["lat"][c] = latency
                st["rx"][c] = arrived

    def _axis_error_text(self, rob) -> str:
        return (
            f"{self.name}: the controller reports {len(rob.axis_actual_deg)} robot axes and "
            f"{len(rob.external_actual_deg)} external axes, the robot model has {self.n}"
        )

    def _start_session(self, rob, actual) -> bool:
        """First packet of an RSI session: reference = ASPos (or AIPos), hold = current offset.
        False (and an ``axis_error`` event) when the axis count differs from the model's."""
        if len(actual) != self.n:
            self._ref_deg = None
            if not self._axis_error_sent:
                self._axis_error_sent = True
                self.link.send("axis_error", self._axis_error_text(rob))
            return False
        self._axis_error_sent = False
        if rob.axis_setpoint_deg is not None and (
            rob.external_setpoint_deg is not None or not rob.external_actual_deg
        ):
            ref = np.asarray(rob.axis_setpoint_deg + (rob.external_setpoint_deg or ()), dtype=float)
        else:
            ref = np.asarray(actual, dtype=float)
        self._formatter = SenFormatter(len(rob.axis_actual_deg), len(rob.external_actual_deg), self.sen_type)
        self._ref_deg = ref
        hold = np.asarray(actual, dtype=float) - ref  # keep the robot where it is
        self._hold = hold
        self._prev = hold.copy()
        self._prev2 = hold.copy()
        self._session += 1
        self._stop_flag = False
        self._session_ended = False
        self._delay_n = 0
        return True

    def _plan_stop(self, m: _Motion) -> _Motion:
        """Replace motion ``m`` by a stop planned from the state of its last answered row."""
        dt = self.dt
        if m.traj is not None and m.k > 0:
            p, v, a = m.traj.sample(m.k * dt)
        else:  # emergency: state from the last answers
            p = np.radians(self._ref_deg + self._prev)
            v = np.radians(self._prev - self._prev2) / dt
            a = np.zeros_like(v)
        stop = JointTrajectory.stop(p, v, a, self.vmax, self.amax, self.jmax)
        n_rows = max(1, math.ceil(stop.duration / dt - 1e-9))
        pos, _, _ = stop.sample(dt * np.arange(1, n_rows + 1))
        rows = np.degrees(pos) - self._ref_deg
        s = _Motion(m.id, rows, stop, m.session, is_stop=True)
        s.error = m.error
        self._motion = s
        return s

    def _clamp(self, cmd: np.ndarray) -> np.ndarray:
        """The closest command to ``cmd`` that keeps velocity and acceleration per cycle in limits."""
        prev, prev2 = self._prev, self._prev2
        v_prev = prev - prev2
        lo = np.maximum(-self._g_step, v_prev - self._g_acc) * (1 - 2 * GUARD_SLACK)
        hi = np.minimum(self._g_step, v_prev + self._g_acc) * (1 - 2 * GUARD_SLACK)
        return prev + np.clip(cmd - prev, np.minimum(lo, hi), np.maximum(lo, hi))
