"""``calib.report.svg``: ticks at round values, labels with the decimals their spacing needs, data mapped
to pixels and back, scatters that draw what lies within the limits, well-formed SVG."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from calib.report.svg import Figure, data_limits, log_ticks, nice_ticks, tick_labels
from svgread import axes, texts  # tests/calib is on sys.path under pytest


@pytest.mark.parametrize("lo, hi", [(0.0, 1.0), (-0.0123, 0.0171), (1.47, 2.03), (-1200.0, 35.0), (0.1917, 0.1898 + 0.003)])
def test_ticks_are_round_evenly_spaced_and_inside_the_limits(lo, hi):
    t = nice_ticks(lo, hi, 5)
    assert 2 <= t.size <= 6 and t.min() >= lo - 1e-12 and t.max() <= hi + 1e-12
    step = np.diff(t)
    np.testing.assert_allclose(step, step[0])
    mantissa = step[0] / 10 ** np.floor(np.log10(step[0]))
    assert any(np.isclose(mantissa, m) for m in (1, 2, 2.5, 5))


def test_tick_labels_share_decimals_and_use_a_true_minus():
    assert tick_labels(np.array([-0.01, -0.005, 0.0, 0.005, 0.01])) == ["−0.010", "−0.005", "0.000", "0.005", "0.010"]
    assert tick_labels(np.array([0.0, 250.0, 500.0])) == ["0", "250", "500"]
    assert tick_labels(np.array([1.5, 1.75, 2.0])) == ["1.50", "1.75", "2.00"]


def test_log_ticks_are_decades_or_1_2_5_within_one():
    np.testing.assert_allclose(log_ticks(0.05, 30.0), [0.1, 1.0, 10.0])
    np.testing.assert_allclose(log_ticks(0.3, 2.5), [0.5, 1.0, 2.0])


def test_points_map_to_pixels_and_back_and_a_scatter_drops_what_lies_outside():
    fig = Figure(400, 300)
    ax = fig.axes((50, 20, 300, 200), (-2.0, 2.0), (10.0, 20.0))
    X, Y = ax.px([-2.0, 2.0, 0.0], [10.0, 20.0, 15.0])
    np.testing.assert_allclose(X, [50, 350, 200])
    np.testing.assert_allclose(Y, [220, 20, 120])  # y upwards
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-3, 3, 500), rng.uniform(8, 22, 500)
    drawn = ax.scatter(x, y, color="#000", label="pts")
    inside = (np.abs(x) <= 2) & (y >= 10) & (y <= 20)
    assert drawn == inside.sum() < 500
    ax.frame(title="t", xlabel="x (mm)", ylabel="y (mm)")
    svg = ET.fromstring(fig.svg("a test <figure> & more"))  # well-formed, the label escaped
    assert svg.get("aria-label") == "a test <figure> & more"
    (read,) = axes(svg)
    got = read.scatter("pts")
    np.testing.assert_allclose(got, np.column_stack([x, y])[inside], atol=max(read.resolution()))
    words = texts(svg)
    assert {"t", "x (mm)", "y (mm)"} <= set(words) and "−2" in words and "20" in words


def test_a_log_axis_places_decades_evenly():
    fig = Figure(300, 300)
    ax = fig.axes((0, 0, 100, 300), (0.0, 1.0), (0.01, 10.0), logy=True)
    _, Y = ax.px([0.5, 0.5, 0.5, 0.5], [0.01, 0.1, 1.0, 10.0])
    np.testing.assert_allclose(Y, [300, 200, 100, 0])
    assert data_limits(np.array([0.1, 10.0]), log=True)[0] < 0.1


def test_bad_limits_are_refused_with_what_was_given():
    fig = Figure(100, 100)
    with pytest.raises(ValueError, match=r"increasing.*given x \(1.0, 1.0\)"):
        fig.axes((0, 0, 10, 10), (1.0, 1.0), (0.0, 1.0))
    with pytest.raises(ValueError, match="positive on a log scale"):
        fig.axes((0, 0, 10, 10), (0.0, 1.0), (0.0, 1.0), logy=True)
