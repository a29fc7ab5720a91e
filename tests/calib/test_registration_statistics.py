"""The registration seed's spatial correlation reaches the user: result.json and the warnings."""

from __future__ import annotations

import numpy as np

from calib.fit.regstats import spatial_correlation
from calib.report.report_summary import warnings


def test_an_error_growing_with_range_is_significant_and_warned_about():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1500, 1500, (60, 3)) + [0, 0, 2500]
    dist = np.linalg.norm(pts, axis=1)
    grows = np.abs(rng.normal(0.02, 0.005, 60)) + 2e-5 * dist  # 20 µm per metre of range
    flat = np.abs(rng.normal(0.05, 0.01, 60))
    c_grows, c_flat = spatial_correlation(grows, pts), spatial_correlation(flat, pts)
    assert c_grows.significant and c_grows.r > 0.5
    assert not c_flat.significant
    doc = {"registration_statistics": {"tracker": {"r": c_grows.r, "p_value": c_grows.p_value, "n": 60,
                                                   "significant": True, "decision": c_grows.decision}}}
    assert any("grows with the distance from the sensor" in w for w in warnings(doc))
    doc["registration_statistics"]["tracker"].update(significant=False)
    assert not any("grows with the distance" in w for w in warnings(doc))
