"""Laser tracker driver: our documented line protocol (``PROTOCOL.md``) over any pyserial URL.

- ``codec``: commands and replies as dataclasses, ``LineCodec`` to and from ASCII lines.
- ``client``: ``TrackerSensor``, a ``PositionSensor`` with ``aim`` / ``search`` / ``status`` /
  ``set_mode`` / ``home``.
- ``fake``: ``FakeTracker`` device logic on a simulated scene, served by ``TcpTrackerServer``
  (127.0.0.1) and ``PtyTrackerServer`` (a pseudo-terminal), with fault hooks.
"""

from drivers.tracker.client import DistanceLostError, TrackerSensor, TrackerWarmingUpError
from drivers.tracker.codec import LineCodec, Mode

__all__ = ["DistanceLostError", "LineCodec", "Mode", "TrackerSensor", "TrackerWarmingUpError"]
