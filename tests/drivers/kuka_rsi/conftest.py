"""Fixtures for the RSI tests (helpers live in ``rsi_helpers``)."""

from __future__ import annotations

import pytest
from rsi_helpers import kr6_limits

from drivers.protocols import JointLimits


@pytest.fixture
def limits() -> JointLimits:
    """KUKA KR 6 R900-2 joint limits, speeds and planning accelerations."""
    return kr6_limits()
