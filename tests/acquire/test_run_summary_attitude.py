"""The run summary prints attitude accuracy (EACAE / EMCAE before → after) when the result has it,
and otherwise says how many configurations carried an orientation and that the fit used positions."""

from __future__ import annotations

import math

from acquire.commands.run_summary import attitude_summary_lines

from test_recorder import new_log  # noqa: E402 - tests/acquire is on sys.path under pytest


def test_attitude_metrics_in_the_result_are_printed():
    fit = {"metrics": {"validation": {"before": {"EACPE": 0.7, "EMCPE": 1.2, "EACAE": 0.167, "EMCAE": 0.281},
                                      "after": {"EACPE": 0.08, "EMCPE": 0.22, "EACAE": 0.077, "EMCAE": 0.177}}}}
    (line,) = attitude_summary_lines(fit)
    assert line.startswith("attitude accuracy (validation): EACAE 0.1670 → 0.0770°, EMCAE 0.2810 → 0.1770°")


def test_a_position_only_fit_of_a_run_with_orientations_says_so(tmp_path):
    half = math.sqrt(0.5)
    path = tmp_path / "run.mcap"
    with new_log(path) as lg:
        for i in range(3):
            mk = {"sensor": "mocap", "marker": "sir", "mean_mm": [1.0, 2.0, 3.0], "std_mm": [0.03] * 3, "count": 5}
            if i:
                mk |= {"quat_wxyz": [half, half, 0.0, 0.0], "std_deg": 0.03}
            lg.sample({"config_id": f"c{i}", "q_measured_deg": [0.0] * 7, "markers": [mk]})
    (line,) = attitude_summary_lines({"metrics": {"absolute": {"before": {"mean": 3.0}, "after": {"mean": 0.5}}}}, path)
    assert line.startswith("attitude: 2 configurations measured with the target's orientation")
    assert "positions only" in line
    assert attitude_summary_lines({"metrics": {}}, tmp_path / "missing.mcap") == []
