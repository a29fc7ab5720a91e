"""The end-of-run fit in a process of its own (``acquire.run.fitting.fit_run_log_apart``): the
answer, the progress lines and the errors come back to the run's process."""

from __future__ import annotations

import pytest

from acquire.run import fitting
from acquire.run.fitting import fit_run_log_apart


class _BadPlan:
    """A loaded plan whose plan cannot be read: the fit raises ValueError at its first look."""

    @property
    def plan(self):
        raise ValueError("plan: unreadable (a test's)")


def test_an_error_of_the_fit_comes_back_as_it_was_raised(tmp_path):
    """The fit process's ValueError is the run's, with its text: the run's summary says why there is no result."""
    with pytest.raises(ValueError, match=r"plan: unreadable \(a test's\)"):
        fit_run_log_apart(tmp_path / "run.mcap", _BadPlan())


def test_a_fit_process_that_dies_is_an_error_naming_the_log(tmp_path, monkeypatch):
    """The process ends without a result (killed, or a failure it could not report): RuntimeError
    with the exit code and the command that fits the kept log later."""
    log = tmp_path / "run.mcap"
    monkeypatch.setattr(fitting, "_fit_apart", _die)  # (the fork server imports this module by name)
    with pytest.raises(RuntimeError, match=r"ended \(exit code 7\) without a result.*acquire fit .*run\.mcap"):
        fit_run_log_apart(log, None)


def _die(log_path, lp, n_random, every_s, messages) -> None:
    import os

    os._exit(7)
