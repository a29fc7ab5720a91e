"""Fixtures for the NatNet tests (helpers live in ``natnet_helpers``)."""

from __future__ import annotations

import pytest
from natnet_helpers import PlateScene, StillScene


@pytest.fixture
def scene() -> PlateScene:
    return PlateScene()


@pytest.fixture
def still_scene() -> StillScene:
    return StillScene()
