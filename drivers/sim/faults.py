"""Faults on demand for a running simulated cell: what each fault does to which fake device.

A fault is named, aimed at a device of the cell (a sensor's name or ``controller``; none aims it
at every device it applies to) and lasts ``duration_s`` wall seconds (faults that are events,
like a controller restart, have no duration). ``FaultInjector(launch).inject(...)`` applies one
now through the fakes' own fault hooks and undoes it when its time is up; ``FaultTimeline``
fires the cell file's ``faults:`` list at their ``at_s`` (wall seconds after the cell started).

==================  ===================================================================================
fault               what the device does
==================  ===================================================================================
session_drop        FRI: the session falls back to MONITORING_WAIT (the application restarts its
                    motion once the client answers again). RSI: the link is down both ways for
                    ``duration_s``: every cycle is late, and at the KR C4's late limit its RSI
                    program stops (the cell's simulated operator restarts it). Tracker (line, emScon): every TCP
                    connection is closed. NatNet: Motive forgets its unicast clients (they must
                    CONNECT again).
drives_off          FRI: drive state OFF, brakes hold, for ``duration_s`` (then ACTIVE again). Sunrise
                    only: an RSI message carries no drive state.
beam_break          a sensor's line of sight is blocked for ``duration_s`` (someone walks through it):
                    the tracker loses its lock and keeps it lost until re-acquired; Motive loses the
                    body while blocked.
sensor_stall        tracker: the next request is answered ``duration_s`` late (a hung device). NatNet:
                    no frames for ``duration_s`` (commands are still answered).
controller_restart  the controller restarts: FRI session IDLE and counters from zero (the application
                    opens it again); RSI: the program restarts (new start position, IPOC restarts).
packet_loss         UDP devices lose each datagram with ``probability`` for ``duration_s``: NatNet
                    frames, RSI state packets, FRI monitoring messages. TCP devices (trackers) are
                    refused: TCP does not lose packets, it stalls (use sensor_stall).
==================  ===================================================================================

Nothing here reads the simulator's truth; it only calls the fakes' fault hooks.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

#: fault name → the device kinds (``DeviceAddress.kind`` of the launch) it applies to.
FAULTS: dict[str, tuple[str, ...]] = {
    "session_drop": ("fri", "rsi", "tracker", "emscon", "natnet"),
    "drives_off": ("fri",),
    "beam_break": ("tracker", "emscon", "natnet"),
    "sensor_stall": ("tracker", "emscon", "natnet"),
    "controller_restart": ("fri", "rsi"),
    "packet_loss": ("fri", "rsi", "natnet"),
}
#: Faults that are events: no duration.
INSTANT = ("controller_restart",)
#: What a fault lasts when none is given (wall s).
DEFAULT_DURATION_S = 3.0
#: packet_loss: the probability of losing a datagram when none is given.
DEFAULT_LOSS = 0.2

#: One key per fault while ``acquire sim`` runs in a terminal (``KEY_HELP`` says it in one line).
KEYS = {"d": "session_drop", "o": "drives_off", "b": "beam_break", "s": "sensor_stall",
        "r": "controller_restart", "l": "packet_loss"}
KEY_HELP = ("keys: d session drop, o drives off, b beam break, s sensor stall, r controller restart, "
            f"l packet loss ({DEFAULT_DURATION_S:g} s, every device it applies to), q quit")


class FaultError(ValueError):
    """A fault that cannot be applied: unknown name or device, or a device it does not apply to."""


@dataclass(frozen=True)
class Fault:
    """One fault: ``fault`` (a ``FAULTS`` name) on ``device`` (None: every device it applies to)
    for ``duration_s`` wall seconds (None: ``DEFAULT_DURATION_S``; ignored for ``INSTANT``)."""

    fault: str
    device: str | None = None
    duration_s: float | None = None
    probability: float = DEFAULT_LOSS


def parse_command(line: str) -> Fault:
    """``"FAULT [DEVICE] [DURATION_S] [PROBABILITY]"`` (one line of ``acquire sim``'s stdin) as a
    Fault; ``-`` or ``all`` as DEVICE means every device. Raises FaultError saying the format."""
    parts = line.split()
    usage = (f"give 'FAULT [DEVICE|all] [DURATION_S] [PROBABILITY]' with FAULT one of {', '.join(FAULTS)}; "
             f"given {line.strip()!r}")
    if not parts or parts[0] not in FAULTS or len(parts) > 4:
        raise FaultError(usage)
    device = parts[1] if len(parts) > 1 and parts[1] not in ("-", "all") else None
    try:
        duration = float(parts[2]) if len(parts) > 2 else None
        probability = float(parts[3]) if len(parts) > 3 else DEFAULT_LOSS
    except ValueError:
        raise FaultError(usage) from None
    if duration is not None and not duration > 0:
        raise FaultError(f"DURATION_S must be positive; {usage}")
    if not 0 < probability <= 1:
        raise FaultError(f"PROBABILITY must be within (0, 1]; {usage}")
    return Fault(parts[0], device, duration, probability)


def _rsi_link_back(fake) -> None:
    fake.drop_outgoing(probability=0.0)
    fake.drop_answers(0.0)


class FaultInjector:
    """Applies faults to the fakes of a started ``drivers.sim.launch.SimLaunch``.

    ``inject(fault)`` returns the device names it hit; the fault is undone after its duration by
    a timer thread (``close()`` undoes every one still running). ``history`` lists
    ``(wall time, fault name, device, "on" | "off")`` for tests and the console.
    """

    def __init__(self, launch, *, seed: int = 0) -> None:
        self.launch = launch
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._timers: list[threading.Timer] = []
        self._undo: dict[int, object] = {}
        self.history: list[tuple[float, str, str, str]] = []

    # --- which devices --------------------------------------------------------------------
    def targets(self, fault: str, device: str | None) -> list[str]:
        """The devices ``fault`` hits: ``device`` if it applies there, else every one it applies to."""
        if fault not in FAULTS:
            raise FaultError(f"unknown fault {fault!r}; allowed: {', '.join(FAULTS)}")
        kinds = FAULTS[fault]
        devices = self.devices()
        if device is not None:
            if device not in devices:
                raise FaultError(f"no device {device!r} in this cell; it has {', '.join(sorted(devices))}")
            if not set(devices[device]) & set(kinds):
                raise FaultError(f"{fault} does not apply to {device!r} ({'/'.join(devices[device])}); "
                                 f"it applies to {', '.join(kinds)} devices")
            return [device]
        hit = [name for name, ks in devices.items() if set(ks) & set(kinds)]
        if not hit:
            raise FaultError(f"{fault} applies to {', '.join(kinds)} devices; this cell has "
                             + ", ".join(f"{n} ({'/'.join(k)})" for n, k in devices.items()))
        return hit

    def devices(self) -> dict[str, tuple[str, ...]]:
        """Device name (a cell sensor or ``controller``) → the kinds it is served as."""
        out: dict[str, list[str]] = {}
        for name, addr in self.launch.addresses.items():
            base = name[: -len("-emscon")] if name.endswith("-emscon") else name
            out.setdefault(base, []).append(addr.kind)
        return {k: tuple(v) for k, v in out.items()}

    # --- applying ---------------------------------------------------------------------------
    def inject(self, fault: Fault) -> list[str]:
        """Apply ``fault`` now; the devices hit. Raises FaultError if it applies nowhere asked."""
        hit = self.targets(fault.fault, fault.device)
        duration = None if fault.fault in INSTANT else (fault.duration_s or DEFAULT_DURATION_S)
        for device in hit:
            undo = self._apply(fault, device, self.devices()[device])
            self._note(fault.fault, device, "on")
            if duration is not None:
                self._later(duration, fault.fault, device, undo)
        return hit

    def _apply(self, fault: Fault, device: str, kinds: tuple[str, ...]):
        """Do it; return the callable that undoes it (or None)."""
        name, launch = fault.fault, self.launch
        ctrl = launch.controller if device == "controller" else None
        if name == "beam_break":
            view = launch.views[device]
            view.blocked = True
            return lambda: setattr(view, "blocked", False)
        if name == "session_drop":
            if "fri" in kinds:
                ctrl.inject_fault("session_drop")
                return None
            if "rsi" in kinds:  # the link is down both ways; RSI counts each cycle late
                ctrl.drop_outgoing(probability=1.0)
                ctrl.drop_answers(1.0)
                return lambda: _rsi_link_back(launch.controller)
            if "natnet" in kinds:
                launch.motives[device].restart(forget_clients=True)
                return None
            for server in self._servers(device):
                server.drop()
            return None
        if name == "drives_off":
            ctrl.inject_fault("drives_off")
            return ctrl.clear_fault
        if name == "sensor_stall":
            if "natnet" in kinds:
                motive = launch.motives[device]
                motive.stall()
                return motive.resume
            for server in self._servers(device):
                server.stall(fault.duration_s or DEFAULT_DURATION_S)
            return None
        if name == "controller_restart":
            ctrl.restart()
            return None
        if name == "packet_loss":
            p = float(fault.probability)
            if "natnet" in kinds:
                motive = launch.motives[device]
                motive.set_faults(drop=p)
                return lambda: motive.set_faults(drop=0.0)
            if "rsi" in kinds:
                ctrl.drop_outgoing(probability=p)
                return lambda: launch.controller.drop_outgoing(probability=0.0)
            return self._fri_loss(ctrl, p)
        raise FaultError(f"unknown fault {name!r}")  # pragma: no cover - targets() checked it

    def _servers(self, device: str) -> list:
        """The TCP servers (line protocol and/or emScon) in front of tracker ``device``."""
        out = []
        if device in self.launch.trackers:
            out.append(self.launch.trackers[device][1])
        if device in self.launch.emscon and self.launch.emscon[device][1] not in out:
            out.append(self.launch.emscon[device][1])
        return out

    @staticmethod
    def _fri_loss(fake, p: float):
        """The fake Sunrise loses each monitoring message with probability ``p`` (its own
        ``loss_out``; 1: every one, the controller falls silent); the undo restores what it lost before."""
        before = fake.loss_out
        fake.loss_out = p
        return lambda: setattr(fake, "loss_out", before)

    def _later(self, duration: float, name: str, device: str, undo) -> None:
        key = id(object())

        def end() -> None:
            with self._lock:
                fn = self._undo.pop(key, None)
            if fn is not None:
                try:
                    fn()
                except Exception:  # noqa: BLE001 - the device may be gone (a restarted KR C4)
                    log.exception("undoing %s on %s", name, device)
            self._note(name, device, "off")

        with self._lock:
            self._undo[key] = undo
        timer = threading.Timer(duration, end)
        timer.daemon = True
        with self._lock:
            self._timers.append(timer)
        timer.start()

    def _note(self, name: str, device: str, what: str) -> None:
        log.warning("fault %s on %s: %s", name, device, "begins" if what == "on" else "ends")
        with self._lock:
            self.history.append((time.monotonic(), name, device, what))

    def close(self) -> None:
        """Cancel the pending timers and undo what is still on."""
        with self._lock:
            timers, self._timers = self._timers, []
            undo, self._undo = list(self._undo.values()), {}
        for t in timers:
            t.cancel()
        for fn in undo:
            if fn is not None:
                try:
                    fn()
                except Exception:  # noqa: BLE001
                    log.debug("undo at close failed", exc_info=True)


class FaultTimeline:
    """Fires a list of ``(at_s, Fault)`` at ``at_s`` wall seconds after ``start()`` (the cell
    file's ``faults:``), through ``injector``. ``fired`` counts the ones applied."""

    def __init__(self, injector: FaultInjector, steps: list[tuple[float, Fault]]) -> None:
        self.injector = injector
        self.steps = sorted(steps, key=lambda s: s[0])
        self.fired = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "FaultTimeline":
        t0 = time.monotonic()

        def run() -> None:
            for at_s, fault in self.steps:
                if self._stop.wait(max(0.0, t0 + at_s - time.monotonic())):
                    return
                try:
                    self.injector.inject(fault)
                    self.fired += 1
                except FaultError as exc:
                    log.error("fault timeline: %s", exc)

        if self.steps:
            self._thread = threading.Thread(target=run, name="sim-fault-timeline", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
