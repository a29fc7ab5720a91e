"""report.html from a real fit of the shipped simulated iiwa data: the summary on top, values
formatted for people, identifiability named by combination, the paper's TCP cloud (Fig. 5).

Content, not pixels: the tests read the HTML text (with the inline SVG figures cut out) and check
the numbers against the fit they came from; the figures are read back into numbers (``svgread``)
and compared with the arrays they were drawn from.
"""

from __future__ import annotations

import copy
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from calib.robot.controller import apply_guards, controller_values
from calib.measure.dataset import read_csv
from calib.fit.offsets import FitOptions, _scale, fit_offsets
from calib.robot.kinematics import Chain
from calib.fit.metrics import accuracy_metrics
from calib.robot.model import load_robot_model
from calib.plan.observability import observability
from calib.report.html import render_report, write_report
from calib.fit.metrics import absolute_errors, predicted_base
from calib.report.report_figures import tcp_clouds
from calib.report.report_format import num
from calib.fit.result import result_dict
from svgread import axes, svgs, texts  # tests/calib is on sys.path under pytest

# One xdist worker runs this file: its module fixture (a fit) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("calib/test_report")

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
DATA = ROOT / "fixtures" / "datasets"
SVG = re.compile(r"<svg\b.*?</svg>", re.S)


def _doc(result, cal, val):
    metrics = accuracy_metrics(Chain(IIWA), cal, result.applied_offsets_rad, result.offset_samples_rad,
                               result.applied_sigma_mm, validation=val, n_random=100, n_draws=200, seed=0)
    doc = result_dict(result, cal, metrics=metrics)
    apply_guards(doc)
    values = controller_values(IIWA, doc["joint_offsets"])
    doc["controller"] = values.to_dict()
    return doc, values.format()


@pytest.fixture(scope="module")
def fitted():
    cal = read_csv(DATA / "iiwa14_sim_cal.csv", IIWA)
    val = read_csv(DATA / "iiwa14_sim_val.csv", IIWA)
    result = fit_offsets(IIWA, cal, FitOptions(n_draws=300, seed=1))
    doc, text = _doc(result, cal, val)
    return result, cal, doc, render_report(result, cal, doc, text)


def _text(page: str) -> str:
    """The page without its figures."""
    return SVG.sub("<svg>…</svg>", page)


def test_summary_comes_first_and_gives_the_values_to_enter(fitted):
    result, _, doc, page = fitted
    text = _text(page)
    summary = text[text.index("id=summary"): text.index("</section>")]
    assert text.index("id=summary") < text.index("<h2 id=controller>Values to enter")
    # A1 needs a base-fixed reference, A7 cannot be told from a turn of the fitted tool.
    assert "Enter the offsets of 5 axes" in summary
    for j in doc["joint_offsets"]:
        if j["identifiable"]:
            assert f"{j['value_deg']:+.4f}".replace("-", "−") in summary
            assert f"{-j['value_deg']:+.4f}".replace("-", "−") in summary  # the correction
    first = doc["joint_offsets"][0]
    assert not first["identifiable"] and f"{first['joint']}: leave unchanged" in summary
    after = doc["metrics"]["validation_absolute"]["after"]["mean"]
    assert "validation set, with the calibration registration" in summary and f"<b>{after:.3f}</b>" in summary


def test_summary_says_do_not_enter_with_the_guards_reasons(fitted):
    result, cal, doc, _ = fitted
    bad = copy.deepcopy(doc)
    bad.pop("do_not_enter", None)
    bad["diagnostics"]["rhat_max"] = 1.7
    reasons = apply_guards(bad)
    bad["controller"] = controller_values(IIWA, bad["joint_offsets"]).to_dict()
    text = _text(render_report(result, cal, bad))
    summary = text[text.index("id=summary"): text.index("</section>")]
    assert reasons and "DO NOT ENTER" in summary and "Enter the offsets" not in summary
    assert "R-hat 1.70 &gt; 1.05" in summary and "R-hat 1.700 &gt; 1.05" in summary  # reason and warning


