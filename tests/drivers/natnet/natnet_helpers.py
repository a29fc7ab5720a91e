"""Helpers for the NatNet tests: a tiny marker scene, fixture paths, and natnetsdk plumbing."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.natnet import codec
from drivers.sim.scene import MarkerObservation

REPO = Path(__file__).resolve().parents[3]
CAPTURES = REPO.parent / "shared" / "fixtures" / "natnet-motive-2.1"

V30, V31, V40, V41 = (3, 0, 0, 0), (3, 1, 0, 0), (4, 0, 0, 0), (4, 1, 0, 0)
VERSIONS = [V30, V31, V40, V41]

#: Tool-plate marker layout (mm, plate frame) and where the plate sits in Motive's frame.
PLATE_MM = np.array([[0.0, 0.0, 0.0], [120.0, 0.0, 0.0], [0.0, 90.0, 0.0], [40.0, 30.0, 70.0]])
PLATE_ORIGIN_MM = np.array([250.0, 1400.0, -600.0])


def capture(name: str) -> bytes:
    """Bytes of one real Motive capture, or skip when the shared fixtures are absent."""
    path = CAPTURES / name
    if not path.is_file():
        pytest.skip(f"real Motive capture {path} is absent (shared fixtures not mounted)")
    return path.read_bytes()


class PlateScene:
    """A ``MarkerScene``: four markers on a plate turning about z at ``omega_rad_s``.

    ``hidden``: names reported invisible. ``observe`` gives positions in mm for any sensor at
    the time ``clock()`` says (injectable, so a test can turn the plate without waiting).
    """

    def __init__(self, omega_rad_s: float = 0.3, clock=time.monotonic) -> None:
        self.clock = clock
        self.t0 = clock()
        self.omega = omega_rad_s
        self.hidden: set[str] = set()
        self.names = [f"m{i}" for i in range(len(PLATE_MM))]
        self._lock = threading.Lock()

    def positions_mm(self, t: float) -> np.ndarray:
        a = self.omega * t
        r = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        return PLATE_MM @ r.T + PLATE_ORIGIN_MM

    def observe(self, sensor: str) -> list[MarkerObservation]:
        with self._lock:
            hidden = set(self.hidden)
        pos = self.positions_mm(self.clock() - self.t0)
        return [MarkerObservation(n, pos[i], n not in hidden) for i, n in enumerate(self.names)]


class StillScene(PlateScene):
    """The plate standing still (positions exactly ``PLATE_MM + PLATE_ORIGIN_MM``)."""

    def __init__(self) -> None:
        super().__init__(omega_rad_s=0.0)


# ---------------------------------------------------------------- sample messages for the codec


def f32(rng, *shape) -> np.ndarray:
    """Random float32 values (exactly representable, so they survive the wire)."""
    return rng.uniform(-3, 3, size=shape).astype("<f4")


def rich_frame(rng, version) -> codec.FrameOfData:
    """A frame using every section the version has."""
    rb = np.zeros(3, codec.RIGID_BODY_DTYPE)
    rb["id"], rb["pos"], rb["quat"] = [1, 2, 70000], f32(rng, 3, 3), f32(rng, 3, 4)
    rb["mean_error"], rb["params"] = f32(rng, 3), [1, 0, 1]
    lm = np.zeros(5, codec.LABELED_MARKER_DTYPE)
    lm["id"] = [(1 << 16) | 1, (1 << 16) | 2, (2 << 16) | 1, 50007, 0xFFFFFFFF]
    lm["pos"], lm["size"], lm["residual"] = f32(rng, 5, 3), f32(rng, 5), f32(rng, 5)
    lm["params"] = [0x0A, 0x0B, 0x04, 0x10, -1]
    bones = rb[:2].copy()
    assets = ()
    if version[:2] >= (4, 1):
        assets = (codec.AssetData(9, bones, lm[:2].copy()), codec.AssetData(10, rb[:0].copy(), lm[:0].copy()))
    return codec.FrameOfData(
        frame_number=123456,
        marker_sets=(codec.MarkerSetData("plate", f32(rng, 4, 3)), codec.MarkerSetData("all", f32(rng, 0, 3)),
                     codec.MarkerSetData("Ünïcode", f32(rng, 1, 3))),
        unlabeled=f32(rng, 2, 3),
        rigid_bodies=rb,
        skeletons=(codec.SkeletonData(4, bones),),
        assets=assets,
        labeled_markers=lm,
        force_plates=(codec.AnalogData(1, (f32(rng, 3), f32(rng, 0))),),
        devices=(codec.AnalogData(2, (f32(rng, 1),)), codec.AnalogData(3, ())),
        timecode=0x01020304, timecode_subframe=5, timestamp=1356.1166666,
        stamp_camera_mid_exposure=1416498518, stamp_data_received=1416498533, stamp_transmit=1416498545,
        precision_timestamp_secs=1700000000 if version[0] >= 4 else 0,
        precision_timestamp_frac_secs=12345 if version[0] >= 4 else 0,
        params=3,
    )


def rich_modeldef(version) -> codec.ModelDef:
    names = version[0] >= 4
    rb = codec.RigidBodyDescription(
        "tool", 1, -1, (0.5, -0.25, 0.125),
        tuple(codec.RigidBodyMarkerDescription((0.0625 * i, -0.5, 1.0), i, f"m{i}" if names else "") for i in range(3)),
    )
    datasets = [
        rb,
        codec.MarkerSetDescription("tool", ("m0", "m1", "m2")),
        codec.MarkerSetDescription("empty", ()),
        codec.SkeletonDescription("skel", 3, (rb, codec.RigidBodyDescription("bone", 2, 1))),
        codec.ForcePlateDescription(
            5, "FP-0042", 0.5, 0.75, (0.25, 0.0, -0.125), tuple(float(i) for i in range(144)),
            tuple(-float(i) for i in range(12)), 1, 2, ("Fx", "Fy", "Fz"),
        ),
        codec.DeviceDescription(6, "NI-DAQ", "SN 1", 3, 1, ("ai0", "ai1")),
        codec.CameraDescription("cam 1", (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)),
    ]
    if version[:2] >= (4, 1):
        datasets.append(codec.AssetDescription(
            "arm", 1, 9, (codec.RigidBodyDescription("link1", 1, -1, (0.0, 0.0, 0.25), rb.markers[:1]),),
            (codec.AssetMarkerDescription("arm_m1", (9 << 16) | 1, (0.125, 0.5, -0.25), 0.015625, 3),
             codec.AssetMarkerDescription("arm_m2", 2, (0.0, 0.0, 0.0), 0.0, 0)),
        ))
        datasets.append(codec.UnknownDescription(7, b"a dataset type newer than 4.1"))
    return codec.ModelDef(tuple(datasets))


def small_messages() -> list:
    return [
        codec.Connect("remaster", (0, 1, 0, 0), (4, 1, 0, 0), "natnetlib"),
        codec.Connect("Ping", (0, 0, 0, 0), (4, 1, 0, 0), "python"),
        codec.Connect("Ping", layout="ping"),
        codec.Discovery("NatNetLib", (3, 0, 0, 0), (3, 0, 0, 0)),
        codec.ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10_000_000, 1511, True, "239.255.42.99"),
        codec.ServerInfo("Old Motive", (1, 10, 0, 0), (2, 10, 0, 0)),
        codec.Request("Bitstream,4.1"),
        codec.Response(code=0),
        codec.Response(code=-1),
        codec.Response(text="Bitstream,4.1"),
        codec.Response(text="abc"),  # 3 chars + NUL would look like a code; padded
        codec.Response(text=""),
        codec.RequestModelDef(), codec.RequestFrameOfData(), codec.KeepAlive(), codec.Disconnect(),
        codec.UnrecognizedRequest(),
        codec.MessageString("Motive: recording started"),
        codec.EchoRequest(2**64 - 1),
        codec.EchoResponse(278554190, 1416498545924),
    ]



# ---------------------------------------------------------------- natnetsdk (OptiTrack's client)


def natnetsdk_client(fake, multicast: bool):
    """OptiTrack's ``NatNetClient`` aimed at ``fake``'s ports, recording what it decodes.

    Its own sockets bind to all interfaces and (multicast) to 127.0.0.1, which on Linux never
    receives group traffic; the two socket factories are replaced by loopback-only ones that
    bind the data socket to the group address. Its threads, handshake and decoder are its own.
    Returns (client, decoded) where ``decoded`` collects (raw datagram, offset, MoCapData).
    """
    from natnetsdk.NatNetClient import NatNetClient

    c = NatNetClient()
    c.set_print_level(0)
    c.set_server_address("127.0.0.1")
    c.set_client_address("127.0.0.1")
    c.set_use_multicast(multicast)
    c.multicast_address = fake.multicast_group
    c.command_port = fake.command_port
    c.data_port = fake.data_port
    decoded: list = []
    raw: list[bytes] = []
    process = c._NatNetClient__process_message
    unpack = c._NatNetClient__unpack_mocap_data

    def process_and_keep(data, print_level=0):
        raw.append(bytes(data))
        return process(data, print_level)

    def unpack_and_keep(data, packet_size, major, minor):
        offset, mocap = unpack(data, packet_size, major, minor)
        decoded.append((raw[-1], offset, mocap, (major, minor)))
        return offset, mocap

    def data_socket(port):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if multicast:
            s.bind((fake.multicast_group, port))
            s.setsockopt(
                socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                socket.inet_aton(fake.multicast_group) + socket.inet_aton("127.0.0.1"),
            )
        else:
            s.bind(("127.0.0.1", 0))
        return s

    def command_socket():
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.settimeout(2.0)
        return s

    c._NatNetClient__process_message = process_and_keep
    c._NatNetClient__unpack_mocap_data = unpack_and_keep
    c._NatNetClient__create_data_socket = data_socket
    c._NatNetClient__create_command_socket = command_socket
    return c, decoded


def stop_natnetsdk(c, fake) -> None:
    """Stop its threads: they block in recvfrom with no timeout, so set the stop flag, wake
    each socket with an empty datagram and let both threads end before its own ``shutdown()``
    closes the sockets (its unicast thread sends a keep-alive after each datagram: closing
    under it raises EBADF in that thread)."""
    c.stop_threads = True
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as w:
        w.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        w.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        for sk in (c.command_socket, c.data_socket):
            host, port = sk.getsockname()
            w.sendto(b"", (host, port))
    for t in (c.command_thread, c.data_thread):
        t.join(timeout=5.0)
    c.shutdown()


def wait_until(predicate, timeout: float = 3.0, step: float = 0.005) -> bool:
    """Poll a condition on real sockets (no clock to inject there); True if it became true."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return bool(predicate())


_MULTICAST_OK: list[str | None] = []


def need_loopback_multicast(group: str = "239.255.42.99") -> None:
    """Skip (with the reason) unless this kernel delivers multicast on loopback: join ``group``
    on 127.0.0.1, send one datagram to it with TTL 0 and receive it back."""
    if not _MULTICAST_OK:
        reason = None
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, \
                    socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                rx.bind((group, 0))
                rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                              socket.inet_aton(group) + socket.inet_aton("127.0.0.1"))
                rx.settimeout(2.0)
                tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
                tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
                tx.sendto(b"probe", (group, rx.getsockname()[1]))
                if rx.recv(16) != b"probe":
                    reason = "a foreign datagram arrived instead of the probe"
        except OSError as exc:
            reason = str(exc)
        _MULTICAST_OK.append(reason)
    if _MULTICAST_OK[0] is not None:
        pytest.skip(f"this kernel does not deliver multicast on loopback ({_MULTICAST_OK[0]})")
