"""The end-of-run fit's progress in the run's status (``RunState.fitting``) and on its status line."""

from __future__ import annotations

from acquire.live.progress import status_line
from acquire.run.state import RunState
from calib.fit.progress import Progress


class _Publisher:
    def __init__(self) -> None:
        self.statuses: list[dict] = []

    def progress(self, status: dict) -> None:
        self.statuses.append(status)


def test_the_fit_says_what_it_is_doing_in_the_run_status_with_the_time_left():
    pub = _Publisher()
    state = RunState(pub)
    assert state.status()["fit"] is None  # no fit running: the field is there, empty
    now = [0.0]
    progress = Progress(state.fitting, clock=lambda: now[0], every_s=1.0)
    progress.begin("cross-validation", 10)
    progress.step("cross-validation: fold 1 of 5, model 1 of 2 (offsets)")
    now[0] = 4.0
    progress.step("cross-validation: fold 1 of 5, model 2 of 2 (offsets+tool)")  # 1 of 10 took 4 s: 36 s left
    fit = pub.statuses[-1]["fit"]
    assert fit == {"doing": "cross-validation: fold 1 of 5, model 2 of 2 (offsets+tool) [2/10]", "eta_s": 36.0}
    line = status_line(pub.statuses[-1])
    assert "fit: cross-validation: fold 1 of 5, model 2 of 2 (offsets+tool) [2/10] (ETA 36s)" in line
