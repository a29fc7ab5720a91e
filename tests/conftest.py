"""Suite-wide settings.

One BLAS thread in every test process and in the processes tests start (set before numpy is
loaded: the environment is read once, when OpenBLAS starts). The fits here are small — tens of
parameters — where threads buy nothing, and on a shared, loaded machine OpenBLAS's threads fight
for the same cores: beside four CPU hogs the compliance coverage study
(``tests/calib/test_gravity.py``) took 84.6 s with the default threads and 30.4 s with one, and
two suites run at once drove it past its 240 s timeout. A value already set is kept.
"""

import logging
import os

import pytest

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# No per-example wall-clock deadline (hypothesis's default is 200 ms): beside other test workers
# and CPU hogs an example that takes 20 ms quiet takes 350, and that says nothing about the code.
# A test that sets its own deadline keeps it; pytest-timeout still bounds every test.
from hypothesis import settings  # noqa: E402

settings.register_profile("suite", deadline=None)
settings.load_profile("suite")


def _ours(handler: logging.Handler) -> bool:
    """A handler not installed by pytest itself (its capture handlers come and go per phase)."""
    return not type(handler).__module__.startswith("_pytest")


@pytest.fixture(autouse=True)
def _root_logging_restored():
    """Each test leaves the root logger as it found it. A command run in-process
    (``CliRunner().invoke(app, ["run", …])``) configures the process's logging as a CLI should:
    it replaces the root handlers by one writing INFO lines to ``sys.stderr``. Left installed,
    that handler would print into every later test's output (and pytest's own)."""
    root = logging.getLogger()
    before, level = [h for h in root.handlers if _ours(h)], root.level
    yield
    for handler in [h for h in root.handlers if _ours(h) and h not in before]:
        root.removeHandler(handler)
        handler.close()
    for handler in before:
        if handler not in root.handlers:
            root.addHandler(handler)
    root.setLevel(level)
