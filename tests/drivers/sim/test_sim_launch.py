"""All fakes of a simulated cell on loopback: each speaks its wire protocol, every one of them
reports the same truth, and ``close`` stops them all. Real sockets, bounded waits."""

import socket
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from drivers.kuka_fri.messages import FRIMonitoringMessage
from drivers.natnet import codec as natnet
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH, SimConfig, load_sim_config
from drivers.sim.launch import SimLaunch
from drivers.tracker.codec import LineCodec, MeasurePoint, PointReply

WAIT_S = 5.0


def udp_listener() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(WAIT_S)
    return sock


def natnet_frame(port: int) -> natnet.FrameOfData:
    """CONNECT to a fake Motive on ``port`` and return the first frame it streams to us."""
    with udp_listener() as sock:
        sock.sendto(natnet.encode_packet(natnet.Connect(layout="ping")), ("127.0.0.1", port))
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            msg = natnet.decode_packet(sock.recv(65536), (3, 0, 0, 0))
            if isinstance(msg, natnet.FrameOfData):
                return msg
    raise AssertionError("no frame of data from the fake Motive")


def tracker_point(host: str, port: int) -> PointReply:
    codec = LineCodec()
    with socket.create_connection((host, port), timeout=WAIT_S) as conn:
        conn.sendall(codec.encode_request(1, MeasurePoint()))
        buf = bytearray()
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            buf += conn.recv(4096)
            for line in LineCodec.split_frames(buf):
                rid, reply = codec.decode_reply(line)
                if rid == 1:
                    return reply
    raise AssertionError("no MEAS reply from the fake tracker")


def test_every_fake_reports_the_same_cell():
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=4)
    q = cell.joint_positions()
    with udp_listener() as fri_client:
        with SimLaunch(cell, fri_port=fri_client.getsockname()[1], max_runtime_s=30) as launch:
            assert set(launch.addresses) == {"mocap", "tracker", "controller"}
            assert all(a.host.startswith("127.") for a in launch.addresses.values())  # loopback (the fake Sunrise: 127.0.0.2, its FRI port)

            # The controller streams the cell's joint positions to the FRI client.
            msg = FRIMonitoringMessage.decode(fri_client.recv(65536))
            measured = np.array(msg.monitor_data.measured_joint_position)
            assert measured == pytest.approx(q, abs=1e-9)

            # The motion-capture bar sees the infrared marker where the truth puts it (metres).
            frame = natnet_frame(launch.addresses["mocap"].port)
            truth_mocap = cell.true_marker_positions(q, frame="mocap")[cell.marker_names.index("sir")]
            assert len(frame.labeled_markers) == 4  # the SIR first, then its rigid-body cluster
            (body,) = frame.rigid_bodies  # tracked from the four: its origin is the SIR
            assert body["pos"] * 1000 == pytest.approx(truth_mocap, abs=0.2)
            assert frame.labeled_markers["pos"][0] * 1000 == pytest.approx(truth_mocap, abs=0.2)

            # The tracker measures the retroreflector in its own frame (mm).
            t = launch.addresses["tracker"]
            point = tracker_point(t.host, t.port)
            truth_tracker = cell.true_marker_positions(q, frame="tracker")[cell.marker_names.index("smr")]
            assert [point.x, point.y, point.z] == pytest.approx(truth_tracker, abs=0.1)
            tracker_port = t.port
    # Everything is stopped: the tracker refuses connections, addresses are gone.
    assert launch.addresses == {}
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", tracker_port), timeout=WAIT_S).close()


def kr6_cell(time_scale: float) -> SimCell:
    data = load_sim_config(DEFAULT_CONFIG_PATH).model_dump()
    data["robot"] = str(DEFAULT_CONFIG_PATH.parent.parent / "robots" / "kuka_kr6_r900_2.yaml")
    data["initial_joint_positions_deg"] = [0, -90, 90, 0, 45, 0]
    data["deflection"] = {"link_masses_kg": None, "compliance_rad_per_nm": None}
    data["occlusion"] = {"link_radii_mm": None}
    return SimCell(SimConfig.model_validate(data), clock=SimClock(time_scale=time_scale))


def test_a_kss_robot_gets_an_rsi_controller_that_is_restarted_after_a_timeout():
    cell = kr6_cell(time_scale=20)  # 100 late cycles take 20 ms
    with udp_listener() as silent_commander:  # receives <Rob> packets, never answers
        with SimLaunch(cell, rsi_port=silent_commander.getsockname()[1], max_runtime_s=30,
                       operator=False) as launch:
            assert launch.addresses["controller"].kind == "rsi"
            assert b"<Rob" in silent_commander.recv(65536)
            first = launch.controller
            assert first.wait_stopped(WAIT_S)  # 100 late answers: RSI timeout
            assert "RSI timeout" in first.stats().stopped_reason
            assert launch.controller is first  # nobody restarts it without the operator
            assert launch.restart_stopped_rsi()
            second = launch.controller
            assert second is not first
            deadline = time.monotonic() + WAIT_S
            while second.stats().sent == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert second.stats().sent > 0  # the new session streams to the same commander port


def test_the_simulated_operator_restarts_a_stopped_rsi_program_by_itself():
    cell = kr6_cell(time_scale=20)
    with udp_listener() as silent_commander:
        with SimLaunch(cell, rsi_port=silent_commander.getsockname()[1], max_runtime_s=30) as launch:
            first = launch.controller
            assert first.wait_stopped(WAIT_S)
            deadline = time.monotonic() + WAIT_S
            while launch.controller is first and time.monotonic() < deadline:
                time.sleep(0.02)
            assert launch.controller is not first and launch.operator_restarts >= 1


