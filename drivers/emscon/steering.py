"""``BeamSteering``: pointing the tracker's beam at a reflector again (re-acquisition).

``aim(xyz)`` sends ``GoPosition`` (with ADM) to the predicted reflector position and checks
``GetMeasurementStatusInfo`` for a found reflector; ``search(radius, timeout)`` sets the search
parameters (only when they change) and sends ``FindReflector``; ``go_birdbath`` sends the beam
home. ``last_xyz`` is the last position aimed at or measured (mm, tracker frame): its distance
is the approximate distance ``FindReflector`` is given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.base import Clock, check_timeout
from drivers.emscon import codec as es
from drivers.emscon.channel import EmsconChannel
from drivers.emscon.codec import Cmd
from drivers.emscon.configuration import REFLECTOR_FOUND
from drivers.errors import TargetLostError


@dataclass(frozen=True)
class SearchResult:
    """A ``FindReflector`` that found the reflector; ``elapsed_s`` on the sensor's clock."""

    found: bool
    elapsed_s: float


class BeamSteering:
    """Aim, search and bird bath over ``channel``. search_radius_mm: default spiral radius of
    ``reacquire``; approx_distance_mm: distance given to ``FindReflector`` before anything was
    aimed at or measured; clock: times a search (s)."""

    def __init__(self, channel: EmsconChannel, *, search_radius_mm: float, approx_distance_mm: float,
                 clock: Clock) -> None:
        self.channel = channel
        self.name = channel.name
        self.search_radius_mm = search_radius_mm
        self.approx_distance_mm = approx_distance_mm
        self.clock = clock
        #: last position aimed at or measured, shape (3,), mm (None: none yet)
        self.last_xyz: np.ndarray | None = None
        self._search: tuple[float, int] | None = None  # (dSearchRadius, lTimeOut) last set

    def forget_parameters(self) -> None:
        """The server's search parameters are unknown again (a new connection)."""
        self._search = None

    def go_birdbath(self, timeout: float = 30.0) -> None:
        """Send the beam to the bird bath (the reflector's home on the tracker)."""
        self.channel.request(es.Request(Cmd.GoBirdBath), timeout=self.channel.reply_timeout + check_timeout(timeout))

    def aim(self, xyz_mm, timeout: float = 10.0) -> None:
        """``GoPosition`` (with ADM) to ``xyz_mm`` (shape (3,), tracker frame, mm); raises
        TargetLostError if no reflector is locked there afterwards."""
        p = np.asarray(xyz_mm, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"aim point must be 3 finite numbers (mm), got {xyz_mm!r}")
        request = self.channel.request
        request(es.Request(Cmd.GoPosition, {"dVal1": p[0], "dVal2": p[1], "dVal3": p[2], "bUseADM": 1}),
                timeout=self.channel.reply_timeout + check_timeout(timeout))
        self.last_xyz = p
        info = request(es.Request(Cmd.GetMeasurementStatusInfo)).values["lMeasurementStatusInfo"]
        if not info & REFLECTOR_FOUND:
            raise TargetLostError(f"{self.name}: GoPosition to ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm found no "
                                  "reflector there; try search()")

    def search(self, radius_mm: float, timeout: float, max_turns: int = 0) -> SearchResult:
        """``FindReflector`` within ``radius_mm`` around the current beam direction, for at most
        ``timeout`` seconds (``max_turns`` is not an emScon parameter and is ignored). Raises
        TargetLostError when nothing is found."""
        if not (isinstance(radius_mm, (int, float)) and math.isfinite(radius_mm) and 0 < radius_mm <= 10_000):
            raise ValueError(f"radius_mm must be in (0, 10000] mm, got {radius_mm!r}")
        timeout = check_timeout(timeout)
        params = (float(radius_mm), max(1, int(round(timeout * 1000))))
        if self._search != params:
            self.channel.request(es.Request(Cmd.SetSearchParams, {"dSearchRadius": params[0], "lTimeOut": params[1]}))
            self._search = params
        approx = float(np.linalg.norm(self.last_xyz)) if self.last_xyz is not None else self.approx_distance_mm
        t0 = self.clock()
        try:
            self.channel.request(es.Request(Cmd.FindReflector, {"dAproxDistance": approx}),
                                 timeout=self.channel.reply_timeout + timeout)
        except TargetLostError as exc:
            raise TargetLostError(f"{self.name}: FindReflector within {radius_mm:g} mm found no reflector "
                                  f"({exc})") from None
        return SearchResult(True, self.clock() - t0)

    def reacquire(self, xyz_mm, search_radius_mm: float | None = None, timeout: float = 30.0) -> None:
        """Aim at the predicted reflector position, and ``FindReflector`` there if that fails."""
        try:
            self.aim(xyz_mm, timeout)
        except TargetLostError:
            self.search(search_radius_mm or self.search_radius_mm, timeout)
