"""The simulated controller's own mastering: per-axis zero corrections the operator enters.

A real controller turns an encoder reading into an axis angle with its mastering (KUKA KSS:
``axis angle = encoder angle − $MAMES[i]``; a Sunrise cabinet, a UR or an ABB keep an axis zero
of their own). Entering a correction c_i shifts that zero: the axis angle the controller reports
for the same physical position changes by −c_i, and a commanded axis angle lands c_i further on.
The correction is the column ``correction_deg`` that ``calib.robot.controller`` prints (−δ_i for a
fitted offset δ_i: ``$MAMES[i] = $MAMES[i] + correction``), so entering it makes the reported
angle grow by δ_i — what the fit's convention "true angle = reported angle + δ" asks for.

In the simulated cell the ``SimCell``'s joint positions are the arm's positions as the controller
read them when it was built (mastering all zero); the fake controllers (``drivers.kuka_fri.fake``,
``drivers.kuka_rsi.fake``) see the arm through a ``MasteredScene``::

    reported axis angle  = cell position − c        (what the controller reports)
    cell position        = commanded axis angle + c (where a commanded angle puts the arm)

(the sign convention ``calib.robot.controller`` assumes and calls unverified: the simulation
follows it, it cannot prove it), so the controller keeps its nominal kinematics and its own
limits in axis angles, the truth (hidden offsets, links, sag) stays in the cell, and nothing
above the driver can tell.

A real controller takes a new mastering only at standstill, with no program running (KSS reads
``$MAMES`` from its machine data at a cold start; the iiwa is mastered from the smartPAD): the
launch (``SimLaunch.enter_mastering``) refuses while a client commands the robot and restarts the
controller with the new table, from where the arm stands. Units: degrees in the table and the
cell file, radians to the scene.
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass

import numpy as np

from drivers.sim.scene import RobotScene

#: How each controller names a mastering entry, for the lines a person reads.
ENTRY_NAMES = {"kss": "$MAMES[{index}]", "sunrise": "axis {axis} zero"}

_MAMES_LINE = re.compile(r"^\s*\$MAMES\[(\d+)\]\s*=\s*\$MAMES\[(\d+)\]\s*([+-]\s*[0-9.eE+-]+)\s*(;.*)?$")


class MasteringError(ValueError):
    """A mastering entry that cannot be made: unknown axis, not a number, or the robot in motion."""


@dataclass(frozen=True)
class MasteringEntry:
    """One correction to enter: ``axis`` (its name) and ``correction_deg`` (added to the zero)."""

    axis: str
    correction_deg: float


class Mastering:
    """The controller's table of per-axis zero corrections (deg), relative to the mastering the
    arm was built with. Thread-safe: the controllers read it every cycle.

    axis_names: the robot's axes (A1…, J1…); controller: ``kss``, ``sunrise`` or another kind
    (how the lines name an entry); corrections_deg: the table at start (None: all zero).
    """

    def __init__(self, axis_names, controller: str = "", corrections_deg=None) -> None:
        self.axis_names = tuple(axis_names)
        self.controller = controller
        n = len(self.axis_names)
        c = np.zeros(n) if corrections_deg is None else np.asarray(corrections_deg, dtype=float).reshape(-1)
        if c.shape != (n,) or not np.all(np.isfinite(c)):
            raise MasteringError(f"mastering: {n} finite corrections (deg) needed, one per axis "
                                 f"{', '.join(self.axis_names)}; given {np.asarray(corrections_deg).tolist()}")
        self._lock = threading.Lock()
        self._c_rad = np.radians(c)
        self._c_rad.setflags(write=False)

    # --- reading ------------------------------------------------------------------------
    @property
    def corrections_deg(self) -> np.ndarray:
        """(n,) the corrections now, deg (a copy)."""
        return np.degrees(self._c_rad)

    def reported(self, cell_q_rad: np.ndarray) -> np.ndarray:
        """The axis angles (n,) rad the controller reports for the arm at cell positions (n,) rad."""
        return np.asarray(cell_q_rad, dtype=float) - self._c_rad

    def cell_position(self, axis_q_rad: np.ndarray) -> np.ndarray:
        """Where commanded axis angles (n,) rad put the arm, as cell positions (n,) rad."""
        return np.asarray(axis_q_rad, dtype=float) + self._c_rad

    def axis_index(self, axis: str) -> int:
        """0-based index of ``axis`` given by name (``A2``, any case) or 1-based number (``2``)."""
        text = str(axis).strip()
        names = [a.lower() for a in self.axis_names]
        if text.lower() in names:
            return names.index(text.lower())
        if text.isdigit() and 1 <= int(text) <= len(self.axis_names):
            return int(text) - 1
        raise MasteringError(f"unknown axis {axis!r}; allowed: {', '.join(self.axis_names)} or 1…{len(self.axis_names)}")

    def lines(self) -> list[str]:
        """The table for a person: one line per axis, in the controller's own words."""
        form = ENTRY_NAMES.get(self.controller, "axis {axis} zero")
        c = self.corrections_deg
        return [f"{form.format(index=i + 1, axis=a)}: {c[i]:+.4f}° from the mastering as built"
                for i, a in enumerate(self.axis_names)]

    # --- changing -----------------------------------------------------------------------
    def after(self, entries: list[MasteringEntry]) -> np.ndarray:
        """The table (n,) deg that entering ``entries`` (added, in order) gives; checks each."""
        c = self.corrections_deg
        for e in entries:
            if not np.isfinite(e.correction_deg) or abs(e.correction_deg) > 180.0:
                raise MasteringError(f"{e.axis}: correction {e.correction_deg!r}° not allowed (a number within ±180°)")
            c[self.axis_index(e.axis)] += e.correction_deg
        return c

    def set(self, corrections_deg: np.ndarray) -> None:
        """Take the table (n,) deg. Only the launch calls this, with the controller restarted
        around it (``SimLaunch.enter_mastering``)."""
        c = np.radians(np.asarray(corrections_deg, dtype=float))
        c.setflags(write=False)
        with self._lock:
            self._c_rad = c


