"""Network faults the fake Motive applies to its frame packets (``FakeMotive.set_faults``):
per-frame drop, duplicate and reorder, drawn from a seeded generator."""

from __future__ import annotations

import threading

import numpy as np


class FrameFaults:
    """Per-frame probabilities of dropping a packet, sending it twice, or holding it back to go
    after the next one; all zero (no fault) until ``set``. Thread-safe."""

    def __init__(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._drop = self._dup = self._reorder = 0.0
        self._held: bytes | None = None  # a frame held back for reordering

    def set(self, *, drop: float = 0.0, duplicate: float = 0.0, reorder: float = 0.0) -> None:
        """New probabilities, each within [0, 1] (ValueError naming the bad one)."""
        for name, p in (("drop", drop), ("duplicate", duplicate), ("reorder", reorder)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} probability must be within [0, 1], got {p}")
        with self._lock:
            self._drop, self._dup, self._reorder = drop, duplicate, reorder

    def forget_held(self) -> None:
        """Drop a held-back packet (the server restarted)."""
        with self._lock:
            self._held = None

    def apply(self, packet: bytes) -> list[bytes]:
        """The packets to send for ``packet``, in order (none, it, it twice, and/or the one
        held back before it)."""
        with self._lock:
            drop, dup, reorder = self._drop, self._dup, self._reorder
            u = self._rng.random(3)
            if drop and u[0] < drop:
                return []
            out = [packet, packet] if dup and u[1] < dup else [packet]
            if self._held is not None:
                out.append(self._held)  # the held-back older frame goes after this newer one
                self._held = None
            elif reorder and u[2] < reorder:
                self._held = packet
                out = out[1:]
            return out
