"""``StationaryMeasurer``: one emScon stationary (or 6D stationary) measurement.

``SetStationaryModeParams`` (measure time, ADM) is sent only when the measure time changes;
``StartMeasurement`` is answered by a confirmation and then the result: a
``SingleMeasResultT`` (position ``dVal1..3`` mm, per-axis spread ``dStd1..3`` mm) or, in 6D
stationary mode, a ``ProbeStationaryResultT`` (``drivers.emscon.probe.probe_pose``).
"""

from __future__ import annotations

import numpy as np

from drivers.emscon import codec as es
from drivers.emscon.channel import EmsconChannel
from drivers.emscon.codec import Cmd
from drivers.emscon.probe import probe_pose
from drivers.errors import ProtocolError


class StationaryMeasurer:
    """Stationary measurements over ``channel``."""

    def __init__(self, channel: EmsconChannel) -> None:
        self.channel = channel
        self.name = channel.name
        self._stationary: tuple[int, int] | None = None  # (lMeasTime, bUseADM) last set

    def forget_parameters(self) -> None:
        """The server's stationary parameters are unknown again (a new connection)."""
        self._stationary = None

    def _set_stationary(self, meas_time_ms: int) -> None:
        want = (int(meas_time_ms), 1)
        if self._stationary != want:
            self.channel.request(es.Request(Cmd.SetStationaryModeParams, {"lMeasTime": want[0], "bUseADM": want[1]}))
            self._stationary = want

    def measure(self, meas_time_ms: int, timeout: float):
        """One measurement of ``meas_time_ms`` ms; ``timeout`` s at least (the measure time plus
        the reply timeout when longer). Returns (xyz (3,) mm, std (3,) mm, host time s,
        rotation (3, 3) or None, std_deg or None); ProtocolError for non-finite values."""
        self._set_stationary(meas_time_ms)
        result, host_time = self.channel.exchange(es.Request(Cmd.StartMeasurement),
                                                  timeout=max(timeout, meas_time_ms / 1000.0 + self.channel.reply_timeout),
                                                  want_result=True)
        v = result.values
        rotation = std_deg = None
        if result.type is es.DataType.StationaryProbeMeasResult:
            xyz, std, rotation, std_deg = probe_pose(v, self.name)  # degrees: the angle unit set on connect
        else:
            xyz = np.array([v["dVal1"], v["dVal2"], v["dVal3"]], dtype=float)
            std = np.array([v["dStd1"], v["dStd2"], v["dStd3"]], dtype=float)
        if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(std))):
            raise ProtocolError(f"{self.name}: the server sent a non-finite measurement {xyz} ± {std}")
        return xyz, std, host_time, rotation, std_deg