def test_no_number_is_printed_raw(fitted):
    result, cal, doc, page = fitted
    # The start analysis has an exact null direction: condition number ~1e16.
    assert doc["identifiability"]["start"]["condition_number"] > 1e12
    text = _text(page)
    long_runs = re.findall(r"\d[\d.]{11,}", text)
    assert not long_runs, long_runs[:5]
    assert not re.search(r"\d\.\d{7,}", text)  # no float with more decimals than anybody reads
    assert "∞ (1 exact null direction)" in text
    assert num(11008502658314538.0) == "1.101×10¹⁶" and num(-3.2e-7, 2) == "−3.2×10⁻⁷"
    assert num(0.25118) == "0.2512" and num(12345.6) == "12346" and num(None) == "—"


def test_identifiability_names_the_combination_each_direction_mixes(fitted):
    result, _, doc, page = fitted
    text = _text(page)
    section = text[text.index("<h2 id=identifiability>"): text.index("<h2>Sampler diagnostics")]
    assert "singular value (mm)" not in section  # the old table of sorted values beside names
    start = result.identifiability_start
    (null,) = start.null_space
    assert null.exact and "A1.offset" in null.loadings
    row = re.search(r"<tr><td class=l><span class=bad>not determined</span></td><td class=l>([^<]+)</td>", section)
    assert row and row.group(1) == null.describe()
    names = re.findall(r"[+-]\d\.\d\d·([\w.]+)", row.group(1))
    assert "A1.offset" in names and any(n.startswith("mocap.") for n in names)
    # Every direction at the estimate is listed, each with its verdict, and the table's condition
    # number is the inverse of the observability index O2 of the same scaled Jacobian.
    est = result.identifiability
    every = section[section.index("<details class=estimate>"):]
    every = every[: every.index("</details>")]
    rows = re.findall(r"<span class=(good|warn|bad)>(determined|weakly determined|not determined)</span>", every)
    assert len(rows) == len(est.names) and f"{len(est.names)} directions: determined" in section
    combos = re.findall(r"</span></td><td class=l>([^<]+)</td>", section)
    assert len(combos) == 1 + len(start.names) + len(est.names)  # start: the weak one, then all; estimate: all
    assert all(re.fullmatch(r"[+-]\d\.\d\d·[\w.]+( [+-]\d\.\d\d·[\w.]+)*( \(\+\d+ smaller\))?", c) for c in combos), combos
    post = result.posterior
    jac = post.jacobian(result.mode[: post.dim])
    link_pos, _ = post.link_free()
    keep = np.setdiff1d(np.arange(post.dim), link_pos)
    lever = doc["diagnostics"]["lever_arm_mm"]
    o2 = observability(jac[:, keep] / _scale(post, lever)[keep], n_configs=1)["O2"]
    assert est.condition_number == pytest.approx(1 / o2, rel=1e-6)
    assert f"condition number {num(est.condition_number, 3)}." in section


def _figure_svgs(page: str, label: str) -> list:
    return [s for s in svgs(page) if s.get("aria-label", "").startswith(label)]


