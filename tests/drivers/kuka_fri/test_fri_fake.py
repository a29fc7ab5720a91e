"""``FakeSunrise`` on its own, driven by a hand-written client socket: what it sends, how it
grades answers (late, missing, bad counter, malformed), its state machine and its servo."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest
from fri_helpers import iiwa14_limits

from drivers.errors import ProtocolError
from drivers.kuka_fri.fake import FakeSunrise
from drivers.kuka_fri.messages import (
    COMMAND_MESSAGE_ID,
    CommandData,
    ConnectionQuality,
    DriveState,
    FRICommandMessage,
    FRIMonitoringMessage,
    MessageHeader,
    SafetyState,
    SessionState,
    decode_monitoring,
)

Q0 = np.radians([5.0, 10.0, -5.0, -30.0, 0.0, 20.0, 0.0])


class RawClient:
    """A client socket whose answers the test writes by hand."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.seq = 0
        self.controller = None

    @property
    def address(self):
        return self.sock.getsockname()

    def receive(self) -> FRIMonitoringMessage:
        data, self.controller = self.sock.recvfrom(4096)
        return decode_monitoring(data)

    def answer(self, reflected: int, q=None, raw: bytes | None = None) -> None:
        if raw is None:
            msg = FRICommandMessage(
                MessageHeader(COMMAND_MESSAGE_ID, self.seq, reflected),
                None if q is None else CommandData(joint_position=tuple(np.asarray(q, dtype=float))),
            )
            raw = msg.encode()
            self.seq += 1
        self.sock.sendto(raw, self.controller)

    def echo_until(self, fake: FakeSunrise, state: SessionState, n_max: int = 400, key="commanded"):
        """Answer every message with the controller's position until ``state`` is reported."""
        for _ in range(n_max):
            m = self.receive()
            if m.connection_info.session_state == state:
                return m
            if m.connection_info.session_state != SessionState.IDLE:
                q = m.ipo_data.joint_position if key == "ipo" and m.ipo_data.joint_position else \
                    m.monitor_data.commanded_joint_position
                self.answer(m.header.sequence_counter, q)
        raise AssertionError(f"fake never reached {state.name}; it is {fake.session_state.name}")

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def client():
    c = RawClient()
    yield c
    c.close()


def make_fake(client, **kw) -> FakeSunrise:
    kw.setdefault("limits", iiwa14_limits())
    kw.setdefault("initial_position_rad", Q0)
    return FakeSunrise(client.address, **kw)


def test_monitoring_messages_carry_what_a_client_needs(client):
    with make_fake(client, send_period_ms=4, receive_multiplier=2, idle_cycles=2):
        msgs = [client.receive() for _ in range(6)]
    # the application opens the session: no IDLE message before it (an SDK example would quit)
    states = [m.connection_info.session_state for m in msgs]
    assert states == [SessionState.MONITORING_WAIT] * 6
    assert [m.header.sequence_counter for m in msgs] == list(range(6))
    # sent from the FRI port (the client's), as Sunrise does
    assert client.controller == ("127.0.0.2", client.address[1])
    m = msgs[-1]
    assert (m.connection_info.send_period, m.connection_info.receive_multiplier) == (4, 2)
    assert m.connection_info.quality == ConnectionQuality.POOR  # nobody answered yet
    assert m.robot_info.number_of_joints == 7
    assert m.robot_info.drive_state == (DriveState.ACTIVE,) * 7
    assert m.robot_info.safety_state == SafetyState.NORMAL_OPERATION
    np.testing.assert_allclose(m.monitor_data.measured_joint_position, Q0)
    np.testing.assert_allclose(m.monitor_data.commanded_joint_position, Q0)
    stamps = [x.monitor_data.timestamp.seconds for x in msgs]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert abs(stamps[-1] - time.time()) < 60.0  # the controller's clock: time of day


