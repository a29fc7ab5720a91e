"""The NatNet client's parts on their own, without sockets or threads: frame ordering and the
silence limit (``newest_frame``), re-announcements and bitstream answers (``server_state``), a
frame as samples (``samples``), and the fake's frame faults (``fake_faults``). The same
behaviour end to end, over loopback UDP, is in test_natnet_client.py / test_natnet_transport.py."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from drivers.errors import ConnectionLostError, DeviceTimeoutError
from drivers.natnet import codec
from drivers.natnet.fake_faults import FrameFaults
from drivers.natnet.newest_frame import NewestFrame
from drivers.natnet.samples import frame_samples
from drivers.natnet.selection import MarkerSelector
from drivers.natnet.server_state import ServerState
from drivers.natnet.settings import NatNetSettings

LOG = logging.getLogger("test.natnet.parts")


def settings(**changes) -> NatNetSettings:
    values = dict(
        name="mocap", server="127.0.0.1", command_port=1510, data_port=None, multicast=None,
        local="127.0.0.1", bitstream=None, silence_timeout_s=0.5, handshake_timeout_s=2.0,
        keepalive_interval_s=1.0, units="m", reorder_window=60, restart_run=3,
    )
    values.update(changes)
    return NatNetSettings(**values)


def offer_all(frames: NewestFrame, numbers) -> list[str | None]:
    return [frames.offer(codec.FrameOfData(frame_number=n), 0.0) for n in numbers]


# ----------------------------------------------------------------------------- NewestFrame


def test_late_and_duplicate_frames_are_stale_and_a_run_of_older_ones_is_a_restart():
    frames = NewestFrame(settings(reorder_window=60, restart_run=3), time.monotonic)
    reasons = offer_all(frames, [10, 11, 11, 9, 12])  # a duplicate and a late frame
    assert reasons == [None] * 5
    assert (frames.frames_accepted, frames.frames_stale, frames.restarts) == (3, 2, 0)
    # three older frames in increasing order: the server restarted just behind the newest
    reasons = offer_all(frames, [2, 3, 4])
    assert reasons[:2] == [None, None] and reasons[2] == "frame counter went back from 12 to 4"
    assert (frames.frames_accepted, frames.frames_stale, frames.restarts) == (4, 4, 1)
    assert offer_all(frames, [5]) == [None] and frames.frames_accepted == 5


def test_a_jump_back_beyond_the_reorder_window_is_a_restart_at_once():
    frames = NewestFrame(settings(reorder_window=60), time.monotonic)
    # 60 behind is still a late frame; 500 behind is a restart
    assert offer_all(frames, [500, 440, 0]) == [None, None, "frame counter went back from 500 to 0"]
    assert (frames.frames_stale, frames.restarts) == (1, 1)


def test_the_first_frame_after_a_re_announcement_is_taken_whatever_its_number():
    frames = NewestFrame(settings(), time.monotonic)
    offer_all(frames, [100])
    frames.rejoin()
    assert offer_all(frames, [99]) == ["frame counter restarted at 99 (was 100) after a new SERVERINFO"]
    frames.rejoin()
    assert offer_all(frames, [120]) == [None]  # a newer one is no restart
    assert (frames.frames_accepted, frames.frames_stale, frames.restarts) == (3, 0, 1)


def test_take_hands_each_frame_out_once_then_reports_silence_with_the_reason():
    now = [10.0]
    frames = NewestFrame(settings(silence_timeout_s=0.5), lambda: now[0])
    frames.offer(codec.FrameOfData(frame_number=7), 9.9)
    frame, host_time = frames.take(1.0, lambda: "unused")
    assert (frame.frame_number, host_time) == (7, 9.9)
    now[0] = 10.4  # 0.5 s since the frame arrived
    with pytest.raises(DeviceTimeoutError, match=r"no NatNet frame for 0\.500 s .*; Motive is paused"):
        frames.take(1.0, lambda: "Motive is paused")


def test_take_times_out_when_frames_keep_coming_but_none_is_new():
    frames = NewestFrame(settings(silence_timeout_s=30.0), time.monotonic)
    frames.heard(time.monotonic())
    with pytest.raises(DeviceTimeoutError, match=r"no new NatNet frame within 0\.05 s"):
        frames.take(0.05, lambda: "unused")


def test_a_failed_receiver_is_raised_to_the_reader():
    frames = NewestFrame(settings(), time.monotonic)
    frames.fail(OSError("network is down"))
    with pytest.raises(ConnectionLostError, match="receiver stopped: network is down"):
        frames.take(1.0, lambda: "unused")


# ----------------------------------------------------------------------------- ServerState


def info(version) -> codec.ServerInfo:
    return codec.ServerInfo("Motive", (3, 1, 0, 0), version, 10_000_000, 1511, False, "239.255.42.99")


def test_a_re_announced_4x_server_is_asked_for_the_bitstream_again_before_frames_are_read():
    state = ServerState(settings(bitstream="4.1"), {}, LOG)
    rejoin, requests = state.on_reannounce(info((4, 0, 0, 0)))
    assert rejoin and requests == [codec.Request("Bitstream,4.1"), codec.RequestModelDef()]
    assert state.stream_version is None and state.pending_bitstream  # frames dropped until then
    state.on_bitstream_reply(codec.Response(code=0))
    assert state.stream_version == (4, 1, 0, 0) and not state.pending_bitstream and state.problem is None


def test_a_refused_bitstream_after_a_restart_says_to_connect_again():
    state = ServerState(settings(bitstream="4.1"), {}, LOG)
    state.on_reannounce(info((4, 0, 0, 0)))
    state.on_bitstream_reply(codec.UnrecognizedRequest())
    assert state.stream_version is None
    assert "refused to stream NatNet 4.1 again" in state.problem and "connect the sensor again" in state.problem


def test_a_re_announced_server_this_driver_cannot_read_has_its_frames_dropped():
    state = ServerState(settings(), {}, LOG)
    assert state.on_reannounce(info((5, 0, 0, 0))) == (False, [])
    assert state.stream_version is None and "set bitstream=4.1" in state.problem
    assert state.on_reannounce(info((3, 1, 0, 0))) == (True, [codec.RequestModelDef()])
    assert state.stream_version == (3, 1, 0, 0) and state.problem is None


def test_new_model_definitions_that_lose_a_named_marker_are_ignored():
    selectors = {"corner": MarkerSelector.parse("ms:tool:m1")}
    state = ServerState(settings(), selectors, LOG)
    good = codec.ModelDef((codec.MarkerSetDescription("tool", ("m1", "m2")),
                           codec.RigidBodyDescription("tool", 3, -1, (0.0, 0.0, 0.0), ())))
    state.on_model_def(good)
    assert state.resolved == {"corner": ("lm", (3 << 16) | 1)}
    state.on_model_def(codec.ModelDef((codec.MarkerSetDescription("other", ("m1",)),)))
    assert state.model_def is good and state.resolved == {"corner": ("lm", (3 << 16) | 1)}


# ----------------------------------------------------------------------------- samples


def test_a_frame_becomes_one_sample_per_plan_marker_in_mm():
    lm = np.zeros(2, codec.LABELED_MARKER_DTYPE)
    lm["id"] = [(1 << 16) | 1, (1 << 16) | 2]
    lm["pos"] = [(0.1, 0.2, 0.3), (0.4, 0.5, 0.6)]
    lm["params"] = [0, codec.MARKER_OCCLUDED]
    lm["residual"] = [0.0002, 0.0]
    rb = np.zeros(1, codec.RIGID_BODY_DTYPE)
    rb["id"], rb["pos"], rb["params"] = 1, (1.0, 2.0, 3.0), codec.RIGID_BODY_TRACKED
    rb["quat"] = (0.0, 0.0, np.sin(0.25), np.cos(0.25))  # 0.5 rad about z
    frame = codec.FrameOfData(frame_number=1, rigid_bodies=rb, labeled_markers=lm, timestamp=4.5)
    resolved = {"a": ("lm", (1 << 16) | 1), "b": ("lm", (1 << 16) | 2), "body": ("rb", 1), "gone": ("rb", 9)}
    out = {s.marker: s for s in frame_samples(frame, 7.0, resolved, ["a", "b", "body", "gone", "later"], 1000.0)}
    assert list(out) == ["a", "b", "body", "gone", "later"]
    np.testing.assert_allclose(out["a"].position_mm, [100, 200, 300], atol=1e-3)
    assert out["a"].visible and out["a"].residual_mm == pytest.approx(0.2, abs=1e-4)
    assert not out["b"].visible  # occluded: Motive's predicted position, not visible
    np.testing.assert_allclose(out["b"].position_mm, [400, 500, 600], atol=1e-3)
    np.testing.assert_allclose(out["body"].position_mm, [1000, 2000, 3000], atol=1e-3)
    c, s = np.cos(0.5), np.sin(0.5)
    np.testing.assert_allclose(out["body"].rotation, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-6)
    for name in ("gone", "later"):
        assert not out[name].visible and np.isnan(out[name].position_mm).all()
    assert {(s.device_time, s.host_time) for s in out.values()} == {(4.5, 7.0)}


# ----------------------------------------------------------------------------- FrameFaults


def test_fake_faults_drop_duplicate_and_swap_frames():
    faults = FrameFaults(seed=0)
    assert faults.apply(b"1") == [b"1"]  # no fault until set
    faults.set(reorder=1.0)
    assert faults.apply(b"2") == []  # held back …
    assert faults.apply(b"3") == [b"3", b"2"]  # … and sent after the next one
    faults.set(duplicate=1.0)
    assert faults.apply(b"4") == [b"4", b"4"]
    faults.set(drop=1.0)
    assert faults.apply(b"5") == []
    with pytest.raises(ValueError, match=r"reorder probability must be within \[0, 1\], got 1\.5"):
        faults.set(reorder=1.5)
