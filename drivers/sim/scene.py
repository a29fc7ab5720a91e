"""What a fake device needs from the simulated cell, as small protocols.

Fakes depend on these, not on ``SimCell`` itself, so a test can hand a fake a tiny scene of its
own. ``drivers.sim.cell.SimCell`` implements both.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np


class MarkerObservation(NamedTuple):
    """A marker as one sensor sees it now.

    position_mm: shape (3,), sensor frame, mm, with the sensor's noise applied.
    visible: False when occluded / the beam is broken / outside the acceptance cone.
    rotation: the marker's frame (a 6-DoF target: T-Mac, probe) as the sensor sees it,
    (3, 3) ``R_sensor←target`` with the sensor's attitude noise applied; None when not visible
    or when the scene gives no orientation.
    """

    name: str
    position_mm: np.ndarray
    visible: bool
    rotation: np.ndarray | None = None


@runtime_checkable
class MarkerScene(Protocol):
    """Read side, used by fake sensors."""

    def observe(self, sensor: str) -> list[MarkerObservation]:
        """Every marker of the tool as ``sensor`` sees it at the cell's current time."""
        ...


@runtime_checkable
class RobotScene(Protocol):
    """Write side, used by fake controllers: they own the servo state and report it here."""

    def set_joint_positions(self, q_rad: np.ndarray) -> None:
        """The robot's actual joint positions now, controller convention, radians, shape (n,)."""
        ...

    def joint_positions(self) -> np.ndarray:
        """The last positions set (or the cell's initial pose), shape (n,), radians."""
        ...
