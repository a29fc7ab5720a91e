"""report.html from a real fit of the shipped simulated iiwa data: the summary on top, values
formatted for people, identifiability named by combination, the paper's TCP cloud (Fig. 5).

Content, not pixels: the tests read the HTML text (with the embedded images cut out) and check
the numbers against the fit they came from.
"""

from __future__ import annotations

import base64
import copy
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib.controller import apply_guards, controller_values
from calib.dataset import read_csv
from calib.fit import FitOptions, _scale, fit_offsets
from calib.kinematics import Chain
from calib.metrics import accuracy_metrics
from calib.model import load_robot_model
from calib.observability import observability
from calib.report import render_report, write_report
from calib.report_figures import tcp_clouds
from calib.report_format import num
from calib.result import result_dict

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
DATA = ROOT / "fixtures" / "datasets"
IMG = re.compile(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"')


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
    """The page without its embedded images."""
    return IMG.sub('src="…"', page)


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


def test_the_tcp_cloud_figure_is_embedded_and_its_numbers_are_the_fits(fitted):
    result, cal, doc, page = fitted
    assert '<h2 id=tcp>TCP cloud' in page
    m = re.search(r'<img alt="TCP cloud[^"]*" src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert m and base64.b64decode(m.group(1))[:8] == b"\x89PNG\r\n\x1a\n"
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


def test_report_is_written_and_the_module_does_not_import_matplotlib(fitted, tmp_path):
    result, cal, doc, _ = fitted
    path = write_report(tmp_path / "report.html", result, cal, doc)
    assert path.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    code = "import sys, calib.report; assert 'matplotlib' not in sys.modules, 'matplotlib imported'"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_tcp_legend_goes_to_the_corner_with_the_fewest_points():
    """The TCP figure's legend corner (in place of matplotlib's slow ``loc="best"``) avoids the data."""
    from calib.report_figures import _emptiest_corner

    rng = np.random.default_rng(0)
    cloud = rng.normal([0.6, 0.6], 0.1, (500, 2))  # upper right of a unit box
    assert _emptiest_corner(cloud, (0.0, 1.0), (0.0, 1.0)) == "lower left"
    assert _emptiest_corner(cloud * [-1, 1] + [1, 0], (0.0, 1.0), (0.0, 1.0)) == "lower right"
    assert _emptiest_corner(cloud * [1, -1] + [0, 1], (0.0, 1.0), (0.0, 1.0)) == "upper left"
