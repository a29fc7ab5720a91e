"""10^5 mutated and random packets into the NatNet decoder: each decodes or raises
ProtocolError, never IndexError / struct.error / UnicodeDecodeError / MemoryError / a hang."""

from __future__ import annotations

import random
import struct
import time

import numpy as np
from natnet_helpers import CAPTURES, VERSIONS, rich_frame, rich_modeldef, small_messages

from drivers.errors import ProtocolError
from drivers.natnet import codec

N_PACKETS = 100_000


def corpus() -> list[tuple[bytes, tuple]]:
    """Valid packets to mutate: our encodings in every version plus the real captures."""
    out = []
    rng = np.random.default_rng(0)
    for v in VERSIONS:
        for msg in small_messages() + [rich_modeldef(v), rich_frame(rng, v), codec.FrameOfData(1)]:
            out.append((codec.encode_packet(msg, v), v))
    for path in sorted(CAPTURES.glob("*.bin")) if CAPTURES.is_dir() else []:
        out.append((path.read_bytes(), VERSIONS[0]))
    return out


def mutate(r: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    kind = r.randrange(7)
    if kind == 0:  # flip a few bytes
        for _ in range(r.randint(1, 8)):
            if b:
                b[r.randrange(len(b))] = r.randrange(256)
    elif kind == 1:  # truncate, keeping the header honest half of the time
        b = b[: r.randrange(len(b) + 1)]
        if len(b) >= 4 and r.random() < 0.5:
            struct.pack_into("<H", b, 2, len(b) - 4)
    elif kind == 2:  # write a hostile int32 (count / byte count) somewhere in the payload
        if len(b) >= 8:
            off = r.randrange(4, len(b) - 3)
            value = r.choice([-1, -(2**31), 2**31 - 1, 0x7FFF, 10_000_000, r.randrange(-50, 50)])
            struct.pack_into("<i", b, off, value)
    elif kind == 3:  # insert or delete a run of bytes, then fix the declared size
        i = r.randrange(len(b) + 1)
        if r.random() < 0.5:
            b[i:i] = bytes(r.randrange(256) for _ in range(r.randint(1, 16)))
        else:
            del b[i:i + r.randint(1, 16)]
        if len(b) >= 4:
            struct.pack_into("<H", b, 2, min(len(b) - 4, 0xFFFF))
    elif kind == 4:  # swap the message id for another one (payload read as the wrong type)
        if len(b) >= 2:
            struct.pack_into("<H", b, 0, r.choice(list(codec.MESSAGE_NAMES)))
    elif kind == 5:  # invalid UTF-8 inside names
        for _ in range(r.randint(1, 4)):
            if len(b) > 4:
                b[r.randrange(4, len(b))] = r.choice([0xC3, 0xFF, 0x80, 0xED])
    else:  # pure noise behind a plausible header
        n = r.randrange(0, 400)
        b = bytearray(struct.pack("<HH", r.choice(list(codec.MESSAGE_NAMES) + [99]), n))
        b += bytes(r.getrandbits(8) for _ in range(n))
    return bytes(b)


def test_mutated_and_random_packets_raise_only_protocol_error():
    r = random.Random(20261121)
    seeds = corpus()
    decoded = refused = 0
    t0 = time.perf_counter()
    for i in range(N_PACKETS):
        data, version = seeds[r.randrange(len(seeds))]
        packet = mutate(r, data)
        if r.random() < 0.2:
            version = r.choice(VERSIONS)
        try:
            codec.decode_packet(packet, version)
            decoded += 1
        except ProtocolError:
            refused += 1
        except Exception as exc:  # noqa: BLE001 - the point of the test: report any other type
            raise AssertionError(
                f"packet #{i} (version {version[:2]}) raised {type(exc).__name__}: {exc}; "
                f"bytes {packet.hex()}"
            ) from exc
    elapsed = time.perf_counter() - t0
    assert decoded + refused == N_PACKETS
    # both outcomes must be common, or the mutations are not exercising the decoder
    assert refused > N_PACKETS // 10 and decoded > N_PACKETS // 20, (decoded, refused)
    assert elapsed < 60, f"fuzzing took {elapsed:.1f} s"
