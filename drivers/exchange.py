"""A cyclic real-time exchange in its own OS process (used by the RSI and FRI commanders).

The controller sends a packet every cycle (4 ms for RSI) and must get its answer within the
cycle. In the main process an answering thread shares the interpreter lock and the garbage
collector with fitting, MCAP writing and the bus; here the loop runs in a child process of its
own, so nothing the main process does can make an answer late.

Parent side (``ExchangeProcess``):

- the UDP socket is bound by the parent (so ``bind()``/``address`` work synchronously) and
  handed to the child at start (the spawn context duplicates its file descriptor); the parent
  then closes its copy: the child owns the socket;
- requests go to the child over a stream socket pair (``request(kind, *args)``: a pickled
  tuple behind a 4-byte length). The child reads it without ever blocking and unpickles only
  complete messages: a parent descheduled half-way through writing a long move can never hold
  the real-time loop (a blocking ``Connection.recv`` would wait for it: priority inversion);
- the child's events (motion done, faults, log lines) come back over a ``Pipe`` and are handed
  to the parent's ``on_event`` callback by one reader thread;
- the latest state, counters and latency rings are read from a shared-memory block
  (``SharedState``, a seqlock over numpy views: the child writes, the parent copies).

Child side (``run_child``, the spawned process's entry point): asks for SCHED_FIFO and locks
its memory (``mlockall``) where permitted (one log line saying which, a quiet fallback on
EPERM), builds the driver's loop object, warms it up, then freezes and disables the garbage
collector before the first packet. It ignores SIGINT (Ctrl-C reaches the whole process group;
the parent decides how to stop) and takes SIGTERM as an order to end on its own. ``ChildLink``
gives the loop its requests without blocking,
its events back, and ``parent_gone()``: true once the request socket reaches EOF or the process was
re-parented (``os.getppid()`` changed), so a loop can stop the robot by itself when the main
process dies (``PR_SET_PDEATHSIG`` is not used: it fires on the death of the parent *thread*).

A loop class is built in the child as ``loop_cls(link, sock, state, **options)`` and must
provide ``warm_up()`` and ``run()``; it returns from ``run`` to end the process.

The spawn start method re-imports the main script in the child: a script that opens a
commander must do so under ``if __name__ == "__main__":`` (the ``acquire`` entry point, pytest
and ``python -c`` need nothing).
"""

from __future__ import annotations

import atexit
import ctypes
import gc
import logging
import multiprocessing
import os
import pickle
import signal
import socket
import struct
import threading
import time
import tracemalloc
from multiprocessing import shared_memory
from typing import Any, Callable, Mapping

import numpy as np

__all__ = ["ExchangeProcess", "SharedState", "ChildLink", "run_child", "set_realtime", "ring_in_order", "read_state",
           "answer_log", "ring_timing"]

_MCL_CURRENT, _MCL_FUTURE = 1, 2
_LENGTH = struct.Struct("<I")


def ring_in_order(ring: np.ndarray, count: int) -> np.ndarray:
    """The entries of a ring buffer that has had ``count`` writes (write ``k`` went to slot
    ``k % len(ring)``), oldest first: shape (min(count, len(ring)),) — a copy."""
    w = ring.shape[0]
    if count <= w:
        return ring[:count].copy()
    i = count % w
    return np.concatenate([ring[i:], ring[:i]])


def read_state(exchange: "ExchangeProcess | None", names) -> dict[str, np.ndarray] | None:
    """``exchange.state.read(names)`` (copies), or None when there is no exchange process, it
    has no state any more, or another thread closed it meanwhile."""
    state = None if exchange is None else exchange.state
    if state is None:
        return None
    try:
        return state.read(names)
    except ConnectionError:  # closed meanwhile by another thread
        return None


def answer_log(exchange: "ExchangeProcess | None") -> tuple[int, np.ndarray, np.ndarray]:
    """``(count, arrived, latency)`` from a commander's rings ``count`` / ``rx`` / ``lat``: cycles
    so far and, for the last min(count, window), oldest first, each shape (m,), the arrival
    stamp (s) and the answer latency (s); ``(0, [], [])`` without a running exchange."""
    st = read_state(exchange, ("count", "lat", "rx"))
    if st is None:
        return 0, np.zeros(0), np.zeros(0)
    count = int(st["count"][0])
    return count, ring_in_order(st["rx"], count), ring_in_order(st["lat"], count)


