"""The simulated cell in a process of its own (``drivers.sim.process``): every fake device in a
child process, real-time where the host permits it, handled from the parent through its API."""

from __future__ import annotations

import logging
import os
import socket

import pytest

from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH
from drivers.sim.faults import FaultError
from drivers.sim.process import CellProcess, enter_realtime
from drivers.sim.running import free_udp_port


def _fifo_permitted() -> bool:
    """Whether this host lets a thread take SCHED_FIFO (asked by a throwaway thread: the test's
    own threads keep their policy)."""
    import threading

    got = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            got.append(True)
        except OSError:
            got.append(False)

    if not hasattr(os, "sched_setscheduler"):
        return False
    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return got[0]


def _policies(pid: int) -> dict[int, int]:
    """Scheduling policy of every thread of process ``pid``."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out[int(tid)] = os.sched_getscheduler(int(tid))
        except (ProcessLookupError, FileNotFoundError):
            pass
    return out


def test_the_cell_runs_in_its_own_process_real_time_where_permitted_and_answers_through_its_api(caplog):
    caplog.set_level(logging.INFO)
    port = free_udp_port()
    cell = CellProcess(DEFAULT_CONFIG_PATH, clock=SimClock(1.0), seed=5,
                       launch_options=dict(fri_port=port, rsi_port=port, fault_timeline=False))
    with cell:
        assert cell.pid != os.getpid() and cell.alive()
        assert cell.seed == 5
        assert {"controller", "mocap", "tracker"} <= set(cell.addresses)
        # the fakes listen in the child: a tracker's TCP port takes a connection
        tracker = cell.addresses["tracker"]
        with socket.create_connection((tracker.host, tracker.port), timeout=10):
            pass
        # the child's threads (the fake Sunrise's cycle, Motive's frames, the tracker's server…)
        policies = _policies(cell.pid)
        assert len(policies) > 3
        if _fifo_permitted():
            assert cell.realtime.startswith("SCHED_FIFO 30")
            assert set(policies.values()) == {os.SCHED_FIFO}, policies  # every thread inherits it
        else:
            assert "not permitted" in cell.realtime
        assert os.sched_getscheduler(0) == os.SCHED_OTHER  # this process keeps its own policy
        # the fault API: the devices hit, or the fakes' own error
        assert cell.inject("drives_off", "controller", 0.5) == ["controller"]
        with pytest.raises(FaultError, match="no device 'laser'"):
            cell.inject("beam_break", "laser")
        assert any(line.startswith("controller") and "fake Sunrise" in line for line in cell.describe())
        assert len(cell.truth_offsets_deg()) == 7 and len(cell.mastering_lines()) == 7
        pid = cell.pid
    assert not cell.alive() and cell.addresses == {}
    # the child's log records reach this process's loggers under their own names
    assert any(r.name == "drivers.sim.process" and f"process {pid} runs at" in r.getMessage() for r in caplog.records)
    assert any(r.name == "drivers.sim.faults" and "drives_off on controller" in r.getMessage() for r in caplog.records)
    with pytest.raises(RuntimeError, match="not started"):
        cell.inject("drives_off")


def test_a_cell_that_cannot_start_raises_its_error_in_the_parent():
    port = free_udp_port()
    cell = CellProcess(DEFAULT_CONFIG_PATH, clock=SimClock(1.0), launch_options=dict(fri_port=port, rsi_port=port, mocap_rate_hz=5.0))
    with pytest.raises(ValueError, match="rate_hz must be within 120–360 Hz"):
        cell.start()
    assert not cell.alive()


def test_enter_realtime_says_normal_priority_when_asked_for_none(caplog):
    caplog.set_level(logging.INFO)
    assert enter_realtime(0, "probe") == "normal priority (rt priority 0)"
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert any("probe: process" in r.getMessage() for r in caplog.records)


def test_the_simulated_cell_of_a_fake_run_lives_in_its_own_process():
    """``acquire run --fake`` / the daemon's ``fake`` cell (``SimulatedCell``): its devices in a
    cell process, described to the run like any cell; the truth for the after-run summary is
    the cell process's (built from the same file and seed as this process's description)."""
    from drivers.sim.running import SimulatedCell

    sim = SimulatedCell(time_scale=4.0, seed=3).start()
    try:
        assert isinstance(sim.launch, CellProcess) and sim.launch.pid != os.getpid()
        cell = sim.describe("fri", [("mocap", "natnet", ""), ("tracker", "emscon", "")])
        assert cell.commander_url.startswith(f"fri://127.0.0.1:{sim.port}?timeout_ms=")
        assert cell.sensor_urls == {"mocap": sim.launch.addresses["mocap"].url,
                                    "tracker": sim.launch.addresses["tracker-emscon"].url}
        assert any("fake Sunrise" in line for line in cell.notes)
        assert sim.truth_offsets_deg() == pytest.approx([float(v) for v in sim.cell.truth.offsets_deg], abs=0)
    finally:
        sim.close()
    assert sim.launch is None
