"""A fake KR C4 running RSI: the controller side of the RSI Ethernet exchange, on loopback.

Every cycle (4 ms ``#IPO_FAST`` or 12 ms ``#IPO``, scaled by an optional ``SimClock``) it sends a
``<Rob>`` state packet to the commander's address and waits until the next cycle for the
``<Sen>`` answer carrying the same IPOC. The axis corrections (``AK``, ``#ABSOLUTE``: total offset
from the start position ``ASPos``, degrees) drive a second-order servo per axis, integrated
exactly (zero-order hold over the cycle). Answers that do not arrive in time or carry the wrong
IPOC count as late; when the count reaches ``late_limit`` (consecutive or in total, a setting
because the real rule is unverified) the robot stops with an "RSI timeout" and the fake stops
sending, like the real controller leaving its RSI program.

What it sends and reads follows an RSI Ethernet configuration file (``ethernet_config``; by
default, for a 6-axis robot, the one we ship in ``drivers/kuka_rsi/controller/``): the ``SEND``
elements in their order, the answer's ``Sen Type`` checked against ``SENTYPE`` (RSI ignores
other packets), ``<Stop>`` honoured only when the configuration maps it to a channel.

Fault hooks: ``drop_outgoing`` / ``drop_answers`` (packet loss either way), ``send_malformed``,
``restart`` (new RSI session: new start position and IPOC sequence), ``stop_sending`` /
``resume_sending``, ``jitter_s`` (random send delay), ``hold_brakes`` (the axes stay put while
the exchange goes on normally), ``drives_off`` (the robot stops and the RSI program with it).

Units: degrees on the wire and in the fake's state; radians to the ``RobotScene``.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import expm

from drivers.errors import ProtocolError
from drivers.kuka_rsi.codec import RobFormatter, parse_sen
from drivers.kuka_rsi.ethernet_config import RsiEthernetConfig
from drivers.udp import enable_rx_timestamps, recv_stamped
from drivers.sim.clock import SimClock
from drivers.sim.scene import RobotScene

log = logging.getLogger("remaster.device.fake_krc4")

__all__ = ["FakeKrc4", "FakeKrc4Stats", "ReceivedCommand"]


#: Pause of the lockstep fake between an answer and its next packet (see ``FakeKrc4._loop``).
LOCKSTEP_REST_S = 0.0005


@dataclass(frozen=True, slots=True)
class ReceivedCommand:
    """One answer as the fake received it. correction_deg: AK then EK, degrees."""

    ipoc: int
    correction_deg: tuple[float, ...]
    stop: bool
    on_time: bool


@dataclass
class FakeKrc4Stats:
    """Counters of one fake controller (read with ``FakeKrc4.stats()``, a snapshot)."""

    # counted when a cycle's answer window closes: a snapshot has cycles == answers_on_time + late_total
    cycles: int = 0  # state packets due (sent, dropped or garbled)
    sent: int = 0
    answers_on_time: int = 0
    late: int = 0  # missing, wrong-IPOC or too-late answers, in this RSI session
    late_total: int = 0  # over all sessions
    late_consecutive: int = 0
    stale_answers: int = 0  # answers that arrived for an earlier cycle
    malformed_answers: int = 0
    clipped_corrections: int = 0
    max_correction_step_deg: float = 0.0
    sessions: int = 1
    running: bool = False
    stopped_reason: str | None = None
    errors: list[str] = field(default_factory=list)
    late_events: list[str] = field(default_factory=list)  # the first 100, for diagnosis


class FakeKrc4:
    """Controller twin. ``target``: the commander's (host, port). Start with ``start()`` (or a
    ``with`` block); it stops by itself after ``max_runtime_s`` wall seconds.

    n_axes robot axes (≤ 6) and n_external external axes; ``initial_deg`` shape (n_axes +
    n_external,). Servo: natural frequency ``servo_hz`` and damping ``servo_damping`` (0.6 →
    ~10 % overshoot, settling ≈ 4/(ζω) ≈ 70 ms at 15 Hz). ``lockstep``: send the next packet as
    soon as the answer is in (still within the cycle deadline; after a 0.5 ms rest), so tests run
    faster than real time while the simulated time advances one cycle per packet. ``rt_priority`` > 0 runs the
    cycle thread SCHED_FIFO (like a controller, it then keeps its period on a loaded host).
    """

    def __init__(
        self,
        target: tuple[str, int],
        *,
        n_axes: int = 6,
        n_external: int = 0,
        initial_deg=None,
        cycle_ms: int = 4,
        late_limit: int = 100,
        late_consecutive: bool = False,
        servo_hz: float = 15.0,
        servo_damping: float = 0.6,
        max_correction_step_deg: float | None = None,
        scene: RobotScene | None = None,
        clock: SimClock | None = None,
        lockstep: bool = False,
        jitter_s: float = 0.0,
        bind: tuple[str, int] = ("127.0.0.1", 0),
        ipoc_start: int = 4_000_000,
        seed: int = 0,
        record_limit: int = 200_000,
        max_runtime_s: float = 600.0,
        rob_type: str = "KUKA",
        rt_priority: int = 0,
        ethernet_config: RsiEthernetConfig | None = None,
    ) -> None:
        if cycle_ms not in (4, 12):
            raise ValueError(f"cycle_ms must be 4 (#IPO_FAST) or 12 (#IPO), got {cycle_ms}")
        if late_limit < 1:
            raise ValueError(f"late_limit must be at least 1, got {late_limit}")
        if not target[0].startswith("127."):
            raise ValueError(f"the fake controller only talks on loopback, got target {target[0]!r}")
        n = n_axes + n_external
        self.n_axes, self.n_external, self.n = n_axes, n_external, n
        self.cycle_ms = cycle_ms
        self.cycle_s = cycle_ms / 1000.0
        self.target = (target[0], int(target[1]))
        self.late_limit = late_limit
        self.late_consecutive_rule = late_consecutive
        self.max_correction_step_deg = max_correction_step_deg
        self.scene = scene
        self.clock = clock
        self.lockstep = lockstep
        self.jitter_s = float(jitter_s)
        self.max_runtime_s = max_runtime_s
        self.rt_priority = int(rt_priority)
        self._rng = np.random.default_rng(seed)
        if ethernet_config is None and (n_axes, n_external) == (6, 0):
            ethernet_config = RsiEthernetConfig.load()
        if ethernet_config is not None and ethernet_config.axes_read() != n_axes:
            raise ValueError(f"{ethernet_config.path} reads {ethernet_config.axes_read()} AK corrections; "
                             f"the robot has {n_axes} axes")
        self.config = ethernet_config
        elements = ethernet_config.send if ethernet_config is not None else RobFormatter.DEFAULT_ELEMENTS
        self._fmt = RobFormatter(n_axes, n_external, rob_type, elements=elements)
        if initial_deg is None:
            initial_deg = np.zeros(n)
            if scene is not None:
                initial_deg = np.degrees(np.asarray(scene.joint_positions(), dtype=float))
        q0 = np.asarray(initial_deg, dtype=float).reshape(-1)
        if q0.shape != (n,):
            raise ValueError(f"initial_deg must have {n} values, got {q0.shape[0]}")
        # servo: x'' = w²(r - x) - 2ζw x', exact zero-order-hold discretisation over one cycle
        w = 2 * math.pi * servo_hz
        A = np.array([[0.0, 1.0, 0.0], [-w * w, -2 * servo_damping * w, w * w], [0.0, 0.0, 0.0]])
        M = expm(A * self.cycle_s)
        self._Ad, self._Bd = M[:2, :2].copy(), M[:2, 2].copy()
        self._lock = threading.Lock()
        self._x = q0.copy()  # actual position, deg
        self._xd = np.zeros(n)  # actual velocity, deg/s
        self._aspos = q0.copy()  # start position of this RSI session
        self._ak = np.zeros(n)  # correction in force
        self._ipoc = int(ipoc_start)
        self._stats = FakeKrc4Stats()
        self._received: deque[ReceivedCommand] = deque(maxlen=record_limit)
        self._drop_out_n = 0
        self._drop_out_p = 0.0
        self._drop_ans_p = 0.0
        self._malformed_n = 0
        self._silent = False
        self._restart_req: int | None = None
        self._brakes_held = False
        self._drives_off = False
        self._stop = threading.Event()
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(bind)
        self._stamped = enable_rx_timestamps(self._sock)
        self.address = self._sock.getsockname()

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> "FakeKrc4":
        if self._thread is not None:
            raise RuntimeError("fake KR C4 already started")
        self._stats.running = True
        self._thread = threading.Thread(target=self._run, name="fake-krc4", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._sock.close()

    def __enter__(self) -> "FakeKrc4":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def wait_stopped(self, timeout: float) -> bool:
        """True once the RSI exchange has ended (timeout, Stop flag, close)."""
        return self._stopped.wait(timeout)

    # -- observation --------------------------------------------------------------------------

    def stats(self) -> FakeKrc4Stats:
        with self._lock:
            s = FakeKrc4Stats(**{k: getattr(self._stats, k) for k in self._stats.__dataclass_fields__})
            s.errors = list(self._stats.errors)
            s.late_events = list(self._stats.late_events)
            return s

    def actual_deg(self) -> np.ndarray:
        """Actual axis positions now, shape (n,), degrees."""
        with self._lock:
            return self._x.copy()

    def start_position_deg(self) -> np.ndarray:
        with self._lock:
            return self._aspos.copy()

    def received(self) -> list[ReceivedCommand]:
        """Every answer received (up to ``record_limit``), in arrival order."""
        with self._lock:
            return list(self._received)

    # -- fault hooks --------------------------------------------------------------------------

    def drop_outgoing(self, n: int = 0, probability: float = 0.0) -> None:
        """Lose the next ``n`` state packets and/or each with ``probability`` (seeded)."""
        with self._lock:
            self._drop_out_n, self._drop_out_p = int(n), float(probability)

    def drop_answers(self, probability: float) -> None:
        """Lose each answer with ``probability`` on its way back (it then counts as late)."""
        with self._lock:
            self._drop_ans_p = float(probability)

    def send_malformed(self, n: int) -> None:
        """Send ``n`` garbled state packets instead of the next ``n`` valid ones."""
        with self._lock:
            self._malformed_n = int(n)

    def restart(self, ipoc_start: int = 1000) -> None:
        """Restart the RSI program: new start position (the current set-point), corrections
        reset to zero, IPOC sequence restarting at ``ipoc_start``, late count reset."""
        with self._lock:
            self._restart_req = int(ipoc_start)

    def stop_sending(self) -> None:
        with self._lock:
            self._silent = True

    def hold_brakes(self, held: bool = True) -> None:
        """The axes stay where they are (brakes not released, a seized gear) while the RSI
        exchange goes on as if nothing were wrong: the corrections are read, nothing moves."""
        with self._lock:
            self._brakes_held = bool(held)
            self._xd = np.zeros(self.n)

    def drives_off(self) -> None:
        """The drives switch off (enabling switch released, an E-stop): the brakes hold, the
        robot program halts and RSI with it (the controller stops sending)."""
        with self._lock:
            self._drives_off = True

    def resume_sending(self) -> None:
        with self._lock:
            self._silent = False

    # -- the cycle ----------------------------------------------------------------------------

    def _wall(self, sim_s: float) -> float:
        return self.clock.wall_duration(sim_s) if self.clock is not None else sim_s

    def _run(self) -> None:
        if self.rt_priority > 0:
            try:  # a controller keeps its cycle; so should its twin on a loaded host
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
            except (PermissionError, OSError, AttributeError) as exc:
                log.warning("fake KR C4: no SCHED_FIFO priority %d (%s); its cycle may jitter", self.rt_priority, exc)
        try:
            self._loop()
        except OSError as exc:  # socket closed under us by close()
            if not self._stop.is_set():
                log.error("fake KR C4 socket failed: %s", exc)
                with self._lock:
                    self._stats.errors.append(str(exc))
        finally:
            with self._lock:
                self._stats.running = False
            self._stopped.set()

    def _end(self, reason: str) -> None:
        with self._lock:
            self._stats.stopped_reason = reason
        log.warning("fake KR C4: RSI stopped: %s", reason)

    def _loop(self) -> None:
        sock = self._sock
        cycle_wall = self._wall(self.cycle_s)
        t_end = time.monotonic() + self.max_runtime_s
        next_t = time.monotonic()
        st = self._stats
        while not self._stop.is_set():
            if time.monotonic() > t_end:
                self._end("max_runtime_s reached")
                return
            with self._lock:
                if self._restart_req is not None:
                    self._aspos = self._aspos + self._ak
                    self._ak = np.zeros(self.n)
                    self._ipoc = self._restart_req
                    self._restart_req = None
                    st.late = st.late_consecutive = 0
                    st.sessions += 1
                silent = self._silent
                drop = self._drop_out_n > 0 or (self._drop_out_p > 0 and self._rng.random() < self._drop_out_p)
                if self._drop_out_n > 0:
                    self._drop_out_n -= 1
                garble = self._malformed_n > 0
                if garble:
                    self._malformed_n -= 1
                ipoc = self._ipoc
                packet = self._fmt.format(
                    self._x, self._aspos, (0.0,) * 6, (0.0,) * 6, st.late, ipoc
                )
            if self.jitter_s > 0:
                time.sleep(self._rng.uniform(0, self.jitter_s))
            expect_answer = not silent
            sent = False
            if not silent:
                if garble:
                    packet = packet[: len(packet) // 2] + b"<<garbled"
                if not drop:
                    sock.sendto(packet, self.target)
                    sent = True
            # the answer may take a full cycle from the actual send (our own wake-up delay must
            # not shorten it); the next packet goes out on schedule once the answer is in
            t_sent = time.monotonic()
            deadline = max(next_t, t_sent) + cycle_wall
            answered = self._collect(ipoc, deadline) if expect_answer else False
            next_t += cycle_wall
            now = time.monotonic()
            if self.lockstep and answered:
                # a short rest, never a full cycle: the lockstep controller is a thread of the
                # commander's own process, and without a pause it would take the interpreter lock
                # back at every answer — each cycle a write of the exchange's shared state inside
                # any read a starved thread of that process began (seen: a read retried for 60 s)
                time.sleep(LOCKSTEP_REST_S)
                next_t = time.monotonic()
            elif not answered:
                next_t = max(next_t, now)
            elif next_t > now:
                time.sleep(next_t - now)
            if now - next_t > cycle_wall:  # fell behind by more than a cycle: resynchronise
                next_t = now
            with self._lock:
                if expect_answer:  # a cycle is counted once its answer window has closed
                    st.cycles += 1
                    st.sent += sent
                    if answered:
                        st.answers_on_time += 1
                        st.late_consecutive = 0
                    else:
                        st.late += 1
                        st.late_total += 1
                        st.late_consecutive += 1
                        if len(st.late_events) < 100:
                            st.late_events.append(f"IPOC {ipoc}: no answer in time")
                # servo over one cycle, set-point = start position + correction (zero-order hold)
                r = self._aspos + self._ak
                x, xd = self._x, self._xd
                if self._brakes_held or self._drives_off:
                    self._xd = np.zeros(self.n)
                else:
                    self._x = self._Ad[0, 0] * x + self._Ad[0, 1] * xd + self._Bd[0] * r
                    self._xd = self._Ad[1, 0] * x + self._Ad[1, 1] * xd + self._Bd[1] * r
                drives_off = self._drives_off
                self._ipoc += self.cycle_ms
                q_now = self._x.copy()
                count = st.late_consecutive if self.late_consecutive_rule else st.late
                stop_flag = bool(self._received) and self._received[-1].stop and self._received[-1].on_time
            if self.scene is not None:
                self.scene.set_joint_positions(np.radians(q_now))
            if drives_off:
                self._end("drives off: the robot program halted")
                return
            if count >= self.late_limit:
                self._end(f"RSI timeout: {count} late answers (limit {self.late_limit})")
                return
            if stop_flag:
                self._end("Stop flag from the sensor")
                return

    def _collect(self, ipoc: int, deadline: float) -> bool:
        """Read answers until ``deadline``; True once one with ``ipoc`` has been applied."""
        sock = self._sock
        deadline_wall = time.time() + (deadline - time.monotonic())
        while True:
            if self._stop.is_set():
                return False
            remaining = deadline - time.monotonic()
            # past the deadline: still read what arrived in time (judged by the kernel's stamp)
            sock.settimeout(max(remaining, 0.0))
            try:
                data, _, arrived = recv_stamped(sock, 4096, self._stamped)
            except (TimeoutError, BlockingIOError):
                return False
            except ConnectionRefusedError:  # ICMP from a commander not listening yet
                continue
            with self._lock:
                if self._drop_ans_p > 0 and self._rng.random() < self._drop_ans_p:
                    continue
            try:
                cmd = parse_sen(data)
            except ProtocolError as exc:
                with self._lock:
                    self._stats.malformed_answers += 1
                    if len(self._stats.errors) < 100:
                        self._stats.errors.append(str(exc))
                continue
            if self.config is not None and cmd.type != self.config.sen_type:
                with self._lock:  # RSI discards a packet of another sensor type
                    self._stats.malformed_answers += 1
                    if len(self._stats.errors) < 100:
                        self._stats.errors.append(f"Sen Type {cmd.type!r} is not the configured SENTYPE "
                                                  f"{self.config.sen_type!r}: ignored")
                continue
            if self.config is not None and not self.config.reads_stop:
                cmd = replace(cmd, stop=False)  # no channel carries <Stop> to the STOP object
            on_time = cmd.ipoc == ipoc and arrived <= deadline_wall
            values = cmd.axis_correction_deg + cmd.external_correction_deg
            with self._lock:
                self._received.append(ReceivedCommand(cmd.ipoc, values, cmd.stop, on_time))
                if not on_time:
                    self._stats.stale_answers += 1
                    if len(self._stats.late_events) < 100:
                        self._stats.late_events.append(
                            f"answer IPOC {cmd.ipoc} arrived {(arrived - deadline_wall) * 1e3:+.2f} ms after the "
                            f"deadline of IPOC {ipoc}"
                        )
                    continue
                if len(cmd.axis_correction_deg) != self.n_axes or len(cmd.external_correction_deg) != self.n_external:
                    self._stats.malformed_answers += 1
                    self._stats.errors.append(
                        f"answer has {len(cmd.axis_correction_deg)} AK and {len(cmd.external_correction_deg)} EK "
                        f"values, the robot has {self.n_axes} and {self.n_external}"
                    )
                    continue
                ak = np.asarray(values, dtype=float)
                step = np.abs(ak - self._ak)
                self._stats.max_correction_step_deg = max(self._stats.max_correction_step_deg, float(step.max()))
                lim = self.max_correction_step_deg
                if lim is not None and np.any(step > lim):
                    self._stats.clipped_corrections += 1
                    ak = self._ak + np.clip(ak - self._ak, -lim, lim)
                self._ak = ak
            return True
