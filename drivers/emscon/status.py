"""Every ``ES_ResultStatus`` of emScon TPI 3.6 mapped to the driver error a caller catches.

``error_for(status, what)`` builds the exception (with ``status`` and ``status_name``
attributes) for a refused command; ``WARNINGS`` are statuses that accompany a command the
server *did* execute (a parameter outside its nominal range but accepted, warm-up reached) —
the client logs them and goes on. A status this table does not know (a newer server) is a
``DeviceFaultError`` naming the number.

Classes (``drivers.errors``): bad parameters or state → ``LimitError``; an unreadable or
unsupported request → ``ProtocolError``; no reflector locked / no result → ``TargetLostError``
(``DistanceLostError`` when only the distance is missing); warming up → ``TrackerWarmingUpError``;
an internal module that did not answer → ``DeviceTimeoutError``; everything else (hardware
absent or failed, licence, database, busy) → ``DeviceFaultError``.
"""

from __future__ import annotations

from drivers.emscon.codec import Status
from drivers.errors import (
    DeviceFaultError,
    DeviceTimeoutError,
    DistanceLostError,
    LimitError,
    ProtocolError,
    TargetLostError,
    TrackerWarmingUpError,
)

S = Status

#: Statuses of a command the server executed anyway (logged as warnings).
WARNINGS: frozenset[Status] = frozenset({
    S.Parameter1OutOfRangeOK, S.Parameter2OutOfRangeOK, S.Parameter3OutOfRangeOK,
    S.Parameter4OutOfRangeOK, S.Parameter5OutOfRangeOK, S.Parameter6OutOfRangeOK,
    S.WarmedUpStateReached,
})

_LIMIT = {
    S.WrongParameter, S.WrongParameter1, S.WrongParameter2, S.WrongParameter3, S.WrongParameter4,
    S.WrongParameter5, S.WrongParameter6, S.WrongParameter7, S.WrongParameter8, S.WrongParameter9,
    S.WrongParameter10, S.WrongParameter11, S.WrongParameter12, S.WrongParameter13, S.WrongParameter14,
    S.WrongParameter15, S.WrongParameter16,
    S.Parameter1OutOfRangeNOK, S.Parameter2OutOfRangeNOK, S.Parameter3OutOfRangeNOK,
    S.Parameter4OutOfRangeNOK, S.Parameter5OutOfRangeNOK, S.Parameter6OutOfRangeNOK,
    S.WrongCurrentReflector, S.NoLastMeasuredPoint, S.NotInCameraPosition, S.NoSuchCompensation,
    S.MeteoDataOutOfRange, S.SixDModeNotAllowed, S.SixDMeasurementFace2NotAllowed, S.InvalidInputData,
    S.InvalidTipAdapter, S.UsageConflict,
}
_PROTOCOL = {S.NotImplemented}
_TARGET = {S.MeasurementStatusNotReady, S.NoStationaryResult, S.SystemNotReadyForMeasurement}
_DISTANCE = {S.NoDistanceSet}
_WARMING = {S.SensorNotWarmedUp, S.SensorNotStable, S.ADMStartUpBusy}
_TIMEOUT = {S.ModuleTimedOut}

#: Error class of every status that refuses a command (all of ``Status`` except AllOK and WARNINGS).
ERROR_CLASSES: dict[Status, type[Exception]] = {}
for _s in Status:
    if _s is S.AllOK or _s in WARNINGS:
        continue
    ERROR_CLASSES[_s] = (
        LimitError if _s in _LIMIT else
        ProtocolError if _s in _PROTOCOL else
        DistanceLostError if _s in _DISTANCE else
        TargetLostError if _s in _TARGET else
        TrackerWarmingUpError if _s in _WARMING else
        DeviceTimeoutError if _s in _TIMEOUT else
        DeviceFaultError
    )

#: What to do, for the statuses an operator meets in practice.
ADVICE: dict[Status, str] = {
    S.ServerBusy: "another command is still running; wait for its answer",
    S.TrackerNotInitialized: "send Initialize first",
    S.NoTrackerConnected: "the emScon server has no tracker; check the sensor cable / WLAN",
    S.NoTPFound: "the emScon server cannot reach the tracker processor; check the controller",
    S.NoWeathermonitorFound: "no weather station: set the environment in the plan instead",
    S.MeasurementStatusNotReady: "no reflector locked; GoPosition / FindReflector first",
    S.NoStationaryResult: "the beam broke during the stationary measurement; re-acquire and repeat",
    S.NoDistanceSet: "the distance is not set; re-aim with GoPosition (ADM) or GoBirdBath",
    S.SensorNotWarmedUp: "the tracker is warming up; wait",
    S.SensorNotLeveled: "level the tracker",
    S.MultiConnectionsNotAllowed: "another client is connected to the emScon server; close it",
    S.MeteoDataOutOfRange: "temperature / pressure / humidity outside the allowed range",
}


def status_name(status: int) -> str:
    """``ES_RS_<name>`` of ``status`` or ``status <n>`` when unknown."""
    try:
        return f"ES_RS_{Status(status).name}"
    except ValueError:
        return f"status {status}"


def error_for(status: int, what: str) -> Exception:
    """The exception for a refused command: ``what`` says which (e.g. ``"tracker: StartMeasurement"``)."""
    try:
        s = Status(status)
    except ValueError:
        cls: type[Exception] = DeviceFaultError
        advice = "a status this driver does not know (newer emScon server?)"
    else:
        cls = ERROR_CLASSES.get(s, DeviceFaultError)
        advice = ADVICE.get(s, "")
    text = f"{what} refused with {status_name(status)} ({int(status)})"
    exc = cls(f"{text}: {advice}" if advice else text)
    exc.status = int(status)
    exc.status_name = status_name(status)
    return exc
