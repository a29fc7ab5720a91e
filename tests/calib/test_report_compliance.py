"""The fitted joint compliances are in report.html (fast fit and full identification): every
axis's value and 95 % interval as the fit gives them, undetermined axes labelled with the reason."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np

from calib.robot.controller import apply_guards
from calib.fit.offsets import FitOptions, fit_offsets
from calib.fit.identification import IdentOptions, ident_result_dict, identify
from calib.robot.model import load_robot_model
from calib.report.html import render_report
from calib.report.report_ident import render_ident_report
from calib.fit.result import result_dict
from tests.calib.test_gravity import K_TRUE, ROBOTS, _dataset, _real_cell


class _Tables(HTMLParser):
    """Rows (lists of cell texts) of the table after the heading whose text starts with ``title``."""

    def __init__(self, title: str):
        super().__init__()
        self.title, self.in_h2, self.h2, self.on, self.rows, self.cell = title, False, "", False, [], None

    def handle_starttag(self, tag, attrs):
        if tag == "h2":
            self.in_h2, self.h2 = True, ""
            self.on = False
        elif self.on and tag == "tr":
            self.rows.append([])
        elif self.on and tag in ("td", "th"):
            self.cell = ""

    def handle_endtag(self, tag):
        if tag == "h2":
            self.in_h2 = False
            self.on = self.h2.startswith(self.title)
        elif self.on and tag in ("td", "th") and self.cell is not None:
            self.rows[-1].append(self.cell.strip())
            self.cell = None

    def handle_data(self, data):
        if self.in_h2:
            self.h2 += data
        elif self.cell is not None:
            self.cell += data


def _rows(page: str) -> dict[str, list[str]]:
    p = _Tables("Joint compliances")
    p.feed(page)
    assert p.rows, "no compliance section in the report"
    out, last = {}, None
    for r in p.rows[1:]:
        if len(r) == 5:
            out[r[0]] = r
            last = r[0]
        elif len(r) == 1 and last:  # the note line under a row: the reason
            out[last] = out[last] + r
    return out


def _number(text: str) -> float:
    return float(text.replace("−", "-"))


def _interval(text: str) -> tuple[float, float]:
    lo, hi = re.fullmatch(r"\[(.+), (.+)\]", text).groups()
    return _number(lo), _number(hi)


def test_fast_fit_report_shows_the_compliances_with_intervals():
    model = load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml")
    data, _ = _real_cell(model, 0)
    result = fit_offsets(model, data, FitOptions(n_draws=300, compliance=True))
    doc = result_dict(result, data)
    apply_guards(doc)
    rows = _rows(render_report(result, data, doc))
    comp = doc["diagnostics"]["compliance"]
    assert [c["joint"] for c in comp] == list(rows)
    fitted = [c for c in comp if c["status"] == "fitted"]
    assert fitted and any(c["status"] == "undetermined" for c in comp)
    for c in comp:
        r = rows[c["joint"]]
        if c["status"] == "fitted":
            assert abs(_number(r[1]) - c["value"] * 1e6) <= 0.005 * abs(c["value"] * 1e6) + 1e-9
            lo, hi = _interval(r[3])
            assert abs(lo - c["ci95"][0] * 1e6) <= 0.01 * abs(c["ci95"][0] * 1e6) + 0.01
            assert abs(hi - c["ci95"][1] * 1e6) <= 0.01 * abs(c["ci95"][1] * 1e6) + 0.01
            assert r[4] == "fitted"
        else:
            assert r[4] == "undetermined" and r[1] == "—" and r[5] == c["reason"]


def test_full_identification_report_shows_the_compliances():
    model = load_robot_model(ROBOTS / "kuka_iiwa14_r820.yaml")
    q = np.random.default_rng(100).uniform(model.lower_limits_rad * 0.8, model.upper_limits_rad * 0.8, (60, 7))
    data, _ = _dataset(model, q, K_TRUE, seed=0)
    result = identify(model, data, IdentOptions(compliance=True, n_starts=2))
    doc = ident_result_dict(result, data)
    rows = _rows(render_ident_report(result, data, doc))
    for c in doc["compliance"]:
        r = rows[c["joint"]]
        if c["status"] == "fitted":
            assert abs(_number(r[1]) - c["value"] * 1e6) <= 0.005 * abs(c["value"] * 1e6)
            lo, hi = _interval(r[3])
            assert abs(lo - (c["value"] - 1.96 * c["std"]) * 1e6) <= 0.01 * abs(c["value"] * 1e6)
            assert abs(hi - (c["value"] + 1.96 * c["std"]) * 1e6) <= 0.01 * abs(c["value"] * 1e6)
        else:
            assert r[4] == "undetermined" and "gravity turns this axis by only" in r[5]
    assert sum(c["status"] == "fitted" for c in doc["compliance"]) == 3