def test_the_tcp_cloud_figure_is_embedded_and_its_numbers_are_the_fits(fitted):
    result, cal, doc, page = fitted
    assert '<h2 id=tcp>TCP cloud' in page
    clouds = tcp_clouds(result, cal, n_configs=3, n_draws=500)
    chain = Chain(IIWA)
    q = cal.q_rad[clouds.rows]
    _, before = chain.flange_pose(q, chain.with_offsets(np.zeros(IIWA.n_joints)))
    _, after = chain.flange_pose(q, chain.with_offsets(result.applied_offsets_rad))
    np.testing.assert_allclose(clouds.before, before, atol=1e-9)
    np.testing.assert_allclose(clouds.after, after, atol=1e-9)
    # The offset draws scatter around the TCP after; σ widens the cloud by about σ per axis.
    spread = clouds.draws.std(axis=1)
    assert np.all(np.abs(clouds.draws.mean(axis=1) - after) < 5 * spread / np.sqrt(500) + 1e-6)
    wide = clouds.noisy.std(axis=1)
    np.testing.assert_allclose(wide, np.sqrt(spread**2 + clouds.sigma_mm**2), rtol=0.15)
    # Configurations span the before→after shifts: the smallest and the largest of the data.
    q_all = np.unique(cal.q_rad, axis=0)
    _, b_all = chain.flange_pose(q_all, chain.with_offsets(np.zeros(IIWA.n_joints)))
    _, a_all = chain.flange_pose(q_all, chain.with_offsets(result.applied_offsets_rad))
    shifts = np.linalg.norm(a_all - b_all, axis=1)
    assert clouds.shift_mm.min() == pytest.approx(shifts.min()) and clouds.shift_mm.max() == pytest.approx(shifts.max())


def test_the_tcp_figure_draws_every_point_of_the_clouds_where_it_lies(fitted):
    """Read back from the SVG: one figure per configuration; the top panel holds every draw with
    and without σ, before and after at their places, on equal scales; the bottom one the draws
    inside its zoom (the central 99 % per axis)."""
    result, cal, _, page = fitted
    clouds = tcp_clouds(result, cal)  # what the report drew: same defaults, same seed
    figures = _figure_svgs(page, "TCP cloud (Fig. 5)")
    assert len(figures) == len(clouds.rows) == 3
    m = clouds.draws.shape[1]
    assert m == result.offset_samples_rad.shape[0] == 1200  # 4 chains × 300: fewer than the 2000 asked for
    for c, svg in enumerate(figures):
        top, bottom = axes(svg)
        origin = clouds.after[c, :2]
        noisy, draws = clouds.noisy[c, :, :2] - origin, clouds.draws[c, :, :2] - origin
        rx, ry = top.resolution()
        for label, want in (("offset draws + σ", noisy), ("offset draws", draws)):
            got = top.scatter(label)
            assert got.shape == (m, 2), label
            np.testing.assert_allclose(got[:, 0], want[:, 0], atol=rx)
            np.testing.assert_allclose(got[:, 1], want[:, 1], atol=ry)
        marks = top.markers()
        np.testing.assert_allclose(marks["after"], [0, 0], atol=rx)
        np.testing.assert_allclose(marks["before"], clouds.before[c, :2] - origin, atol=rx)
        for ax in (top, bottom):  # equal scales: a square box over equal data ranges
            assert ax.box[2] == ax.box[3]
            assert ax.xlim[1] - ax.xlim[0] == pytest.approx(ax.ylim[1] - ax.ylim[0], rel=1e-5)
        assert top.xlim[0] < min(noisy[:, 0].min(), clouds.before[c, 0] - origin[0]) and top.xlim[1] > noisy[:, 0].max()
        zoomed = bottom.scatter()
        inside = ((draws[:, 0] >= bottom.xlim[0]) & (draws[:, 0] <= bottom.xlim[1])
                  & (draws[:, 1] >= bottom.ylim[0]) & (draws[:, 1] <= bottom.ylim[1]))
        assert 0.95 * m < len(zoomed) == inside.sum() <= m
        words = texts(svg)
        assert f"configuration {clouds.config[c]}: before → after {clouds.shift_mm[c]:.3g} mm" in words
        spread = np.percentile(np.linalg.norm(draws, axis=1), 95)
        assert f"offset draws alone: 95 % within {spread:.2g} mm" in words
        assert words.count("x − x_after (mm)") == 2 and words.count("y − y_after (mm)") == 2
        legend = [e for e in svg.iter() if e.get("class") == "legend"]
        assert len(legend) == (1 if c == 0 else 0)
    assert {"offset draws + σ", "offset draws", "after", "before"} <= set(texts(figures[0]))


