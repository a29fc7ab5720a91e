"""The exchange-process machinery: the seqlocked shared state and the real-time set-up."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest

from drivers import exchange
from drivers.exchange import SharedState, answer_log, read_state, ring_in_order, ring_timing


class RecordingLink:
    name = "rsi"

    def __init__(self) -> None:
        self.lines: list[tuple[int, str]] = []
        self.realtime = "not set"

    def log(self, level, fmt, *args) -> None:
        self.lines.append((level, fmt % args))


def test_shared_state_round_trips_fields_between_two_handles():
    owner = SharedState({"t": (), "q": (3,), "ring": (4,)})
    other = SharedState({"t": (), "q": (3,), "ring": (4,)}, name=owner.name)
    try:
        with other.write():
            other["t"][0] = 2.5
            other["q"][:] = [1.0, 2.0, 3.0]
        got = owner.read(("t", "q", "ring"))
        assert got["t"].tolist() == [2.5] and got["q"].tolist() == [1.0, 2.0, 3.0] and got["ring"].tolist() == [0] * 4
        got["q"][0] = 99.0  # a copy: the block is untouched
        assert owner["q"][0] == 1.0
    finally:
        other.close()
        owner.close()


def test_a_read_never_returns_a_half_written_state():
    state = SharedState({"q": (2,)})
    try:
        section = state.write()
        section.__enter__()  # a writer stopped half-way (odd sequence number)
        state["q"][0] = 1.0
        with pytest.raises(TimeoutError, match="kept changing"):
            state.read(("q",), retries=50)
        section.__exit__(None, None, None)
        assert state.read(("q",))["q"].tolist() == [1.0, 0.0]
    finally:
        state.close()


BUSY_LAYOUT = {**{f"s{i}": () for i in range(30)}, "ring": (1 << 16,), "actual": (7,), "cmd": (7,)}


def _busy_writer(name: str, started, stop) -> None:
    """Child process: as an exchange answering a lockstep controller does, write a new state
    (the same number into every small field, one ring entry) about every 0.1 ms."""
    import time

    st = SharedState(BUSY_LAYOUT, name=name)
    i = 0
    while not stop.is_set():
        i += 1
        with st.write():
            for k in BUSY_LAYOUT:
                if k != "ring":
                    st[k][:] = i
            st["ring"][i % (1 << 16)] = i
        if i == 1:
            started.set()
        time.sleep(50e-6)
    st.close()


def test_the_latest_state_is_read_whole_beside_a_busy_writer():
    # The small fields lie together before the ring: a read of the latest state is one copy of
    # a short span, and every field of it comes from the same write.
    import multiprocessing as mp

    owner = SharedState(BUSY_LAYOUT)
    ctx = mp.get_context("spawn")
    started, stop = ctx.Event(), ctx.Event()
    child = ctx.Process(target=_busy_writer, args=(owner.name, started, stop), daemon=True)
    child.start()
    try:
        assert started.wait(60), "the writer process did not start"
        names = tuple(f"s{i}" for i in range(30)) + ("actual", "cmd")
        values = []
        for _ in range(2000):
            got = owner.read(names)
            flat = np.concatenate([got[k].ravel() for k in names])
            assert (flat == flat[0]).all(), "fields of different writes in one read"
            values.append(flat[0])
        assert values[-1] > values[0] > 0  # the writer kept writing meanwhile
    finally:
        stop.set()
        child.join(10)
        owner.close()


@pytest.fixture
def no_mlock(monkeypatch):
    """(never lock the test process's memory)"""
    monkeypatch.setattr(exchange, "lock_memory", lambda: "memory not locked (test)")


def test_sched_fifo_refusal_is_logged_clearly_with_the_fix(monkeypatch, no_mlock):
    def refuse(pid, policy, param):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    link = RecordingLink()
    exchange.set_realtime(link, 40)
    assert link.realtime.startswith("normal priority (SCHED_FIFO 40 not permitted")
    (level, text), = link.lines
    assert level == logging.WARNING and "LimitRTPRIO=40" in text and "may answer late under load" in text


def test_no_priority_asked_is_said_without_a_warning(no_mlock):
    link = RecordingLink()
    exchange.set_realtime(link, 0)
    assert link.realtime.startswith("normal priority (rt_priority=0)")
    assert [lvl for lvl, _ in link.lines] == [logging.INFO]


def test_ring_in_order_returns_the_last_entries_oldest_first():
    ring = np.zeros(4)
    for k in range(6):  # writes 0..5: slots hold 4, 5, 2, 3
        ring[k % 4] = k
    np.testing.assert_array_equal(ring_in_order(ring, 6), [2, 3, 4, 5])
    np.testing.assert_array_equal(ring_in_order(ring, 3), [4, 5, 2])  # not yet wrapped: first 3 slots
    assert ring_in_order(ring, 0).shape == (0,)


def test_ring_timing_gives_the_period_and_latency_figures_of_the_cycles_kept():
    rx, lat = np.zeros(4), np.zeros(4)
    for k in range(6):  # arrivals every 4 ms, latencies 0.1 .. 0.6 ms: the ring keeps the last 4
        rx[k % 4], lat[k % 4] = 0.004 * k, 1e-4 * (k + 1)
    t = ring_timing(6, rx, lat)
    assert (t["packets"], t["window"]) == (6, 4)
    assert t["period_mean_s"] == pytest.approx(0.004) and t["period_max_s"] == pytest.approx(0.004)
    assert t["period_std_s"] == pytest.approx(0.0, abs=1e-12)
    assert t["latency_p50_s"] == pytest.approx(4.5e-4) and t["latency_max_s"] == pytest.approx(6e-4)
    empty = ring_timing(0, np.zeros(4), np.zeros(4))
    assert (empty["window"], empty["latency_max_s"], empty["period_mean_s"]) == (0, 0.0, 0.0)


def test_no_exchange_reads_as_no_state_and_an_empty_answer_log():
    assert read_state(None, ("count",)) is None
    count, arrived, latency = answer_log(None)
    assert count == 0 and arrived.shape == latency.shape == (0,)


def test_the_exchange_process_does_not_trace_allocations_a_traced_parent_asked_for():
    import subprocess
    import sys

    # spawn passes the environment on: a child of a daemon run with PYTHONTRACEMALLOC=1 starts traced
    code = ("import tracemalloc; from drivers.exchange import stop_tracing; "
            "print(tracemalloc.is_tracing(), end=' '); stop_tracing(); print(tracemalloc.is_tracing())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, PYTHONTRACEMALLOC="1"))
    assert out.stdout.split() == ["True", "False"], out.stderr