def ring_timing(count: int, rx_ring: np.ndarray, lat_ring: np.ndarray) -> dict[str, float | int]:
    """The timing fields of ``LinkStats`` (packets, window, period_* and latency_*, s) from the
    arrival-stamp and latency rings (each shape (window,)) after ``count`` cycles."""
    rx, lat = ring_in_order(rx_ring, count), ring_in_order(lat_ring, count)
    n = lat.shape[0]
    per = np.diff(rx) if n > 1 else np.zeros(1)
    q = np.percentile(lat, [50, 99]) if n else np.zeros(2)
    return dict(packets=count, window=n, period_mean_s=float(per.mean()), period_std_s=float(per.std()),
                period_max_s=float(per.max()), latency_p50_s=float(q[0]), latency_p99_s=float(q[1]),
                latency_max_s=float(lat.max()) if n else 0.0)


class SharedState:
    """Named float64 arrays in one shared-memory block, guarded by a seqlock.

    layout: field name -> shape (a tuple; ``()`` is a scalar stored as shape (1,)). One writer
    (the child, ``write()`` as a context manager around its updates); readers copy with
    ``read(names)``, retrying while a write is in progress. Integers up to 2**53 are exact.

    Fields are stored smallest first, so the latest state (scalars and short arrays) lies in a
    few hundred contiguous bytes before the rings: a reader copies the span of the fields it
    asks for in one ``memcpy``, with few points where another thread of its process can take the
    interpreter lock mid-copy. (Copied field by field, tens of calls, a read beside a test's
    lockstep controller, a thread of the same process that made the exchange write at every
    such switch, once retried for 60 s on a loaded machine.)
    """

    def __init__(self, layout: Mapping[str, tuple], name: str | None = None) -> None:
        self.layout = {k: tuple(v) or (1,) for k, v in layout.items()}
        sizes = {k: int(np.prod(s)) for k, s in self.layout.items()}
        total = 8 * (1 + sum(sizes.values()))
        self._owner = name is None
        # (a spawned child shares the parent's resource tracker: the block is registered once
        # and unlinked by the parent, or by the tracker when both processes are gone)
        self.shm = shared_memory.SharedMemory(name=name, create=self._owner, size=total if self._owner else 0)
        buf = np.ndarray((total // 8,), dtype=np.float64, buffer=self.shm.buf)
        if self._owner:
            buf[:] = 0.0
        self._buf = buf
        self._seq = np.ndarray((1,), dtype=np.int64, buffer=self.shm.buf)
        self.views: dict[str, np.ndarray] = {}
        # field -> (offset, size) in float64 words, and its shape when not 1-D
        self._span: dict[str, tuple[int, int, tuple | None]] = {}
        off = 1
        for k in sorted(self.layout, key=lambda k: sizes[k]):  # (stable: the same order in both processes)
            self.views[k] = buf[off : off + sizes[k]].reshape(self.layout[k])
            self._span[k] = (off, sizes[k], self.layout[k] if len(self.layout[k]) > 1 else None)
            off += sizes[k]

    @property
    def name(self) -> str:
        return self.shm.name

    def __getitem__(self, key: str) -> np.ndarray:
        return self.views[key]

    def write(self) -> "_WriteSection":
        """``with state.write(): state["x"][:] = ...`` (child only)."""
        return _WriteSection(self._seq)

    def read(self, names, *, retries: int = 1000) -> dict[str, np.ndarray]:
        """A consistent copy of the fields ``names`` (each as its shape, float64).
        ConnectionError once the block is closed (another thread may close it meanwhile)."""
        seq, buf = self._seq, self._buf
        if seq is None:
            raise ConnectionError("the exchange's shared state is closed")
        spans = [self._span[k] for k in names]
        lo = min(o for o, _, _ in spans)
        hi = max(o + n for o, n, _ in spans)
        for _ in range(retries):
            s1 = int(seq[0])
            if s1 & 1:
                time.sleep(0)
                continue
            block = buf[lo:hi].copy()  # one memcpy
            if int(seq[0]) == s1:
                out = {k: block[o - lo : o - lo + n] for k, (o, n, _) in zip(names, spans)}
                for k, (_, _, shape) in zip(names, spans):
                    if shape is not None:
                        out[k] = out[k].reshape(shape)
                return out
        raise TimeoutError("shared state kept changing while being read (is the exchange process spinning?)")

    def close(self) -> None:
        self.views = {}  # (a reader still holding the old views keeps their memory mapped)
        self._seq = self._buf = None
        try:
            self.shm.close()
        except BufferError:  # a view still exported somewhere: the OS frees it at exit
            pass
        if self._owner:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass


class _WriteSection:
    __slots__ = ("_seq",)

    def __init__(self, seq: np.ndarray) -> None:
        self._seq = seq

    def __enter__(self) -> None:
        self._seq[0] += 1  # odd: a write is in progress

    def __exit__(self, *exc) -> None:
        self._seq[0] += 1


class ChildLink:
    """The child's ends of the request socket and the event pipe, and its watch on the parent."""

    def __init__(self, requests: socket.socket, events, parent_pid: int, name: str) -> None:
        requests.setblocking(False)
        self._requests = requests
        self._buf = bytearray()
        self.events = events
        self.parent_pid = parent_pid
        self.name = name
        self._gone = False
        self.terminate_requested = False
        self.realtime = "not set"

    def requests(self) -> list[tuple]:
        """The complete requests the parent has sent, oldest first; never blocks (a message
        still being written stays buffered). An empty list once the parent is gone."""
        if self._gone:
            return []
        buf = self._buf
        while True:
            try:
                data = self._requests.recv(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._gone = True
                break
            if not data:  # EOF: the parent closed its end or died
                self._gone = True
                break
            buf += data
        out: list[tuple] = []
        while len(buf) >= _LENGTH.size:
            (n,) = _LENGTH.unpack_from(buf)
            if len(buf) < _LENGTH.size + n:
                break
            out.append(pickle.loads(bytes(buf[_LENGTH.size : _LENGTH.size + n])))
            del buf[: _LENGTH.size + n]
        return out

    def parent_gone(self) -> bool:
        """True once the loop is on its own and must bring the robot to an orderly end: the
        parent closed its end or died (the child was re-parented), or SIGTERM asked this
        process to end (an administrator, or systemd stopping the unit's control group)."""
        if not self._gone and os.getppid() != self.parent_pid:
            self._gone = True
        return self._gone or self.terminate_requested

    def _on_sigterm(self, signum, frame) -> None:
        self.terminate_requested = True

    def send(self, *event) -> None:
        """An event to the parent; dropped silently once the parent is gone."""
        if self._gone:
            return
        try:
            self.events.send(event)
        except (BrokenPipeError, EOFError, OSError):
            self._gone = True

    def log(self, level: int, fmt: str, *args) -> None:
        """A log line, logged by the parent under its device logger (stderr once it is gone)."""
        msg = fmt % args if args else fmt
        if self._gone:
            logging.getLogger(f"remaster.device.{self.name}").log(level, "%s", msg)
        else:
            self.send("log", level, msg)


def lock_memory() -> str:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)`` for the calling process: no page fault on the
    real-time path. Says what happened (refused without CAP_IPC_LOCK or a large enough
    RLIMIT_MEMLOCK; nothing else changes then)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
            return "memory locked"
        return f"memory not locked ({os.strerror(ctypes.get_errno())})"
    except (OSError, AttributeError):
        return "memory not locked (no mlockall)"


def set_realtime(link: ChildLink, priority: int) -> None:
    """SCHED_FIFO ``priority`` and locked memory (``mlockall``) for the calling process where
    permitted; ``link.realtime`` says which, in one log line (a warning with the fix when
    SCHED_FIFO was asked for and refused)."""
    parts = []
    if priority > 0 and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            parts.append(f"SCHED_FIFO {priority}")
        except OSError as exc:
            parts.append(f"normal priority (SCHED_FIFO {priority} not permitted: {exc.strerror})")
    else:
        parts.append("normal priority (rt_priority=0)" if priority <= 0 else "normal priority (no SCHED_FIFO)")
    parts.append(lock_memory())
    link.realtime = ", ".join(parts)
    level = logging.INFO if parts[0].startswith("SCHED_FIFO") or priority <= 0 else logging.WARNING
    hint = "" if level == logging.INFO else (
        "; it may answer late under load. Grant CAP_SYS_NICE and an RLIMIT_RTPRIO "
        f"(systemd: AmbientCapabilities=CAP_SYS_NICE, LimitRTPRIO={priority}) to fix"
    )
    link.log(level, "%s: exchange process %d runs %s%s", link.name, os.getpid(), link.realtime, hint)


def stop_tracing() -> None:
    """Stop ``tracemalloc`` in this process. A parent traced for a soak (``PYTHONTRACEMALLOC=1``)
    passes its environment on, and tracing every allocation of the cyclic loop tripled its answer
    time (daemon soak: p50 655 → 215 µs). The exchange's memory is fixed after its warm-up; the
    parent's heap is what a soak measures."""
    if tracemalloc.is_tracing():
        tracemalloc.stop()


def run_child(requests, events, parent_pid: int, name: str, state_name: str, layout, sock, loop_cls, options,
              priority) -> None:
    """Entry point of the exchange process (spawned; see the module docstring)."""
    entered = time.monotonic()  # (CLOCK_MONOTONIC: one clock for every process of the machine)
    link = ChildLink(requests, events, parent_pid, name)
    # Ctrl-C in a terminal reaches the whole process group: the parent decides how to stop the
    # robot and needs this process for it. SIGTERM ends the exchange in order (stop, hold, end).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, link._on_sigterm)  # noqa: SLF001 - the link owns the flag
    state = SharedState(layout, name=state_name)
    loop = None
    try:
        stop_tracing()
        set_realtime(link, priority)
        loop = loop_cls(link, sock, state, **options)
        loop.warm_up()
        gc.collect()
        gc.freeze()  # everything alive now is never scanned again
        gc.disable()  # the loop allocates little and keeps no cycles: no collector pauses
        link.send("ready", os.getpid(), link.realtime, entered, time.monotonic())
        loop.run()
    except BaseException as exc:  # noqa: BLE001 - report why the exchange ended, then exit
        link.send("crashed", f"{type(exc).__name__}: {exc}")
        raise
    finally:
        sock.close()
        state.close()


class ExchangeProcess:
    """Parent-side handle of one exchange process. See the module docstring.

    name: device name (logs). layout: the shared state's fields (``SharedState``).
    loop_cls / options: the child's loop class (importable, top level) and its keyword options
    (picklable). on_event: called in the reader thread with each event tuple from the child
    (``("log", …)`` events are logged here and not passed on).
    """

    def __init__(
        self,
        name: str,
        layout: Mapping[str, tuple],
        loop_cls: type,
        options: Mapping[str, Any],
        on_event: Callable[[tuple], None],
        *,
        rt_priority: int = 50,
        log: logging.Logger | None = None,
    ) -> None:
        self.name = name
        self.state = SharedState(layout)
        self._layout = dict(layout)
        self._loop_cls = loop_cls
        self._options = dict(options)
        self._on_event = on_event
        self._priority = int(rt_priority)
        self.log = log or logging.getLogger(f"remaster.device.{name}")
        self._conn = None
        self._requests: socket.socket | None = None
        self._proc = None
        self._reader: threading.Thread | None = None
        self._send_lock = threading.Lock()
        self._ready = threading.Event()
        self.pid: int | None = None
        self.realtime = "not started"
        self.crash: str | None = None
        # seconds from ``start()`` to the child's entry point (a fresh interpreter, its imports:
        # the loop's module and, for a script, the parent's main script) and from there to
        # ready (real-time setup, the loop's warm-up); None until ready
        self.startup: dict[str, float] | None = None
        self._t_start = 0.0

    def start(self, sock, ready_timeout: float = 60.0) -> None:
        """Spawn the child with ``sock`` and wait until it is ready for the first packet.

        The parent's copy of ``sock`` is closed once the child has its own.
        """
        self._t_start = time.monotonic()
        ctx = multiprocessing.get_context("spawn")
        requests, child_requests = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        events, child_events = ctx.Pipe(duplex=False)
        proc = ctx.Process(
            target=run_child,
            name=f"{self.name}-exchange",
            args=(child_requests, child_events, os.getpid(), self.name, self.state.name, self._layout, sock,
                  self._loop_cls, self._options, self._priority),
            daemon=False,  # it must outlive a dying parent long enough to stop the robot
        )
        proc.start()
        child_requests.close()
        child_events.close()
        sock.close()  # the child owns the socket now
        self._requests, self._conn, self._proc = requests, events, proc
        atexit.register(self._at_exit)  # runs before multiprocessing joins its children
        self._reader = threading.Thread(target=self._read_events, name=f"{self.name}-events", daemon=True)
        self._reader.start()
        deadline = time.monotonic() + ready_timeout
        while not self._ready.wait(0.05):
            if not proc.is_alive() or time.monotonic() > deadline:
                why = (self.crash or f"exit code {proc.exitcode}") if not proc.is_alive() else "no answer in time"
                self.close(timeout=1.0)
                raise RuntimeError(f"{self.name}: the exchange process did not start ({why})")

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def request(self, *msg) -> None:
        """Send one request tuple to the child. ConnectionError when it is gone."""
        if self._requests is None:
            raise ConnectionError(f"{self.name}: the exchange process is not running")
        payload = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
        with self._send_lock:
            try:
                self._requests.sendall(_LENGTH.pack(len(payload)) + payload)
            except OSError as exc:
                raise ConnectionError(f"{self.name}: the exchange process is gone ({self.crash or exc})") from exc

    def _read_events(self) -> None:
        conn = self._conn
        while True:
            try:
                event = conn.recv()
            except (EOFError, OSError):
                return
            kind = event[0]
            if kind == "log":
                self.log.log(event[1], "%s", event[2])
                continue
            if kind == "ready":
                self.pid, self.realtime = event[1], event[2]
                entered, ready = event[3], event[4]
                self.startup = {"interpreter_and_imports_s": entered - self._t_start,
                                "warm_up_s": ready - entered, "total_s": ready - self._t_start}
                self.log.info("%s: exchange process ready %.0f ms after spawn (interpreter and imports %.0f ms, "
                              "warm-up %.0f ms)", self.name, 1000 * self.startup["total_s"],
                              1000 * self.startup["interpreter_and_imports_s"], 1000 * self.startup["warm_up_s"])
                self._ready.set()
                continue
            if kind == "crashed":
                self.crash = event[1]
                self.log.error("%s: the exchange process failed: %s", self.name, event[1])
            try:
                self._on_event(event)
            except Exception:  # noqa: BLE001 - a handler bug must not stop the event stream
                self.log.exception("%s: handling exchange event %r failed", self.name, kind)

    def _at_exit(self) -> None:
        """The program ends without ``close()``: closing our end of the request socket makes the
        child end on its own (stop, hold, end the session) before the interpreter waits for it."""
        if self._requests is not None:
            self._requests.close()
            self._requests = None
        if self._proc is not None:
            self._proc.join(30.0)
        if self.state is not None and (self._proc is None or not self._proc.is_alive()):
            self.state.close()
            self.state = None

    def close(self, timeout: float = 2.0) -> None:
        """Ask the child to end, wait ``timeout`` s (then terminate it), free the shared block."""
        atexit.unregister(self._at_exit)
        if self._proc is not None:
            try:
                self.request("close")
            except ConnectionError:
                pass
            self._proc.join(timeout)
            if self._proc.is_alive():
                self.log.warning("%s: exchange process did not end; terminating it", self.name)
                self._proc.terminate()  # SIGTERM: it still ends in order if it can
                self._proc.join(5.0)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join(1.0)
            self._proc.close()
            self._proc = None
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(1.0)  # the child's exit closed its end: the reader saw EOF
        self._reader = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._requests is not None:
            self._requests.close()
            self._requests = None
        if self.state is not None:
            self.state.close()
            self.state = None
