"""NatNet frame decoding throughput: ``drivers.natnet.codec`` against OptiTrack's ``natnetsdk``.

Run: ``python tests/bench/bench_natnet.py``

Workload: one FRAMEOFDATA packet holding one rigid body and ten labeled markers (plus the ten
as legacy unlabeled markers and one ten-marker marker set, as Motive sends a tracked plate),
encoded by our codec in NatNet 3.0 and 4.1. Both decoders read the same bytes in the same run:
ours is ``codec.decode_packet`` (header included); the baseline is natnetsdk's
``NatNetClient.__unpack_mocap_data`` (its frame decoder without the printing wrapper). Rate is
frames decoded per second, best of several repeats; the ratio is ours / natnetsdk's (target ≥ 5).
natnetsdk's stdout is redirected while it runs. Both must agree on the decoded values (checked).
"""

from __future__ import annotations

import contextlib
import io
import time

import numpy as np

from drivers.natnet import codec


def bench_frame(rng: np.random.Generator) -> codec.FrameOfData:
    lm = np.zeros(10, codec.LABELED_MARKER_DTYPE)
    lm["id"] = [(1 << 16) | (i + 1) for i in range(10)]
    lm["pos"] = rng.uniform(-2, 2, (10, 3))
    lm["size"], lm["params"], lm["residual"] = 0.014, 0x0A, 2e-4
    rb = np.zeros(1, codec.RIGID_BODY_DTYPE)
    rb["id"], rb["pos"], rb["quat"], rb["mean_error"], rb["params"] = 1, (0.2, 1.4, -0.6), (0, 0, 0, 1), 3e-4, 1
    pos = lm["pos"].copy()
    return codec.FrameOfData(
        frame_number=162734, marker_sets=(codec.MarkerSetData("tool", pos),), unlabeled=pos,
        rigid_bodies=rb, labeled_markers=lm, timestamp=1356.12,
        stamp_camera_mid_exposure=1, stamp_data_received=2, stamp_transmit=3,
    )


def rate(fn, n: int, repeats: int = 5) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def main() -> None:
    from natnetsdk.NatNetClient import NatNetClient

    frame = bench_frame(np.random.default_rng(0))
    client = NatNetClient()
    unpack = client._NatNetClient__unpack_mocap_data
    print("NatNet FRAMEOFDATA decode, 1 rigid body + 10 labeled markers (frames/s, best of 5)")
    for version in ((3, 0, 0, 0), (4, 1, 0, 0)):
        packet = codec.encode_packet(frame, version)
        payload = packet[4:]
        ours = codec.decode_packet(packet, version)
        with contextlib.redirect_stdout(io.StringIO()):
            _, theirs = unpack(payload, len(payload), version[0], version[1])
            # same answer from both
            got = np.array([m.pos for m in theirs.labeled_marker_data.labeled_marker_list], np.float32)
            assert np.array_equal(got, ours.labeled_markers["pos"])
            assert theirs.rigid_body_data.rigid_body_list[0].id_num == int(ours.rigid_bodies["id"][0])
            r_ours = rate(lambda: codec.decode_packet(packet, version), 20_000)
            r_theirs = rate(lambda: unpack(payload, len(payload), version[0], version[1]), 2_000)
        print(
            f"  NatNet {version[0]}.{version[1]} ({len(packet)} B): ours {r_ours:,.0f}/s "
            f"({1e6 / r_ours:.1f} µs)  natnetsdk {r_theirs:,.0f}/s ({1e6 / r_theirs:.1f} µs)  "
            f"ratio {r_ours / r_theirs:.1f}×"
        )
        # what a client needs per frame: decode + positions in mm
        r_mm = rate(lambda: codec.decode_packet(packet, version).labeled_positions_mm(), 20_000)
        print(f"      ours incl. mm conversion: {r_mm:,.0f}/s ({r_mm / r_theirs:.1f}× natnetsdk)")


if __name__ == "__main__":
    main()
