"""``SendLoop``: the fake Sunrise's sending thread, paced like a controller.

Every ``period_s`` wall seconds it collects the answers that arrived, runs one controller cycle
and sends its message, if any (after the cycle's jitter). Descheduled past a send time, it
re-anchors instead of catching up (a real controller never sends two messages back to back),
so the client always has a whole period to answer; ``overruns`` counts those. After
``max_runtime_s`` the robot application ends: ``end`` closes the session and the loop runs
until ``closed`` says the closing IDLE messages are out. The thread asks for SCHED_FIFO
``rt_priority`` when permitted (0: normal priority).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Callable, Optional

from drivers.kuka_fri.fake_port import FriPort

log = logging.getLogger("remaster.fake.sunrise")


class SendLoop:
    """cycle() → (message bytes or None, jitter wall s); on_answer(bytes): one answer datagram;
    end(why): the application ends; closed(): nothing more to send before the loop may stop;
    stats: the fake's ``FakeSunriseStats`` (for the last log line)."""

    def __init__(self, port: FriPort, *, period_s: float, max_runtime_s: float, rt_priority: int,
                 cycle: Callable[[], tuple[Optional[bytes], float]], on_answer: Callable[[bytes], None],
                 end: Callable[[str], None], closed: Callable[[], bool], stats) -> None:
        self.port = port
        self.period_s = period_s
        self.max_runtime_s = max_runtime_s
        self.rt_priority = rt_priority
        self._cycle, self._on_answer, self._end, self._closed = cycle, on_answer, end, closed
        self.overruns = 0
        self.stats = stats
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fake-sunrise", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        """End the thread (waits up to 5 s)."""
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _set_realtime(self) -> None:
        if self.rt_priority <= 0 or not hasattr(os, "sched_setscheduler"):
            return
        try:  # pid 0: this thread (Linux)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
            log.info("fake Sunrise: its cycle runs at SCHED_FIFO %d", self.rt_priority)
        except OSError as exc:
            log.warning("fake Sunrise: SCHED_FIFO %d not permitted (%s); normal priority: its send period may "
                        "stretch on a loaded host", self.rt_priority, exc.strerror or exc)

    def _run(self) -> None:
        self._set_realtime()
        port, period = self.port, self.period_s
        t_end = time.monotonic() + self.max_runtime_s
        next_t = time.monotonic()
        ending = False
        while not self._stop.is_set():
            port.claim(self._on_answer)
            if not ending and time.monotonic() >= t_end:
                ending = True  # the robot application ends: it closes the session first
                self._end(f"robot application ended after max_runtime_s={self.max_runtime_s:g} s")
            if ending and self._closed():
                break
            port.collect_until(next_t, self._on_answer)
            data, jitter = self._cycle()
            if data is not None:
                if jitter:
                    time.sleep(jitter)
                port.send(data)
            next_t += period
            now = time.monotonic()
            if next_t < now + 0.5 * period:
                self.overruns += 1
                next_t = now + period
        log.info("fake Sunrise: stopped after %d messages", self.stats.sent)
