"""The simulated controller keeps its own mastering: what it reports and where a commanded angle
puts the arm change as entering zero corrections on a real controller changes them. Checked on
the wire (FRI monitoring messages, RSI ``<Rob>`` packets answered with ``<Sen>``), against the
cell's arm position."""

import socket
import threading
import time

import numpy as np
import pytest

from drivers.kuka_fri.messages import FRIMonitoringMessage
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH, SimConfig, load_sim_config
from drivers.sim.launch import SimLaunch
from drivers.sim.mastering import Mastering, MasteringEntry, MasteringError, parse_entry

from test_sim_launch import WAIT_S, udp_listener  # noqa: E402 - the test's folder is on sys.path under pytest


def cell_with(mastering_deg, robot: str | None = None, time_scale: float = 1.0, **changes) -> SimCell:
    data = load_sim_config(DEFAULT_CONFIG_PATH).model_dump()
    data["controller"]["mastering_deg"] = mastering_deg
    if robot is not None:
        data["robot"] = str(DEFAULT_CONFIG_PATH.parent.parent / "robots" / robot)
    data.update(changes)
    return SimCell(SimConfig.model_validate(data), clock=SimClock(time_scale=time_scale))


def fri_measured(sock: socket.socket, expected: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Read FRI monitoring messages until one reports ``expected`` (rad); return it."""
    deadline = time.monotonic() + WAIT_S
    last = None
    while time.monotonic() < deadline:
        msg = FRIMonitoringMessage.decode(sock.recv(65536))
        last = np.array(msg.monitor_data.measured_joint_position)
        if last.size and np.allclose(last, expected, atol=tol):
            return last
    raise AssertionError(f"the controller reported {last}, never {expected}")


def test_a_sunrise_reports_the_arm_through_its_mastering_and_a_new_entry_restarts_it():
    c = np.array([0.0, -0.05, 0.02, 0.0, 0.1, 0.0, -0.03])  # deg, in the cell file
    cell = cell_with(c.tolist())
    q_arm = cell.joint_positions()
    with udp_listener() as fri_client:
        with SimLaunch(cell, fri_port=fri_client.getsockname()[1], max_runtime_s=60) as launch:
            # reported axis angle = arm position − correction, on the wire
            fri_measured(fri_client, q_arm - np.radians(c))
            first = launch.controller
            table = launch.enter_mastering([MasteringEntry("A2", -0.0123), MasteringEntry("7", 0.5)])
            c2 = c + [0, -0.0123, 0, 0, 0, 0, 0.5]
            assert table == pytest.approx(c2)
            assert launch.controller is not first  # the controller restarted with the new table
            fri_measured(fri_client, q_arm - np.radians(c2))
            # the arm did not move: only what the controller calls it changed
            assert cell.joint_positions() == pytest.approx(q_arm, abs=1e-12)
            assert any("mastering" in line for line in launch.describe())


def test_an_rsi_controller_reports_and_commands_axis_angles_through_its_mastering():
    """A KR C4: ``AIPos`` is the arm less the correction; an absolute correction AK moves the axis
    angle to ASPos + AK, which puts the arm at that angle plus the correction."""
    from drivers.kuka_rsi.codec import SenFormatter, parse_rob

    c = np.array([0.0, 0.2, -0.1, 0.0, 0.05, 0.0])
    cell = cell_with(c.tolist(), "kuka_kr6_r900_2.yaml", time_scale=0.25,  # 16 ms wall per 4 ms cycle
                     initial_joint_positions_deg=[0, -90, 90, 0, 45, 0],
                     deflection={"link_masses_kg": None, "compliance_rad_per_nm": None},
                     occlusion={"link_radii_mm": None})
    q_arm = np.degrees(cell.joint_positions())
    sen = SenFormatter(6)
    ak = [0.0, 3.0, 0.0, 0.0, 0.0, 0.0]
    target = q_arm - c + ak  # the commanded axis angles
    seen: list = []
    stop = threading.Event()

    def answer(commander) -> None:  # an RSI commander: every packet answered with the same correction
        while not stop.is_set():
            data, peer = commander.recvfrom(65536)
            seen.append(parse_rob(data))
            commander.sendto(sen.format(ak, False, seen[-1].ipoc), peer)

    with udp_listener() as commander:
        with SimLaunch(cell, rsi_port=commander.getsockname()[1], max_runtime_s=30) as launch:
            krc4 = launch.controller
            thread = threading.Thread(target=answer, args=(commander,), daemon=True)
            thread.start()
            deadline = time.monotonic() + WAIT_S
            while time.monotonic() < deadline and not (
                    len(seen) > 25 and all(np.max(np.abs(np.subtract(r.axis_actual_deg, target))) < 0.005
                                           for r in seen[-25:])):
                time.sleep(0.05)  # until the 15 Hz servo has settled
            first = seen[0]
            assert np.array(first.axis_actual_deg) == pytest.approx(q_arm - c, abs=1e-4)
            assert np.array(first.axis_setpoint_deg) == pytest.approx(q_arm - c, abs=1e-4)
            with pytest.raises(MasteringError, match="commands the robot"):
                launch.enter_mastering([MasteringEntry("A1", 0.1)])  # a program runs: refused
            rob, arm = seen[-1], np.degrees(cell.joint_positions())
            stop.set()
            thread.join(timeout=WAIT_S)
            assert launch.controller is krc4 and krc4.stats().sessions == 1  # one RSI session: ASPos is the start's
    assert np.array(rob.axis_actual_deg) == pytest.approx(target, abs=0.005)
    assert arm == pytest.approx(target + c, abs=0.01)


def test_mastering_lines_and_bad_entries():
    m = Mastering(["A1", "A2", "A3"], "kss", [0.0, 0.1, 0.0])
    assert parse_entry("master A2 -0.0123") == [MasteringEntry("A2", -0.0123)]
    assert parse_entry("$MAMES[2] = $MAMES[2] -0.0123   ; A2: δ = +0.0123°") == [MasteringEntry("2", -0.0123)]
    assert m.after(parse_entry("$MAMES[2] = $MAMES[2] -0.0123")) == pytest.approx([0.0, 0.0877, 0.0])
    assert m.corrections_deg == pytest.approx([0.0, 0.1, 0.0])  # after() does not change the table
    assert m.lines()[1] == "$MAMES[2]: +0.1000° from the mastering as built"
    for bad in ("master A9 0.1", "master A2 zero", "master A2", "$MAMES[2] = $MAMES[3] +0.1"):
        with pytest.raises(MasteringError):
            m.after(parse_entry(bad))
    with pytest.raises(MasteringError, match="3 finite corrections"):
        Mastering(["A1", "A2", "A3"], "kss", [0.0, 0.1])


def test_a_cell_file_with_a_mastering_of_the_wrong_length_is_refused():
    from calib.io.yamlfile import ConfigError

    with pytest.raises(ConfigError, match="controller.mastering_deg: 2 values given, the robot has 7"):
        cell_with([0.0, 0.1])