def test_stopping_the_application_closes_the_session_with_idle_messages(client):
    fake = make_fake(client, closing_idle_messages=3).start()
    try:
        assert client.receive().connection_info.session_state == SessionState.MONITORING_WAIT
    finally:
        fake.stop()
    states = []
    client.sock.settimeout(0.5)
    with pytest.raises(socket.timeout):
        while True:
            states.append(client.receive().connection_info.session_state)
    assert states[-3:] == [SessionState.IDLE] * 3
    assert SessionState.IDLE not in states[:-3]


def test_the_session_gets_ready_only_when_answers_come(client):
    with make_fake(client, ready_after=5) as fake:
        for _ in range(30):  # silent client: stays waiting, quality poor
            m = client.receive()
        assert m.connection_info.session_state == SessionState.MONITORING_WAIT
        assert m.connection_info.quality == ConnectionQuality.POOR
        m = client.echo_until(fake, SessionState.MONITORING_READY)
        assert fake.stats.answers >= 5


def test_late_answers_degrade_quality_and_drop_the_session(client):
    with make_fake(client, max_missed=10) as fake:
        # the session gets ready only at GOOD or better (how many in-time answers that took
        # depends on how busy the machine is: the quality is judged against this message's)
        ready = client.echo_until(fake, SessionState.MONITORING_READY)
        assert ready.connection_info.quality >= ConnectionQuality.GOOD
        previous = None
        qualities = []
        late = 0
        for _ in range(200):  # answer each message only after the next one arrived: late
            m = client.receive()
            qualities.append(m.connection_info.quality)
            if m.connection_info.session_state == SessionState.MONITORING_WAIT:
                break
            if previous is not None:
                client.answer(previous.header.sequence_counter, previous.monitor_data.commanded_joint_position)
                late += 1
            previous = m
        assert m.connection_info.session_state == SessionState.MONITORING_WAIT
        # every window since the ready message was missed (its own and each one answered late),
        # so the session drops after max_missed of them and never earlier
        assert len(qualities) == 10 and late == 8
        deadline = time.monotonic() + 10.0  # the fake reads answers every cycle (5 ms) when it runs
        while fake.stats.answers < client.seq and time.monotonic() < deadline:
            time.sleep(0.005)
        assert fake.stats.answers == client.seq
        assert fake.stats.missed_windows >= 10
        assert fake.stats.late_answers >= late
        assert fake.stats.session_drops == 1
        # each missed window makes the quality worse or leaves it, down to below GOOD
        assert all(a >= b for a, b in zip([ready.connection_info.quality] + qualities, qualities))
        assert qualities[-1] < ConnectionQuality.GOOD


def test_bad_counters_and_malformed_answers_are_counted_not_applied(client):
    with make_fake(client) as fake:
        client.echo_until(fake, SessionState.MONITORING_READY)
        m = client.receive()
        client.answer(m.header.sequence_counter + 1000, Q0)
        client.answer(0, raw=b"\x0a\x05\x08")
        client.answer(0, raw=FRIMonitoringMessage(MessageHeader(0x245142, 0, 0)).encode())  # wrong type
        client.receive()
        client.receive()
        assert fake.stats.bad_reflections == 1
        assert fake.stats.malformed_answers == 2


def test_answers_in_idle_are_violations_but_answers_in_flight_at_a_close_are_late(client):
    with make_fake(client, idle_cycles=50, closing_idle_messages=5) as fake:
        client.echo_until(fake, SessionState.MONITORING_READY)
        before = client.receive()
        fake.close_session()
        # an answer to a message sent before the close: in flight, not an IDLE violation
        client.answer(before.header.sequence_counter, Q0)
        m = client.receive()
        while m.connection_info.session_state != SessionState.IDLE:
            m = client.receive()
        client.answer(m.header.sequence_counter, Q0)  # KUKA's SDK sends nothing in IDLE
        client.receive()
        client.receive()
        assert fake.stats.answers_in_idle == 1
        assert fake.stats.violations == ["client answered while the session is IDLE"]
        assert fake.stats.late_answers >= 1