def test_an_rsi_commander_moves_the_robot_the_sensors_see():
    """Answer the fake KR C4's packets with an absolute A1 correction of +10°: its servo moves
    the cell's robot, so the markers move for every sensor."""
    from drivers.kuka_rsi.codec import SenFormatter, parse_rob

    cell = kr6_cell(time_scale=0.25)  # 16 ms wall per 4 ms cycle: on time on a busy machine
    q0 = cell.joint_positions()
    before = cell.true_marker_positions(q0, frame="mocap")
    sen = SenFormatter(6)
    correction = [10.0, 0, 0, 0, 0, 0]
    with udp_listener() as commander:
        with SimLaunch(cell, rsi_port=commander.getsockname()[1], max_runtime_s=30) as launch:
            controller = launch.controller
            for _ in range(120):  # 0.48 s simulated: the 15 Hz servo has settled
                data, peer = commander.recvfrom(65536)
                commander.sendto(sen.format(correction, False, parse_rob(data).ipoc), peer)
            assert controller.stats().late < 10
    q = cell.joint_positions()
    assert np.degrees(q - q0) == pytest.approx(correction, abs=0.05)
    moved = np.linalg.norm(cell.true_marker_positions(q, frame="mocap") - before, axis=-1)
    assert np.all(moved > 10.0)


@pytest.mark.parametrize("bad", [{"fri_port": 0}, {"rsi_port": 70000}, {"max_runtime_s": 0},
                                 {"controller_rt_priority": -1}, {"controller_rt_priority": 100}])
def test_launch_refuses_bad_settings(bad):
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH)
    with pytest.raises(ValueError, match=next(iter(bad))):
        SimLaunch(cell, **bad)


def test_acquire_sim_prints_the_addresses_and_stops_by_itself():
    from acquire.cli import app

    with udp_listener() as fri_client:
        port = fri_client.getsockname()[1]
        result = CliRunner().invoke(
            app, ["sim", "--seed", "2", "--duration", "0.5", "--fri-port", str(port), "--show-truth"]
        )
    assert result.exit_code == 0, result.output
    out = result.output
    assert "natnet://127.0.0.1:" in out and "socket://127.0.0.1:" in out
    assert f"sending to the FRI client on 127.0.0.1:{port}" in out
    truth = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=2).truth
    assert f"A1 {truth.offsets_deg[0]:+.4f}" in out
    assert "stopped; final joints" in out


def test_acquire_sim_reports_a_bad_config(tmp_path):
    from acquire.cli import app

    bad = tmp_path / "cell.yaml"
    bad.write_text("robot: nowhere.yaml\nsensors: []\n", encoding="utf-8")
    result = CliRunner().invoke(app, ["sim", "--config", str(bad), "--duration", "0.1"])
    assert result.exit_code == 2
    assert "sensors" in result.output


def test_a_tracker_can_answer_emscon_and_the_line_protocol_at_once():
    from drivers.emscon.client import EmsconSensor
    from drivers.tracker.client import TrackerSensor

    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=4, clock=SimClock(50.0))
    with SimLaunch(cell, controller=False, tracker_protocols={"tracker": ("line", "emscon")}) as launch:
        line_addr, em_addr = launch.addresses["tracker"], launch.addresses["tracker-emscon"]
        assert (line_addr.kind, em_addr.kind) == ("tracker", "emscon")
        assert em_addr.url.startswith("emscon://127.0.0.1:")
        truth = cell.true_marker_positions(cell.joint_positions(), frame="tracker")
        with EmsconSensor(em_addr.url) as em, TrackerSensor.from_url(line_addr.url) as line:
            a = em.measure("smr", 200, 10.0).mean_mm
            b = line.measure("smr", 200, 10.0).mean_mm
        assert launch.emscon["tracker"][0].tracker is launch.trackers["tracker"][0]  # one simulated tracker
    i = cell.marker_names.index(cell.sensor_markers("tracker")[0])
    # the cell adds its noise (σ ≈ 0.02 mm per axis here) to each observation and an average
    # interpolates two observations, so each mean is within a few hundredths of the truth
    assert np.allclose(a, truth[i], atol=0.1) and np.allclose(b, truth[i], atol=0.1)
    assert not np.allclose(a, b, atol=1e-6)  # two measurements, not one copied
    with pytest.raises(ValueError, match="allowed: line, emscon"):
        SimLaunch(cell, controller=False, tracker_protocols={"tracker": ("leica",)})



def _fifo_permitted() -> bool:
    """Whether this host lets a thread of ours run at SCHED_FIFO (tried on a throw-away thread)."""
    import os
    import threading

    result = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            result.append(True)
        except OSError:
            result.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return result[0]


def test_the_fake_controller_keeps_its_cycle_at_sched_fifo_where_the_host_permits_it():
    """At load 15–30 the fake Sunrise at normal priority stretched its 5 ms send period to 14–22 ms
    and missed its watchdogs (tests/bench/bench_sim_cycle.py measures it under four CPU hogs): its
    cycle runs at SCHED_FIFO where permitted, as the commander's exchange does, else at normal
    priority with a warning."""
    import os
    import threading

    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH)
    with udp_listener() as fri_client:
        with SimLaunch(cell, fri_port=fri_client.getsockname()[1], max_runtime_s=30) as launch:
            assert launch.controller_rt_priority == 30
            fri_client.recv(65536)  # the cycle runs
            (sender,) = [t for t in threading.enumerate() if t.name == "fake-sunrise"]
            policy = os.sched_getscheduler(sender.native_id)
    assert policy == (os.SCHED_FIFO if _fifo_permitted() else os.SCHED_OTHER)
