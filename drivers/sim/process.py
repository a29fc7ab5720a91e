"""The simulated cell in an OS process of its own, real-time where the host permits it.

A real cell's controller and sensors are machines of their own: nothing the cell PC runs can
make them late. A simulated cell started as threads of the run's process shares that process's
interpreter lock and garbage collector with the fit, the recorder and the bus — under a fit and
a loaded host the fake Sunrise's 5 ms send period stretched past its 100 ms watchdog (see
``tests/bench/README.md``). So, as the commander's exchange (``drivers.exchange``) does:

- ``enter_realtime(priority)`` puts the calling thread at SCHED_FIFO ``priority`` and locks the
  process's memory where permitted (one log line says which; a quiet fallback on EPERM). Threads
  started afterwards inherit the policy, so a cell process that calls it before starting its
  fakes runs every fake device real-time: no normal-priority thread of the cell can hold the
  interpreter lock while the host preempts it. ``acquire sim`` (a process of its own already)
  calls it before starting its cell.
- ``CellProcess`` runs a ``drivers.sim.launch.SimLaunch`` in a spawned child process (which calls
  ``enter_realtime``) and is its handle in the parent: ``addresses``, ``inject``,
  ``enter_mastering``, ``describe``, and, for the after-run summary only, ``truth_offsets_deg`` /
  ``mean_sag_deg``. Every fake device lives in the child around one ``SimCell``, so they all
  move and observe one cell; the child's ``SimClock`` is the parent's (the monotonic clock is
  system-wide), so the parent's description of the cell tells the same time as its devices.

The child ignores SIGINT (Ctrl-C reaches the whole process group: the run decides how to stop
the robot and needs the controller for it), stops its fakes on SIGTERM, on ``close()`` and when
the parent is gone (the request pipe reaches EOF or it was re-parented). Its log records come to
the parent's loggers (same names) through a queue and one forwarding thread, so a fake never
waits for the parent to log.

The child is forked from a ``multiprocessing`` fork server that has the cell's modules imported
(``PRELOAD``): after the first, a cell starts without an interpreter importing numpy and the
fakes (about 1.5 CPU-seconds each time); where there is no fork server, it is spawned. A
single-threaded process that has the cell's modules imported already (``acquire sim`` as it
starts) may ask for ``start_method="fork"``: it is refused (the fork server is used) once the
process has a second thread, since a fork copies only the calling thread. A script
that starts a cell process must do so under ``if __name__ == "__main__":`` (the ``acquire``
entry point, pytest and ``python -c`` need nothing).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.clock import SimClock
from drivers.sim.launch import CONTROLLER_RT_PRIORITY, DeviceAddress

log = logging.getLogger(__name__)

#: Wall seconds a cell process may take to start (spawn, imports, every fake bound) on a loaded host.
START_TIMEOUT_S = 120.0
#: Wall seconds one request to the cell process may take (entering a mastering restarts the controller).
REQUEST_TIMEOUT_S = 60.0
#: How often the child checks that its parent is still there (wall s).
PARENT_POLL_S = 0.5
#: What the fork server imports once, so that every cell process forked from it has it already.
PRELOAD = ["drivers.sim.process", "drivers.sim.launch", "drivers.sim.cell", "drivers.sim.faults",
           "drivers.kuka_fri.fake", "drivers.kuka_rsi.fake", "drivers.natnet.fake", "drivers.tracker.fake",
           "drivers.emscon.fake", "drivers.sim.socket_operator"]


def _context(start_method: str | None = None):
    """``"fork"`` if asked for and this process has one thread; else the fork server with
    ``PRELOAD`` imported (spawn where the OS has none)."""
    if start_method == "fork" and threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("fork")
    try:
        ctx = multiprocessing.get_context("forkserver")
    except ValueError:
        return multiprocessing.get_context("spawn")
    ctx.set_forkserver_preload(PRELOAD)  # (only before the server starts; the same list every time)
    return ctx


def enter_realtime(priority: int, name: str = "simulated cell") -> str:
    """SCHED_FIFO ``priority`` for the calling thread (and every thread it starts from now on)
    and locked memory for the process, where permitted; says which in one log line and returns
    it. ``priority`` 0: normal priority, memory not locked."""
    from drivers.exchange import lock_memory

    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        what = "normal priority" + (" (rt priority 0)" if priority <= 0 else " (no SCHED_FIFO on this OS)")
        log.info("%s: process %d runs at %s", name, os.getpid(), what)
        return what
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        what = f"normal priority (SCHED_FIFO {priority} not permitted: {exc.strerror})"
        log.warning("%s: process %d runs at %s; its devices may be late on a loaded host. Grant CAP_SYS_NICE "
                    "and an RLIMIT_RTPRIO (systemd: AmbientCapabilities=CAP_SYS_NICE, LimitRTPRIO=%d) to fix",
                    name, os.getpid(), what, priority)
        return what
    what = f"SCHED_FIFO {priority}, {lock_memory()}"
    log.info("%s: process %d runs at %s", name, os.getpid(), what)
    return what


class CellProcessError(RuntimeError):
    """The cell process died, did not start in time, or did not answer a request in time."""


class CellProcess:
    """A ``SimLaunch`` of the cell file ``cell_file`` (``seed``: None keeps the file's) on
    ``clock``, started in a child process at SCHED_FIFO ``rt_priority`` where permitted.

    launch_options: keyword arguments of ``SimLaunch`` (ports, send period, tracker protocols,
    max_runtime_s, …; picklable). start_method: None (the fork server) or ``"fork"`` (see the
    module's docstring). After ``start()``: ``addresses`` (device name →
    ``DeviceAddress``), ``realtime`` (what the child got, in words) and ``pid``.
    """

    def __init__(self, cell_file: str | Path, *, clock: SimClock, seed: int | None = None,
                 launch_options: dict[str, Any] | None = None, rt_priority: int = CONTROLLER_RT_PRIORITY,
                 start_method: str | None = None) -> None:
        if not (isinstance(rt_priority, int) and 0 <= rt_priority <= 99):
            raise ValueError(f"rt_priority must be an integer in [0, 99], got {rt_priority!r}")
        self.cell_file = Path(cell_file)
        self.clock = clock
        self.seed = seed  # (the cell's own once started)
        self.launch_options = dict(launch_options or {})
        self.rt_priority = rt_priority
        self.start_method = start_method
        self.addresses: dict[str, DeviceAddress] = {}
        self.realtime = ""
        #: The cell file's ``faults:`` timeline the child fires: (at wall s, ``Fault``) each.
        self.timeline_steps: list = []
        self.pid: int | None = None
        self._proc = None
        self._conn = None
        self._logs = None
        self._log_thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._seq = 0  # requests so far: a late answer to one that timed out is told apart

    # --- lifecycle ------------------------------------------------------------------------
    def start(self) -> "CellProcess":
        """Start the child and wait until every fake is up. Raises what starting the cell raised
        in the child (ValueError, OSError), or ``CellProcessError``."""
        if self._proc is not None:
            raise RuntimeError("the cell process is already started")
        ctx = _context(self.start_method)
        parent_conn, child_conn = ctx.Pipe()
        logs_recv, logs_send = ctx.Pipe(duplex=False)
        level = logging.getLogger().getEffectiveLevel()
        self._proc = ctx.Process(
            target=serve, name="remaster-sim-cell", daemon=True,
            args=(child_conn, logs_send, str(self.cell_file), self.seed, self.clock,
                  self.launch_options, self.rt_priority, level),
        )
        self._proc.start()
        child_conn.close()
        logs_send.close()
        self._conn, self._logs = parent_conn, logs_recv
        self.pid = self._proc.pid
        self._log_thread = threading.Thread(target=self._forward_logs, name="sim-cell-logs", daemon=True)
        self._log_thread.start()
        try:
            ready = self._reply(self._proc, 0, START_TIMEOUT_S, "start")
        except BaseException:
            self.close()
            raise
        self.addresses = ready["addresses"]
        self.realtime = ready["realtime"]
        self.seed = ready["seed"]
        self.timeline_steps = ready["timeline"]
        return self

    def close(self) -> None:
        """Stop every fake and end the child (idempotent)."""
        proc, conn = self._proc, self._conn
        if proc is None:
            return
        self._proc = None
        with self._lock:
            try:
                if proc.is_alive():
                    conn.send((-1, "close", ()))
                    if conn.poll(30.0):
                        conn.recv()
            except (OSError, EOFError, BrokenPipeError):
                pass
        proc.join(10.0)
        if proc.is_alive():
            log.warning("the simulated cell's process %d did not end in 10 s; terminating it", proc.pid)
            proc.terminate()
            proc.join(5.0)
        conn.close()
        if self._log_thread is not None:
            self._log_thread.join(5.0)
        self._logs.close()
        self.addresses = {}

    def __enter__(self) -> "CellProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    # --- requests -------------------------------------------------------------------------
    def _call(self, op: str, *args):
        proc = self._proc
        if proc is None:
            raise RuntimeError("the cell process is not started")
        with self._lock:
            self._seq += 1
            try:
                self._conn.send((self._seq, op, args))
            except (OSError, BrokenPipeError) as exc:
                raise CellProcessError(f"the simulated cell's process is gone ({exc})") from None
            return self._reply(proc, self._seq, REQUEST_TIMEOUT_S, op)

    def _reply(self, proc, seq: int, timeout_s: float, op: str):
        """The child's answer to request ``seq`` (answers to earlier ones are dropped)."""
        conn = self._conn
        waited = 0.0
        while True:
            while not conn.poll(0.5):
                waited += 0.5
                if not proc.is_alive():
                    raise CellProcessError(f"the simulated cell's process ended (exit code {proc.exitcode}) "
                                           f"during {op}")
                if waited >= timeout_s:
                    raise CellProcessError(f"the simulated cell's process did not answer {op} within {timeout_s:g} s")
            try:
                got, ok, value = conn.recv()
            except EOFError:
                raise CellProcessError(f"the simulated cell's process ended during {op}") from None
            if got == seq:
                break
        if not ok:
            raise value
        return value

    def inject(self, fault: str, device: str | None = None, duration_s: float | None = None,
               probability: float | None = None) -> list[str]:
        """``SimLaunch.inject`` in the child: the devices hit; raises its ``FaultError``."""
        return self._call("inject", fault, device, duration_s, probability)

    def enter_mastering(self, entries) -> np.ndarray:
        """``SimLaunch.enter_mastering`` in the child: the new table (n,) deg; raises its ``MasteringError``."""
        return self._call("enter_mastering", list(entries))

    def mastering_lines(self) -> list[str]:
        """The controller's mastering table, one line per axis."""
        return self._call("mastering_lines")

    def mastering_corrections_deg(self) -> np.ndarray:
        """The controller's zero corrections (n,) deg."""
        return self._call("mastering_corrections_deg")

    def describe(self) -> list[str]:
        """``SimLaunch.describe``: one line per device, for a person."""
        return self._call("describe")

    def joint_positions(self) -> np.ndarray:
        """The joints as the controller reports them (n,) rad."""
        return self._call("joint_positions")

    def truth_offsets_deg(self) -> list[float]:
        """The cell's hidden zero-offsets (deg): for the after-run summary only."""
        return self._call("truth_offsets_deg")

    def mean_sag_deg(self, q_rad) -> list[float]:
        """The cell's gravity sag averaged over ``q_rad`` (k, n) rad, deg: for the after-run summary only."""
        return self._call("mean_sag_deg", np.atleast_2d(np.asarray(q_rad, dtype=float)))

    def _forward_logs(self) -> None:
        """Re-log the child's records under their own logger names in this process."""
        while True:
            try:
                name, level, message = self._logs.recv()
            except (EOFError, OSError):
                return
            logging.getLogger(name).log(level, "%s", message)


# --- the child ------------------------------------------------------------------------------
class _QueueLog(logging.Handler):
    """Puts (logger name, level, message) on a queue: a fake never blocks on logging."""

    def __init__(self, q: queue.SimpleQueue) -> None:
        super().__init__()
        self.q = q

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = record.getMessage()
            if record.exc_info:
                msg += "\n" + logging.Formatter().formatException(record.exc_info)
            self.q.put((record.name, record.levelno, msg))
        except Exception:  # noqa: BLE001 - logging must not raise
            self.handleError(record)


def _log_to_queue(level: int) -> queue.SimpleQueue:
    """Every log record of this process onto a queue (``_forward``'s thread sends them on)."""
    q: queue.SimpleQueue = queue.SimpleQueue()
    root = logging.getLogger()
    root.handlers[:] = [_QueueLog(q)]
    root.setLevel(level)
    return q


def _forward(q: queue.SimpleQueue, logs_send) -> threading.Thread:
    """A thread that sends the queued records to the parent until it gets None."""

    def forward() -> None:
        while True:
            item = q.get()
            if item is None:
                return
            try:
                logs_send.send(item)
            except (OSError, BrokenPipeError):
                return

    thread = threading.Thread(target=forward, name="sim-cell-log-forward", daemon=True)
    thread.start()
    return thread


def serve(conn, logs_send, cell_file: str, seed: int | None, clock: SimClock,
          launch_options: dict, rt_priority: int, log_level: int) -> None:
    """Entry point of the cell process: real-time where permitted, then the cell's fakes, then
    the parent's requests until ``close``, SIGTERM or the parent is gone."""
    parent_pid = os.getppid()  # (the fork server's, which ends with the process that started it)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    records = _log_to_queue(log_level)
    # before any thread starts: every thread of the cell inherits it (a normal-priority thread
    # preempted while it holds the interpreter lock would hold up the real-time ones)
    realtime = enter_realtime(rt_priority)
    forwarder = _forward(records, logs_send)
    launch = None
    try:
        try:
            from drivers.sim.cell import SimCell
            from drivers.sim.launch import SimLaunch

            cell = SimCell.from_yaml(cell_file, seed=seed, clock=clock)
            launch = SimLaunch(cell, controller_rt_priority=rt_priority, **launch_options).start()
        except Exception as exc:  # noqa: BLE001 - handed to the parent, which raises it
            conn.send((0, False, _picklable(exc)))
            return
        conn.send((0, True, {"addresses": dict(launch.addresses), "realtime": realtime, "seed": launch.seed,
                          "timeline": list(launch.timeline.steps) if launch.timeline is not None else []}))
        _serve_requests(conn, launch, parent_pid, stop)
    finally:
        if launch is not None:
            launch.close()
        records.put(None)
        forwarder.join(5.0)
        try:
            conn.send((-1, True, None))  # (close's answer; nobody reads it when the parent is gone)
        except (OSError, BrokenPipeError):
            pass


def _serve_requests(conn, launch, parent_pid: int, stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            if not conn.poll(PARENT_POLL_S):
                if os.getppid() != parent_pid:  # re-parented: whoever started it is gone
                    log.warning("simulated cell: the process that started it is gone; stopping every fake")
                    return
                continue
            seq, op, args = conn.recv()
        except (EOFError, OSError):
            return
        if op == "close":
            return
        try:
            reply = (seq, True, _REQUESTS[op](launch, *args))
        except Exception as exc:  # noqa: BLE001 - the parent raises it
            reply = (seq, False, _picklable(exc))
        try:
            conn.send(reply)
        except (OSError, BrokenPipeError):
            return


def _picklable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a ``CellProcessError`` saying it."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001
        return CellProcessError(f"{type(exc).__name__}: {exc}")


_REQUESTS = {
    "inject": lambda launch, *a: launch.inject(*a),
    "enter_mastering": lambda launch, entries: launch.enter_mastering(entries),
    "mastering_lines": lambda launch: launch.mastering_lines(),
    "mastering_corrections_deg": lambda launch: launch.mastering_corrections_deg(),
    "describe": lambda launch: launch.describe(),
    "joint_positions": lambda launch: launch.joint_positions(),
    "truth_offsets_deg": lambda launch: [float(v) for v in launch.cell.truth.offsets_deg],
    "mean_sag_deg": lambda launch, q: np.degrees(launch.cell.deflection(q).mean(axis=0)).tolist(),
}
