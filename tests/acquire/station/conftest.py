"""Fixtures of the station tests: short socket folders removed after each test."""

import pytest
from station_harness import remove_short_folders


@pytest.fixture(autouse=True)
def _short_socket_folders():
    """Removes the folders ``station_harness.socket_endpoint`` made for a long tmp_path."""
    yield
    remove_short_folders()
