"""The socket fit's ``report.html`` (``calib.report.report_socket``): it states what ``result.json``
states — method and model, every candidate's held-out error, the offsets with their intervals and
actions, the verdict with its reasons, the ball and its play, each held-out placement — and its
figures draw the document's numbers. The documents are real fits of simulated Panda socket data,
round-tripped through ``result.json``; nothing expected is hard-coded."""

from __future__ import annotations

import html as htmllib
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from acquire.run.socket_fit import run_socket_fit
from calib.fit.result import write_result
from calib.report.report_format import fixed
from calib.report.report_socket import render_socket_report, verdict
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from tests.calib import svgread
from tests.calib.socket_sim import simulate, true_params

# One xdist worker runs this file: its module fixture (a socket fit) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("calib/test_report_socket")

PANDA = Path(__file__).resolve().parents[2] / "fixtures" / "robots" / "franka_panda.yaml"


def _as_file(doc: dict, tmp: Path) -> dict:
    """The document as ``acquire fit -o`` writes it and a reader gets it back."""
    write_result(tmp / "result.json", doc)
    return json.loads((tmp / "result.json").read_text())


@pytest.fixture(scope="module")
def auto_doc(tmp_path_factory) -> dict:
    model = load_robot_model(PANDA)
    rng = np.random.default_rng(2)
    ds, _ = simulate(model, true_params(Chain(model), rng, link_mm=0.5, twist_deg=0.3), rng, per_socket=8)
    doc, _ = run_socket_fit(model, ds, method="auto", link_tolerance=None)
    return _as_file(doc, tmp_path_factory.mktemp("auto"))


def _text(fragment: str) -> str:
    return htmllib.unescape(re.sub(r"<[^>]+>", "", fragment))