class MasteredScene:
    """A ``RobotScene`` seen through a controller's mastering: what the fake controller reads and
    writes is axis angles, what the cell holds is the arm's position (see the module docstring)."""

    def __init__(self, scene: RobotScene, mastering: Mastering) -> None:
        self.scene = scene
        self.mastering = mastering

    def set_joint_positions(self, q_rad: np.ndarray) -> None:
        self.scene.set_joint_positions(self.mastering.cell_position(q_rad))

    def joint_positions(self) -> np.ndarray:
        return self.mastering.reported(self.scene.joint_positions())


def parse_entry(line: str) -> list[MasteringEntry]:
    """One line of ``acquire sim``'s stdin as mastering entries: ``master AXIS CORRECTION_DEG``
    (e.g. ``master A2 -0.0123``), or a KSS line as ``calib.robot.controller`` prints it
    (``$MAMES[2] = $MAMES[2] -0.0123``). Raises MasteringError saying the forms."""
    usage = ("give 'master AXIS CORRECTION_DEG' (e.g. master A2 -0.0123) or '$MAMES[i] = $MAMES[i] ±CORRECTION'; "
             f"given {line.strip()!r}")
    m = _MAMES_LINE.match(line)
    if m:
        if m.group(1) != m.group(2):
            raise MasteringError(f"$MAMES[{m.group(1)}] can only be corrected from itself; {usage}")
        try:
            return [MasteringEntry(m.group(1), float(m.group(3).replace(" ", "")))]
        except ValueError:
            raise MasteringError(usage) from None
    parts = line.split()
    if len(parts) != 3 or parts[0] != "master":
        raise MasteringError(usage)
    try:
        return [MasteringEntry(parts[1], float(parts[2]))]
    except ValueError:
        raise MasteringError(usage) from None
