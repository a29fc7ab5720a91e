"""``SocketSensor``: a joint sensor for socket calibration (``drivers.protocols.JointSensor``).

There is no measuring device: the robot itself is the instrument. At each configuration the
robot has approached a socket (the nominal model puts the ball within millimetres of it); the
operator guides the ball into the socket (an iiwa in joint-impedance mode yields to the hand; a
KR is jogged) and the sensor records the joint angles the controller measures when either

- the operator confirms: a key press (Enter) on the terminal with ``operator://terminal``, a
  ``confirm()`` call (the daemon's control channel), or a press of a controller input named by
  ``input=`` (e.g. the media flange's user button, which the robot application shares over
  FRI: the commander's ``digital_input``) — a press is a change from released to set during
  the wait, so a button held or stuck from before confirms nothing — or
- the robot has been *guided* — its measured position left the commanded one by more than
  ``guide_deg`` on some axis (the hand is holding it; a jogged robot never is, so a KR needs
  the confirmation) — and has then held still within ``still_deg`` for ``window_s``.

Then ``n`` joint states are averaged (mean and std per axis). The stream is the attached
commander's ``joint_state()``; when the controller reports no commanded position (FRI 2.x),
the position at the start of the wait stands in for it.

URL: ``operator://terminal`` (Enter confirms; ignored when stdin is not a terminal) or
``operator://none`` (stillness and ``confirm()`` only), with options ``guide_deg=F`` (0.05),
``still_deg=F`` (0.01), ``window_s=F`` (0.5), ``poll_s=F`` (0.01) and ``input=NAME`` (a
controller input that confirms, e.g. ``input=MediaFlange.UserButton``; needs a commander that
reads inputs: FRI).

Units: radians and seconds inside; options in degrees and seconds.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from typing import Any, Callable
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.base import DeviceBase, check_timeout
from drivers.errors import DeviceTimeoutError, DriverError
from drivers.protocols import DigitalInputs, JointCapture, JointState

_OPTIONS = {"guide_deg": "guide_rad", "still_deg": "still_rad", "window_s": "window_s", "poll_s": "poll_s",
            "input": "confirm_input"}


class SocketSensor(DeviceBase):
    """Records joint angles with the ball in a socket (see the module docstring)."""

    def __init__(self, name: str = "socket", *, confirm_source: str = "none",
                 guide_rad: float = math.radians(0.05), still_rad: float = math.radians(0.01),
                 window_s: float = 0.5, poll_s: float = 0.01, confirm_input: str | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 stdin=None) -> None:
        super().__init__(name, clock=clock)
        if confirm_source not in ("terminal", "none"):
            raise ValueError(f"{name}: confirm source must be terminal or none (operator://terminal, "
                             f"operator://none), got {confirm_source!r}")
        for key, v in (("guide", guide_rad), ("still", still_rad), ("window_s", window_s), ("poll_s", poll_s)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: {key} must be a positive number, got {v!r}")
        if still_rad >= guide_rad:
            raise ValueError(f"{name}: still_deg ({math.degrees(still_rad):g}) must be below guide_deg "
                             f"({math.degrees(guide_rad):g}): a robot held still must not count as guided")
        if confirm_input is not None and not (isinstance(confirm_input, str) and confirm_input.strip()):
            raise ValueError(f"{name}: input must name a controller input (e.g. MediaFlange.UserButton), "
                             f"got {confirm_input!r}")
        self.confirm_source = confirm_source
        self.confirm_input = confirm_input
        self.guide_rad, self.still_rad = float(guide_rad), float(still_rad)
        self.window_s, self.poll_s = float(window_s), float(poll_s)
        self._sleep = sleep
        self._stdin = stdin if stdin is not None else sys.stdin
        self._confirmed = threading.Event()
        self._commander = None
        self._reader: threading.Thread | None = None
        self._closed = threading.Event()
        self.waiting_for: str | None = None  # what the operator is asked to do now (for a display)

    @classmethod
    def from_url(cls, url: str, **kwargs: Any) -> "SocketSensor":
        """``operator://terminal?window_s=0.5`` (see the module docstring); ``commander=`` attaches."""
        parts = urlsplit(url)
        if parts.scheme != "operator" or parts.netloc not in ("terminal", "none"):
            raise ValueError(f"socket sensor URL must be operator://terminal or operator://none[?options], got {url!r}")
        commander = kwargs.pop("commander", None)
        for key, value in parse_qsl(parts.query, strict_parsing=False):
            if key not in _OPTIONS:
                raise ValueError(f"socket sensor URL {url!r}: unknown option {key!r}; allowed {', '.join(_OPTIONS)}")
            if key == "input":
                kwargs["confirm_input"] = value
                continue
            try:
                v = float(value)
            except ValueError:
                raise ValueError(f"socket sensor URL {url!r}: {key} must be a number, got {value!r}") from None
            kwargs[_OPTIONS[key]] = math.radians(v) if key.endswith("_deg") else v
        sensor = cls(confirm_source=parts.netloc, **kwargs)
        if commander is not None:
            sensor.attach(commander)
        return sensor

    def attach(self, commander) -> None:
        if self.confirm_input is not None and not isinstance(commander, DigitalInputs):
            raise ValueError(f"{self.name}: input={self.confirm_input} needs a commander that reads the controller's "
                             f"inputs (FRI); {type(commander).__name__} reads none — confirm with Enter or "
                             "`acquire confirm` instead")
        self._commander = commander

    def connect(self) -> None:
        if self.confirm_source == "terminal" and getattr(self._stdin, "isatty", lambda: False)():
            self._reader = threading.Thread(target=self._read_keys, name=f"{self.name}-keys", daemon=True)
            self._reader.start()
        elif self.confirm_source == "terminal":
            self.log.info("stdin is not a terminal: confirm with the daemon's control call, or hold still")

    def close(self) -> None:
        self._closed.set()

    def _read_keys(self) -> None:
        for _ in iter(self._stdin.readline, ""):
            if self._closed.is_set():
                return
            if self.waiting_for is not None:
                self.confirm()

    def confirm(self) -> None:
        """The operator says the ball sits in the socket: record now (thread-safe)."""
        self._confirmed.set()

    def _state(self) -> JointState:
        if self._commander is None:
            raise DriverError(f"{self.name}: no commander attached; the socket sensor reads the robot's joint "
                              "states (the run attaches its commander)")
        return self._commander.joint_state()

    def capture(self, label: str, n: int, timeout: float) -> JointCapture:
        """Wait until the ball is held in the socket ``label`` (guided, then still; or confirmed),
        then average ``n`` joint states. DeviceTimeoutError after ``timeout`` seconds."""
        if n < 1:
            raise ValueError(f"n must be at least 1, got {n}")
        timeout = check_timeout(timeout)
        deadline = self.clock() + timeout
        self._confirmed.clear()
        self.waiting_for = label
        self.log.warning("guide the ball into %s and hold it still (or press %s / confirm)", label,
                         self.confirm_input or "Enter")
        try:
            trigger = self._wait(label, deadline, timeout)
            states = []
            while len(states) < n:
                if self.clock() > deadline + self.window_s + n * self.poll_s * 4:
                    raise DeviceTimeoutError(f"{self.name}: {len(states)} of {n} joint states at {label}")
                try:
                    states.append(self._state())
                except DeviceTimeoutError:
                    pass
                if len(states) < n:
                    self._sleep(self.poll_s)
        finally:
            self.waiting_for = None
        q = np.stack([np.asarray(s.position_rad, dtype=float) for s in states])
        std = q.std(axis=0, ddof=1) if n > 1 else np.zeros(q.shape[1])
        self.log.info("%s: recorded (%s), spread %.4f°", label, trigger, math.degrees(float(std.max())))
        return JointCapture(label=label, mean_rad=q.mean(axis=0), std_rad=std, count=n, trigger=trigger,
                            device_time=float(states[-1].device_time), host_time=float(states[-1].host_time))

    def _pressed(self) -> bool | None:
        """The confirming input's state, None without one or when the controller's message is stale."""
        if self.confirm_input is None:
            return None
        try:
            return self._commander.digital_input(self.confirm_input)
        except DeviceTimeoutError:
            return None

    def _wait(self, label: str, deadline: float, timeout: float) -> str:
        first = None
        ref_still = None
        t_still = 0.0
        released = False  # the input was seen released during this wait: its next press confirms
        while True:
            if self._confirmed.is_set():
                return "confirm"
            pressed = self._pressed()
            if pressed and released:
                return "input"
            released = released or pressed is False
            now = self.clock()
            if now > deadline:
                raise DeviceTimeoutError(f"{self.name}: the ball was not held in {label} within {timeout:.3g} s; "
                                         "guide it in and hold still, or confirm")
            try:
                st = self._state()
            except DeviceTimeoutError:
                self._sleep(self.poll_s)
                continue
            q = np.asarray(st.position_rad, dtype=float)
            if first is None:
                first = q
            held = np.asarray(st.commanded_rad, dtype=float) if st.commanded_rad is not None else first
            guided = float(np.max(np.abs(q - held))) > self.guide_rad
            if not guided:
                ref_still = None
            elif ref_still is None or float(np.max(np.abs(q - ref_still))) > self.still_rad:
                ref_still, t_still = q, st.host_time
            elif st.host_time - t_still >= self.window_s:
                return "still"
            self._sleep(self.poll_s)