def _rows(page: str, start: str, end: str | None = None) -> list[list[str]]:
    """The table rows (cells as text) between the ids/markers ``start`` and ``end``."""
    part = page[page.index(start): page.index(end) if end else len(page)]
    part = re.sub(r"<svg\b.*?</svg>", "", part, flags=re.S)
    return [[_text(c).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", r, flags=re.S)]
            for r in re.findall(r"<tr>(.*?)</tr>", part, flags=re.S)]


def _num(text: str) -> float:
    return float(text.replace("−", "-").replace("+", ""))


def test_the_report_states_the_numbers_of_result_json(auto_doc):
    doc = auto_doc
    page = render_socket_report(doc)
    text = _text(page)
    fm, mc = doc["fit_model"], doc["model_choice"]
    # which method and model ran
    assert f"method {fm['method']} — model {fm['model']} — fitted model: {fm['description']}" in text
    # the verdict, as the document has it
    fitted = [j for j in doc["joint_offsets"] if j["status"] == "fitted"]
    what, reasons = verdict(doc)
    if what == "enter":
        n = len(fitted)
        assert f"Enter the offsets of {n} ax{'is' if n == 1 else 'es'} below" in text and "DO NOT ENTER" not in text
    else:
        assert "DO NOT ENTER these offsets." in text and all(r in text for r in reasons)
    # the offsets: value, std, 95 % interval and the action of every axis
    rows = {r[0]: r for r in _rows(page, "id=offsets", "id=ball") if len(r) == 5}
    assert sorted(rows) == sorted(j["joint"] for j in doc["joint_offsets"])
    for j in doc["joint_offsets"]:
        r = rows[j["joint"]]
        action = {"fitted": "enter", "undetermined": "leave unchanged"}.get(j["status"], "do not enter")
        assert r[4] == action
        if j["value_deg"] is None:
            assert r[1] == r[2] == r[3] == "—"
            continue
        assert _num(r[1]) == pytest.approx(j["value_deg"], abs=5e-5) and _num(r[2]) == pytest.approx(j["std_deg"], abs=5e-5)
        lo, hi = (_num(v) for v in r[3].strip("[]").split(","))
        assert (lo, hi) == pytest.approx(tuple(j["ci95_deg"]), abs=5e-5)
        if j["reason"]:
            assert j["reason"] in text
    # every candidate's held-out error, the chosen one marked
    table = _rows(page, "id=model-choice", "id=offsets")
    for c in [mc["nominal"]] + mc["candidates"]:
        row = next(r for r in table if r and r[0].split(" ←")[0] == c["model"])
        if c["cv_rms_mm"] is not None:
            assert _num(row[2]) == pytest.approx(c["cv_rms_mm"], abs=5e-5)
            mean, se = (_num(v) for v in row[3].split("±"))
            assert (mean, se) == pytest.approx((c["cv_mean_mm"], c["cv_se_mm"]), abs=5e-5)
        assert row[0].endswith("← chosen") == (c["model"] == mc["chosen"])
    # the ball on the flange and its play
    ball = {r[0]: r for r in _rows(page, "id=ball", "id=links") if len(r) == 3}
    for axis, v, s in zip("xyz", doc["ball_mm"]["value"], doc["ball_mm"]["std"]):
        assert (_num(ball[axis][1]), _num(ball[axis][2])) == pytest.approx((v, s), abs=5e-5)
    assert f"σ = {fixed(doc['sigma_point_mm'], 4)} mm" in text
    # each held-out placement, before → after
    held = {r[0]: r for r in _rows(page, "id=held-out") if len(r) == 6}
    assert sorted(held) == sorted(h["placement"] for h in doc["scores"]["held_out"]) and held
    for h in doc["scores"]["held_out"]:
        r = held[h["placement"]]
        assert int(r[1]) == len(h["configurations"])
        assert (_num(r[2]), _num(r[3])) == pytest.approx((h["before"]["spread_mm"], h["after"]["spread_mm"]), abs=5e-5)


def test_the_held_out_figure_draws_every_held_out_configuration(auto_doc):
    """One panel per held-out placement; its dots are the document's per-configuration distances, and
    their rms is the placement's spread (computed separately by ``socket_scores``)."""
    page = render_socket_report(auto_doc)
    figs = svgread.svgs(page[page.index("id=held-out"):])
    held = auto_doc["scores"]["held_out"]
    assert len(figs) == len(held)
    for fig, h in zip(figs, held):
        (ax,) = svgread.axes(fig)
        assert ax.logy
        for label, key, spread in (("before (data sheet)", "before_mm", h["before"]["spread_mm"]),
                                   ("after (fit on the others)", "after_mm", h["after"]["spread_mm"])):
            values = np.array([c[key] for c in h["configurations"]])
            assert math.sqrt(np.mean(values**2)) == pytest.approx(spread, rel=1e-9)
            dots = ax.scatter(label)
            inside = (values >= ax.ylim[0]) & (values <= ax.ylim[1])
            assert inside.all() and len(dots) == len(values)
            assert np.allclose(dots[:, 1], values, rtol=0.01)  # 0.1 px on a log axis
        assert np.all([c["after_mm"] for c in h["configurations"]] != np.array([c["before_mm"] for c in h["configurations"]]))


def test_the_candidates_figure_draws_each_held_out_mean_and_standard_error(auto_doc):
    mc = auto_doc["model_choice"]
    page = render_socket_report(auto_doc)
    fig = svgread.svgs(page[page.index("id=model-choice"):page.index("id=offsets")])[0]
    (ax,) = svgread.axes(fig)
    scored = [c for c in [mc["nominal"]] + mc["candidates"] if c["cv_mean_mm"] is not None]
    bars = ax.lines()
    assert len(bars) == len(scored)
    for bar, c in zip(bars, scored):
        lo, hi = 10 ** bar[:, 0]
        assert hi == pytest.approx(c["cv_mean_mm"] + c["cv_se_mm"], rel=0.01)
        assert lo == pytest.approx(max(c["cv_mean_mm"] - c["cv_se_mm"], c["cv_mean_mm"] / 3), rel=0.01)


def test_a_fit_that_must_not_be_entered_says_so_with_its_reason(tmp_path):
    """A loose ball (2 mm of play): the fit refuses every offset; the report's banner says DO NOT
    ENTER with the document's reason, and no axis is marked "enter"."""
    model = load_robot_model(PANDA)
    rng = np.random.default_rng(5)
    ds, _ = simulate(model, true_params(Chain(model), rng), rng, per_socket=6, play_mm=2.0)
    doc, _ = run_socket_fit(model, ds, method="fast", link_tolerance=(0.2, 0.02))
    doc = _as_file(doc, tmp_path)
    assert not doc["trusted"] and doc["do_not_enter_reason"]
    text = _text(render_socket_report(doc))
    assert "DO NOT ENTER these offsets." in text and doc["do_not_enter_reason"] in text
    assert "Enter the offsets" not in text
    assert f"method fast — fitted model: {doc['fit_model']['description']}" in text
    rows = _rows(render_socket_report(doc), "id=offsets", "id=ball")
    assert not any(r[-1] == "enter" for r in rows if r)


def test_a_tracker_document_is_refused():
    with pytest.raises(ValueError, match="not a socket fit"):
        render_socket_report({"kind": "offsets"})


def test_the_held_out_distances_equal_an_independent_scorer(tmp_path):
    """Each held-out configuration's distance in result.json (and so in the report) equals one computed
    here from the raw kinematics: the fit on the other placements (the same call the command makes),
    the ball carried by an explicit product of standard-DH link matrices (``_dh_flange``, not
    ``calib.robot.kinematics``), and the held-out socket's place the mean of its predictions."""
    from calib.fit.socket import fit_socket
    from tests.calib.test_canonical import _dh_flange

    model = load_robot_model(PANDA)
    chain = Chain(model)
    rng = np.random.default_rng(7)
    ds, _ = simulate(model, true_params(chain, rng, link_mm=0.3, twist_deg=0.1), rng, per_socket=6)
    doc = _as_file(run_socket_fit(model, ds, method="fast", link_tolerance=(0.2, 0.02))[0], tmp_path)
    held = doc["scores"]["held_out"]
    assert [h["placement"] for h in held] == ds.placements
    for h in held:
        train = ds.subset([p for p in ds.placements if p != h["placement"]])
        test = ds.subset([h["placement"]])
        params = fit_socket(model, train, tolerance=(0.2, 0.02), compliance=False).params
        ball = np.append(params[chain.marker_slice()][:3], 1.0)
        pos = np.array([(_dh_flange(model, params, q) @ ball)[:3] for q in test.q_rad])
        centre = {g: pos[test.group == g].mean(axis=0) for g in set(test.group.tolist())}
        mine = np.array([np.linalg.norm(p - centre[g]) for p, g in zip(pos, test.group)])
        theirs = np.array([c["after_mm"] for c in h["configurations"]])
        assert len(h["configurations"]) == len(test.q_rad)
        assert [c["socket"] for c in h["configurations"]] == [test.groups[g][1] for g in test.group]
        np.testing.assert_allclose(theirs, mine, rtol=0, atol=1e-9)
        assert math.sqrt(np.mean(mine**2)) == pytest.approx(h["after"]["spread_mm"], abs=1e-9)