def test_commanding_needs_the_ipo_echo_then_takes_commands_through_the_servo(client):
    with make_fake(client, limits=None, commanding_wait_cycles=5) as fake:
        client.echo_until(fake, SessionState.MONITORING_READY)
        with pytest.raises(RuntimeError, match="needs MONITORING_READY"):
            fake.close_session() or fake.start_commanding()
        client.echo_until(fake, SessionState.MONITORING_READY)
        fake.start_commanding()
        for _ in range(20):  # a wrong echo keeps the session waiting
            m = client.receive()
            client.answer(m.header.sequence_counter, np.asarray(m.ipo_data.joint_position or Q0) + 0.01)
        assert fake.session_state == SessionState.COMMANDING_WAIT
        assert any("does not echo the ipo position" in v for v in fake.stats.violations)
        m = client.echo_until(fake, SessionState.COMMANDING_ACTIVE, key="ipo")
        # a 0.02 rad step, held: the servo overshoots a little and settles
        step = Q0 + 0.02
        trace = []
        client.answer(m.header.sequence_counter, Q0)
        for _ in range(100):  # 0.5 s
            m = client.receive()
            trace.append(np.asarray(m.monitor_data.measured_joint_position))
            client.answer(m.header.sequence_counter, step)
        err = np.asarray(trace)[:, 0] - step[0]
        assert err[0] < -0.015  # starts a step behind
        assert 0.0002 < err.max() < 0.003  # overshoot of a few percent (ζ = 0.7)
        assert abs(err[-1]) < 1e-4  # settled after 0.5 s


def test_a_too_fast_command_aborts_the_motion(client):
    with make_fake(client, commanding_wait_cycles=3) as fake:
        client.echo_until(fake, SessionState.MONITORING_READY)
        fake.start_commanding()
        m = client.echo_until(fake, SessionState.COMMANDING_ACTIVE, key="ipo")
        client.answer(m.header.sequence_counter, Q0)
        m = client.receive()
        jump = Q0.copy()
        jump[6] += 0.05  # 10 rad/s at 5 ms: far above 2.36 rad/s
        client.answer(m.header.sequence_counter, jump)
        client.receive()
        m = client.receive()
        assert m.connection_info.session_state == SessionState.MONITORING_READY
        assert "commanded speed 10 rad/s on A7 above 2.356 rad/s" in fake.stats.violations[-1]


def test_fake_refuses_non_loopback_and_bad_settings():
    with pytest.raises(ValueError, match="only talks to loopback"):
        FakeSunrise(("192.168.0.10", 30200))
    with pytest.raises(ValueError, match="send_period_ms must be an integer in \\[1, 100\\]"):
        FakeSunrise(("127.0.0.1", 30200), send_period_ms=0)
    with pytest.raises(ValueError, match="kind must be"):
        FakeSunrise(("127.0.0.1", 30200)).inject_fault("meteor")


def test_malformed_hook_sends_bytes_our_decoder_rejects(client):
    with make_fake(client) as fake:
        client.receive()
        fake.send_malformed(3, "truncated")
        fake.send_malformed(1, "wrong_id")
        fake.send_malformed(1, "garbage")
        bad = 0
        for _ in range(10):
            data, _ = client.sock.recvfrom(4096)
            try:
                decode_monitoring(data)
            except ProtocolError:
                bad += 1
        assert bad == 5


def test_a_client_started_after_the_fake_can_still_bind_its_port_on_every_address():
    """KUKA's SDK binds INADDR_ANY:port without SO_REUSEADDR: the fake must not hold the port
    before a client does. Such a client then hears the fake from an ephemeral port."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    with FakeSunrise(("127.0.0.1", port), initial_position_rad=Q0):
        time.sleep(0.7)  # past a port claim attempt with no client
        sdk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sdk.bind(("0.0.0.0", port))
            sdk.settimeout(2.0)
            data, sender = sdk.recvfrom(4096)
            time.sleep(0.7)  # another claim attempt: the port is held on every address
            data, sender = sdk.recvfrom(4096)
        finally:
            sdk.close()
    assert decode_monitoring(data).connection_info.session_state == SessionState.MONITORING_WAIT
    assert sender[0] == "127.0.0.1" and sender[1] != port
