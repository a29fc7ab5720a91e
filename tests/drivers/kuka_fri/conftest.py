"""Fixtures for the FRI tests (helpers live in ``fri_helpers``)."""

from __future__ import annotations

import pytest
from fri_helpers import iiwa14_limits

from drivers.protocols import JointLimits


@pytest.fixture
def limits() -> JointLimits:
    """LBR iiwa 14 limits, acceleration 5 × speed per second."""
    return iiwa14_limits()
