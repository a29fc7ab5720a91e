"""Fixtures shared by the tests in tests/acquire (defined in their harness modules)."""

from daemon_harness import daemon, notify, socket_dir  # noqa: F401 - pytest fixtures offered to every test here
