"""A ``FakeSunrise`` in an OS process of its own, for the tests that judge the commander's timing.

A real Sunrise cabinet is a machine of its own. A fake started as a thread of the pytest worker
shares that process's interpreter lock with the test's own threads (the test body, the
commander's event reader): when the host preempts one of them while it holds the lock, the
fake's SCHED_FIFO thread waits for it. Beside four CPU hogs its 5 ms send period stretched to
0.75 s (measured), and what a test then sees is the harness starving, not the commander. Here
every thread of the child runs at SCHED_FIFO ``rt_priority`` where permitted (set before the fake
starts, so its threads inherit it); the child serves the test's requests on a pipe.

``FakeSunriseProcess(client_address, rt_priority=60, **fake_options)`` takes ``FakeSunrise``'s
options (picklable: ``scene`` is pickled over and lives in the child). Requests: ``stats``
(a copy of ``FakeSunriseStats``), ``scene`` (a copy of the child's scene), ``overruns``,
``actual_position()``, ``wait_state(state, timeout)``, ``start_commanding()``,
``stop_commanding()``, ``send_malformed(n, kind)``, ``inject_fault(kind)``; ``stop()`` ends the child.
"""

from __future__ import annotations

import multiprocessing
import os

from drivers.kuka_fri.fake import FakeSunrise

#: Wall seconds for the child to start (a fresh interpreter and its imports on a loaded host).
START_TIMEOUT_S = 120.0
#: Wall seconds a request may take beyond its own timeout.
REQUEST_SLACK_S = 30.0

_CALLS = ("actual_position", "wait_state", "start_commanding", "stop_commanding", "send_malformed", "inject_fault")
_VALUES = ("stats", "scene", "overruns")


def _serve(conn, client_address, rt_priority: int, options: dict) -> None:
    """The child: real-time where permitted, the fake started, then one request at a time."""
    if rt_priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
        except OSError:
            pass  # the fake's own thread says so in its log line
    fake = FakeSunrise(client_address, rt_priority=rt_priority, **options)
    try:
        fake.start()
        conn.send(("ok", fake.address))
        while True:
            kind, name, args = conn.recv()
            if kind == "stop":
                fake.stop()
                conn.send(("ok", fake.stats))
                return
            try:
                out = getattr(fake, name)(*args) if kind == "call" else getattr(fake, name)
            except Exception as exc:  # noqa: BLE001 - raised again in the test process
                conn.send(("error", exc))
            else:
                conn.send(("ok", out))
    finally:
        fake.stop()


class FakeSunriseProcess:
    """The parent's handle of a ``FakeSunrise`` running in a child process (see the module docstring)."""

    def __init__(self, client_address: tuple[str, int], *, rt_priority: int = 60, **fake_options) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, client_address, rt_priority, fake_options),
                                 name="fake-sunrise", daemon=True)
        self._child_end = child
        self._final_stats = None
        self.address = None

    def start(self) -> "FakeSunriseProcess":
        self._proc.start()
        self._child_end.close()
        self.address = self._reply(START_TIMEOUT_S)
        return self

    def stop(self):
        """End the fake (closing its session, as ``FakeSunrise.stop`` does); returns its last stats."""
        if self._final_stats is None and self._proc.is_alive():
            self._conn.send(("stop", None, ()))
            self._final_stats = self._reply(REQUEST_SLACK_S)
        self._proc.join(REQUEST_SLACK_S)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)
        return self._final_stats

    def __getattr__(self, name: str):
        if name in _VALUES:
            return self._request("get", name)
        if name in _CALLS:
            return lambda *args: self._request("call", name, *args)
        raise AttributeError(name)

    def _request(self, kind: str, name: str, *args):
        if self._final_stats is not None:
            return self._final_stats if name == "stats" else self._gone()
        self._conn.send((kind, name, args))
        timeout = args[1] if name == "wait_state" else 0.0
        return self._reply(timeout + REQUEST_SLACK_S)

    def _reply(self, timeout: float):
        try:
            if not self._conn.poll(timeout):
                self._gone()
            status, value = self._conn.recv()
        except (EOFError, OSError):
            self._gone()
        if status == "error":
            raise value
        return value

    def _gone(self):
        raise RuntimeError(f"the fake Sunrise process is gone or does not answer (exit code {self._proc.exitcode})")
