"""Error classes raised by drivers.

Each also inherits from the built-in a caller would naturally catch (python-can / ophyd
style), so ``except TimeoutError`` still works around a driver call.
"""

from __future__ import annotations


class DriverError(Exception):
    """Base class of every error a driver raises on purpose."""


class DriverUnavailableError(DriverError, ImportError):
    """A registered driver could not be imported (missing dependency, broken plug-in)."""


class ProtocolError(DriverError, ValueError):
    """Bytes or a line from a device (or a peer) that do not follow the protocol."""


class DeviceTimeoutError(DriverError, TimeoutError):
    """The device did not answer, or stopped streaming, within the allowed time."""


class ConnectionLostError(DriverError, ConnectionError):
    """The transport to the device closed or failed."""


class DeviceFaultError(DriverError, RuntimeError):
    """The device reported a fault (error reply, controller stop, drive fault)."""


class TargetLostError(DriverError, RuntimeError):
    """The sensor cannot see the requested marker (occluded, beam broken)."""


class LimitError(DriverError, ValueError):
    """A command was refused before anything moved: outside limits, too fast, bad state."""


class NotReadyError(LimitError):
    """A move refused before anything moved because the device's state does not allow one *now*
    (drives off, a session not commanding, a stale joint state, the last move still ending, the
    robot not yet at rest). Unlike a target outside the limits, it may clear by itself: a run
    waits for the device within its allowance, verifies it again, then moves."""



class DistanceLostError(TargetLostError):
    """A laser tracker's beam is locked but its distance is not valid (interferometer distance
    lost after a beam break, or no ADM distance set): re-establish it (``home()``) or re-aim."""


class TrackerWarmingUpError(DeviceFaultError):
    """A laser tracker refuses to measure until it has warmed up (or its temperature is stable)."""
