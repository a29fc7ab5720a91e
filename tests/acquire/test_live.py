"""The live view, tested with a real WebSocket client (``websockets``) speaking the Foxglove
WebSocket protocol to the SDK's server: serverInfo / advertise → subscribe → binary message
data (opcode 0x01, uint32 subscription id, uint64 timestamp, payload).

The client offers both subprotocol names, as the Foxglove app does: ``foxglove.sdk.v1`` (what
foxglove-sdk ≥ 0.x and foxglove_bridge ≥ 3.2 require; the same messages) and the older
``foxglove.websocket.v1``."""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

pytest.importorskip("foxglove", reason="the live view needs foxglove-sdk")
websockets_sync = pytest.importorskip("websockets.sync.client", reason="the live tests need the websockets package")
import websockets.exceptions  # noqa: E402

from acquire.record import foxglove_view as fv  # noqa: E402
from acquire.live.foxglove_server import LiveServer  # noqa: E402
from acquire.record.recorder import RunLog  # noqa: E402
from calib.robot.kinematics import Chain  # noqa: E402
from calib.robot.model import load_robot_model  # noqa: E402

from run_helpers import popen, small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest

ROOT = Path(__file__).resolve().parents[2]
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01


class FoxgloveClient:
    """A minimal Foxglove WebSocket client: channels by topic, subscribe, message data."""

    def __init__(self, url: str, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._stack = contextlib.ExitStack()
                self.ws = self._stack.enter_context(websockets_sync.connect(url, subprotocols=SUBPROTOCOLS, open_timeout=10))
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        assert self.ws.subprotocol in SUBPROTOCOLS
        self.channels: dict[str, dict] = {}
        self.server_info: dict | None = None
        self._subs: dict[int, str] = {}
        self._next = 1
        self.notices: list[str] = []

    def _handle_text(self, text: str) -> None:
        msg = json.loads(text)
        if msg["op"] == "serverInfo":
            self.server_info = msg
        elif msg["op"] == "advertise":
            for ch in msg["channels"]:
                self.channels[ch["topic"]] = ch
        elif msg["op"] in ("status", "unadvertise"):  # kept for a failure's message
            self.notices.append(text[:300])

    def recv(self, timeout: float) -> tuple[str, int, bytes] | None:
        """The next message data frame (topic, timestamp ns, payload), or None on timeout."""
        try:
            frame = self.ws.recv(timeout=timeout)
        except TimeoutError:
            return None
        if isinstance(frame, str):
            self._handle_text(frame)
            return None
        assert frame[0] == MESSAGE_DATA, f"unexpected binary opcode {frame[0]}"
        sub_id, t_ns = struct.unpack_from("<IQ", frame, 1)
        return self._subs[sub_id], t_ns, bytes(frame[13:])

    def wait_channels(self, topics: set[str], timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not topics <= set(self.channels):
            assert time.monotonic() < deadline, f"not advertised: {sorted(topics - set(self.channels))}"
            self.recv(0.2)

    def subscribe(self, *topics: str) -> None:
        subs = []
        for t in topics:
            sid = self._next
            self._next += 1
            self._subs[sid] = t
            subs.append({"id": sid, "channelId": self.channels[t]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def close(self) -> None:
        self._stack.close()


def test_live_clients_receive_exactly_the_logged_messages(tmp_path):
    path = tmp_path / "run.mcap"
    with LiveServer("127.0.0.1", 0, name="test cell") as server:
        lg = RunLog.create(path, run_id="r", plan_text="", model_text="", metadata={}, live=server)
        names = [f"A{i + 1}" for i in range(7)]
        lg.record_joint_state("fri", np.zeros(7), names=names, device_time=-1.0)  # advertises /joint_state
        client = FoxgloveClient(server.url)
        try:
            client.wait_channels({"/joint_state", "/run/sample", "/log"})
            assert client.server_info["name"] == "test cell"
            ch = client.channels["/joint_state"]
            assert (ch["encoding"], ch["schemaName"], ch["schemaEncoding"]) == ("json", "remaster.JointState", "jsonschema")
            assert json.loads(ch["schema"]) == fv.JOINT_STATE_SCHEMA
            client.subscribe("/joint_state", "/run/sample")
            deadline = time.monotonic() + 30
            while True:  # until the subscription is in effect on the server
                lg.record_joint_state("fri", np.zeros(7), names=names, device_time=-1.0)
                got = client.recv(0.1)
                if got is not None:
                    break
                assert time.monotonic() < deadline, "no message data after subscribing"
            rng = np.random.default_rng(2)
            for i in range(20):
                lg.record_joint_state("fri", rng.normal(size=7), names=names, device_time=float(i))
            lg.sample({"config_id": "c0", "q_measured_deg": [1.5] * 7, "markers": []})
            live: dict[str, list[tuple[int, bytes]]] = {"/joint_state": [], "/run/sample": []}
            while len([1 for _, d in live["/joint_state"] if json.loads(d)["device_time"] >= 0]) < 20 or not live["/run/sample"]:
                assert time.monotonic() < deadline + 30, f"live data incomplete: {len(live['/joint_state'])} joint states"
                got = client.recv(0.5)
                if got is not None:
                    live[got[0]].append((got[1], got[2]))
        finally:
            client.close()
            lg.close()
    with open(path, "rb") as fh:
        logged = {(ch.topic, m.log_time): m.data for _, ch, m in make_reader(fh).iter_messages(topics=["/joint_state", "/run/sample"])}
    fresh = [(t, d) for t, d in live["/joint_state"] if json.loads(d)["device_time"] >= 0]
    assert [json.loads(d)["device_time"] for _, d in fresh] == [float(i) for i in range(20)]
    for t, d in fresh + [(t, d) for t, d in live["/run/sample"]]:
        topic = "/run/sample" if json.loads(d).get("config_id") else "/joint_state"
        assert logged[(topic, t)] == d  # the same bytes and the same log time as in the MCAP file


def test_a_runs_channels_exist_before_a_viewer_connects_and_the_log_writes_to_them(tmp_path):
    # A channel created while a viewer connects can be advertised to it before the SDK counts it
    # as known to that viewer: the subscription is refused ("attempted to subscribe to unknown
    # channel") and the topic stays dark all run (seen with /tf on a loaded CI host).
    from acquire.record.recorder import advertise_run_channels

    topics = {"/run/sample", "/run/event", "/log", "/tf", "/markers", "/joint_state", "/mocap/markers"}
    model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    with LiveServer("127.0.0.1", 0) as server:
        advertise_run_channels(server, ["mocap"])
        client = FoxgloveClient(server.url)
        lg = None
        try:
            client.wait_channels(topics, timeout_s=10)  # before anything is written
            ids = {t: client.channels[t]["id"] for t in topics}
            client.subscribe(*sorted(topics))
            lg = RunLog.create(tmp_path / "run.mcap", run_id="r", plan_text="", model_text="", metadata={}, live=server)
            view = fv.RobotView(Chain(model))
            got: set[str] = set()
            deadline = time.monotonic() + 30
            while got != topics:
                assert time.monotonic() < deadline, f"nothing on {sorted(topics - got)}"
                t = time.time_ns()
                lg.record_joint_state("fri", np.zeros(7), names=model.axis_names, log_time_ns=t)
                lg.record_transforms(view.transforms(np.zeros(7), t), log_time_ns=t)
                lg.record_markers("mocap", {"m1": [1.0, 2.0, 3.0]}, log_time_ns=t)
                lg.sample({"config_id": "c0", "q_measured_deg": [0.0] * 7, "markers": []})
                lg.event("note", text="x")
                while (msg := client.recv(0.05)) is not None:
                    got.add(msg[0])
            assert {t: client.channels[t]["id"] for t in topics} == ids  # the same channels, never re-created
            assert not [n for n in client.notices if "unadvertise" in n or "unknown channel" in n]
        finally:
            client.close()
            if lg is not None:
                lg.close()


def test_live_server_refuses_a_bad_port_and_a_taken_one():
    from acquire.live.foxglove_server import LiveServerError

    with pytest.raises(ValueError, match="0..65535"):
        LiveServer("127.0.0.1", 70000)
    with LiveServer("127.0.0.1", 0) as first:
        with pytest.raises(LiveServerError, match="--live-port"):
            LiveServer("127.0.0.1", first.port)


def _compose(transforms: list[dict], frame: str) -> np.ndarray:
    from test_foxglove_view import compose

    return compose(transforms, frame)


@pytest.mark.timeout(170)
def test_acquire_run_live_serves_the_robot_frames_and_the_joint_state(tmp_path):
    # a long plan: still running when the client has what it needs (the test stops it with SIGTERM)
    plan = small_plan(tmp_path, n=30, sequencing={"samples": 5, "settle_window_s": 0.2}, fake={"time_scale": 4.0})
    proc = popen("run", str(plan), "--fake", "--no-bus", "--no-fit", "--live", "--live-port", "0")
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stderr], daemon=True).start()
    url = None
    deadline = time.monotonic() + 90
    while url is None:
        assert time.monotonic() < deadline and proc.poll() is None, "no live view announced"
        try:
            line = lines.get(timeout=0.5)
        except queue.Empty:
            continue
        if line.startswith("live view: open "):
            url = line.split()[3]
    client = FoxgloveClient(url)
    try:
        client.wait_channels({"/tf", "/joint_state"}, timeout_s=90)
        client.subscribe("/tf", "/joint_state", "/markers")
        tfs: dict[int, dict] = {}
        joints: dict[int, dict] = {}
        scenes: list[dict] = []
        def paired() -> list[int]:  # a joint state and its frames, once base → mocap (the registration) is known
            return sorted(t for t in set(tfs) & set(joints) if "mocap" in {f["child_frame_id"] for f in tfs[t]["transforms"]})

        while not paired() or not scenes:
            assert time.monotonic() < deadline + 60 and proc.poll() is None, "no /tf, /joint_state and /markers pair received"
            try:
                got = client.recv(0.5)
            except websockets.exceptions.ConnectionClosed as exc:  # the run ended: say why
                tail = []
                while not lines.empty():
                    tail.append(lines.get_nowait())
                with_mocap = sum("mocap" in {f["child_frame_id"] for f in d["transforms"]} for d in tfs.values())
                raise AssertionError(
                    f"live view closed ({exc}) before a pair: received /tf {len(tfs)} ({with_mocap} with base → mocap), "
                    f"/joint_state {len(joints)}, common stamps {len(set(tfs) & set(joints))}, /markers {len(scenes)}; "
                    f"server notices {client.notices[-5:]}; the run's warnings:\n"
                    f"{''.join([x for x in tail if 'WARNING' in x or 'ERROR' in x][-10:])}the run said:\n{''.join(tail[-25:])}"
                ) from exc
            if got is None:
                continue
            topic, t_ns, data = got
            doc = json.loads(data)
            (tfs if topic == "/tf" else joints if topic == "/joint_state" else {}).__setitem__(t_ns, doc)
            if topic == "/markers":
                scenes.append(doc)
    finally:
        client.close()
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    t = paired()[0]
    q = np.array(joints[t]["position_rad"])
    frames = tfs[t]["transforms"]
    np.testing.assert_allclose(_compose(frames, "flange"), Chain(model).fk(q), atol=1e-3)  # the streamed frames are the robot's
    mocap = next(f for f in frames if f["child_frame_id"] == "mocap")  # base → sensor: the run's registration estimate
    assert mocap["parent_frame_id"] == "base"
    assert any(e["frame_id"] in ("mocap", "flange") for s in scenes for e in s["entities"])


# --------------------------------------------------------------------------------- the daemon
def test_daemon_config_live_section_binds_loopback_unless_remote_is_allowed(tmp_path):
    from acquire.daemon.config import DaemonConfig

    cfg = DaemonConfig(cell="c1", fake=True, live={"enabled": True, "port": 9000})
    assert (cfg.live.host, cfg.live.port) == ("127.0.0.1", 9000)
    with pytest.raises(ValueError, match="not loopback.*allow_remote"):
        DaemonConfig(cell="c1", fake=True, live={"enabled": True, "host": "0.0.0.0"})
    assert DaemonConfig(cell="c1", fake=True, live={"enabled": True, "host": "0.0.0.0", "allow_remote": True}).live.allow_remote
    with pytest.raises(ValueError, match="less than or equal to 65535"):
        DaemonConfig(cell="c1", fake=True, live={"enabled": True, "port": 70000})


@pytest.mark.slow  # a daemon and a run; the live server itself is test_acquire_run_live_serves_… (default)
@pytest.mark.timeout(170)
def test_daemon_serves_its_runs_live_when_configured(tmp_path):
    from daemon_harness import OPERATOR_TOKEN, DaemonProcess, NotifySocket, control, free_port, open_client, write_config

    notify = NotifySocket()
    port, live_port = free_port(), free_port()
    proc = DaemonProcess(write_config(tmp_path, port, live={"enabled": True, "port": live_port}), notify)
    client = None
    try:
        proc.wait_ready(timeout=90)
        client = FoxgloveClient(f"ws://127.0.0.1:{live_port}")
        deadline = time.monotonic() + 30
        while client.server_info is None:
            assert time.monotonic() < deadline, "no serverInfo from the daemon's live view"
            client.recv(0.2)
        assert client.server_info["name"].startswith("remaster ")
        with open_client(port) as bus:
            control(bus, "operator", OPERATOR_TOKEN).call("start", {"plan": "example.yaml"}, timeout=60)
            client.wait_channels({"/tf", "/joint_state", "/log"}, timeout_s=90)
            client.subscribe("/log")
            deadline = time.monotonic() + 120
            lines: list[str] = []
            while not any(x.startswith("measured ") for x in lines):
                assert time.monotonic() < deadline, f"no measured configuration on /log; got {lines[-5:]}"
                got = client.recv(0.5)
                if got is not None:
                    lines.append(json.loads(got[2])["message"])
    finally:
        if client is not None:
            client.close()
        proc.stop(signal.SIGTERM, timeout=60)
        notify.close()