def test_trace_and_error_figures_carry_every_chain_and_every_measurement(fitted):
    result, cal, _, page = fitted
    (trace,) = _figure_svgs(page, "trace plots")
    fitted_axes = [i for i, s in enumerate(result.offset_status) if s == "fitted"]
    panels = axes(trace)
    assert len(panels) == 2 * len(fitted_axes)  # a trace and its histogram per fitted offset
    samples = result.chains.samples  # (chains, draws, dim)
    full = result.posterior.full_vector(samples[..., : result.posterior.dim])
    for k, i in enumerate(fitted_axes):
        tr, hist = panels[2 * k], panels[2 * k + 1]
        lines = tr.lines()
        assert len(lines) == samples.shape[0]
        step = int(lines[0][1, 0] - lines[0][0, 0] + 0.5)
        for c, line in enumerate(lines):
            np.testing.assert_allclose(line[:, 1], np.degrees(full[c, ::step, i]), atol=tr.resolution()[1])
        (stairs,) = hist.series("stairs")
        assert int(stairs.get("data-total")) == full.shape[0] * full.shape[1]
        assert hist.ylim == tr.ylim
        assert f"δ{IIWA.axis_names[i]} (°)" in texts(trace)
    errors = _figure_svgs(page, "post-registration error")
    assert len(errors) == 2
    chain = Chain(IIWA)
    before = absolute_errors(cal, predicted_base(chain, cal, np.zeros(chain.n)))
    after = absolute_errors(cal, predicted_base(chain, cal, result.applied_offsets_rad))
    for svg, x in zip(errors, (np.arange(len(cal)), np.linalg.norm(cal.xyz_mm, axis=1) / 1000)):
        (ax,) = axes(svg)
        for label, want in (("before (nominal offsets)", before), ("after (applied offsets)", after)):
            got = ax.scatter(label)
            assert got.shape == (len(cal), 2)
            np.testing.assert_allclose(got[:, 0], x, atol=ax.resolution()[0])
            np.testing.assert_allclose(got[:, 1], want, atol=ax.resolution()[1])
        assert "error after registration, eq. 18 (mm)" in texts(svg)


class _Balance(HTMLParser):
    """Open elements on a stack: every end tag must close the innermost open one."""

    VOID = {"meta", "br", "img", "hr", "input", "link", "wbr"}

    def __init__(self):
        super().__init__()
        self.stack, self.errors = [], []

    def handle_starttag(self, tag, attrs):
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        pass  # <path …/> inside SVG

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()


def test_report_is_written_as_html_whose_elements_all_close(fitted, tmp_path):
    result, cal, doc, _ = fitted
    path = write_report(tmp_path / "report.html", result, cal, doc)
    page = path.read_text(encoding="utf-8")
    assert page.startswith("<!DOCTYPE html>") and "<img" not in page
    parser = _Balance()
    parser.feed(page)
    parser.close()
    assert not parser.errors and not parser.stack, (parser.errors[:3], parser.stack)
    assert len(svgs(page)) == 6  # well-formed XML each: 3 TCP panels, the traces, 2 error plots


def test_tcp_legend_goes_to_the_corner_with_the_fewest_points():
    """The TCP figure's legend goes where it hides the fewest points."""
    from calib.report.report_figures import _emptiest_corner

    rng = np.random.default_rng(0)
    cloud = rng.normal([0.6, 0.6], 0.1, (500, 2))  # upper right of a unit box
    assert _emptiest_corner(cloud, (0.0, 1.0), (0.0, 1.0)) == "lower left"
    assert _emptiest_corner(cloud * [-1, 1] + [1, 0], (0.0, 1.0), (0.0, 1.0)) == "lower right"
    assert _emptiest_corner(cloud * [1, -1] + [0, 1], (0.0, 1.0), (0.0, 1.0)) == "upper left"
