"""The model-choice table in the reports: the identification report of a default fit that chose (or
was forced to) full identification shows every candidate, full included, with its held-out error;
socket documents' tables render the same way."""

from __future__ import annotations

import re

from calib.fit.auto_fit import auto_fit
from calib.fit.offsets import FitOptions
from calib.report.report_choice import model_choice_section
from calib.report.report_ident import render_ident_report
from tests.calib.test_model_choice import cell


def _rows(html: str) -> list[str]:
    return [re.sub(r"<[^>]+>", "", r) for r in re.findall(r"<tr>(.*?)</tr>", html, flags=re.S)]


def test_identification_report_of_the_default_shows_every_candidate_with_its_held_out_error(monkeypatch):
    import calib.fit.model_choice as mc

    model, _, cal = cell(5, k=24)
    real = mc.one_se_choice
    monkeypatch.setattr(mc, "one_se_choice", lambda scores: "full" if any(s.name == "full" for s in scores) else real(scores))
    done = auto_fit(model, cal, None, FitOptions(n_draws=200), n_starts=1, n_random=20)  # every candidate, full chosen
    assert done.ident is not None
    html = render_ident_report(done.ident, cal, done.doc)
    mc = done.doc["model_choice"]
    rows = _rows(html[html.index("id=model-choice"):])
    for c in [mc["nominal"]] + mc["candidates"]:
        row = next(r for r in rows if r.startswith(c["model"]))
        if c["cv_rms_mm"] is not None:
            assert f"{c['cv_rms_mm']:.4f}" in row, row
    assert any(r.startswith("full ← chosen") for r in rows)
    assert {c["model"] for c in mc["candidates"]} >= {"offsets", "offsets+tool", "offsets+tool+links", "full"}
    assert "link prior of offsets+tool+links (empirical Bayes" in html and "lengths ±" in html and "angles ±" in html


def test_socket_model_choice_renders_with_one_link_prior_per_links_candidate():
    mc = {"chosen": "offsets+ball+links", "forced": False, "folds": 3, "grouped_by": "placement",
          "rule": "the simplest model within one standard error of the best cross-validated mean error",
          "nominal": {"model": "nominal (data sheet, ball from the training data)", "free_parameters": 0,
                      "cv_rms_mm": 0.5, "cv_mean_mm": 0.45, "cv_se_mm": 0.02, "failed": None},
          "candidates": [{"model": "offsets", "free_parameters": 6, "cv_rms_mm": None, "cv_mean_mm": None,
                          "cv_se_mm": None, "failed": "fold 2: the fit did not converge"},
                         {"model": "offsets+ball+links", "free_parameters": 25, "cv_rms_mm": 0.2, "cv_mean_mm": 0.18,
                          "cv_se_mm": 0.01, "failed": None}],
          "link_scale": {"offsets+ball+links": {"length_mm": 0.3, "angle_deg": 0.1}}}
    html = "\n".join(model_choice_section({"model_choice": mc}))
    rows = _rows(html)
    assert any(r.startswith("offsets") and "failed: fold 2" in r for r in rows)
    assert any(r.startswith("offsets+ball+links ← chosen") and "0.2000" in r for r in rows)
    assert "link prior of offsets+ball+links (empirical Bayes" in html and "lengths ±0.3 mm, angles ±0.1°" in html
    assert model_choice_section({}) == []


def test_the_offsets_report_summary_names_the_link_scales_the_evidence_chose():
    from calib.report.report_summary import summary_html

    model, _, cal = cell(6, k=24, link_mm=0.3, angle_deg=0.05)
    done = auto_fit(model, cal, None, FitOptions(n_draws=200), force="offsets+tool+links", include_full=False,
                    n_random=20)
    sc = done.doc["model_choice"]["link_scale"]
    html = summary_html(done.doc)
    assert f"lengths ±{sc['length_mm']:g} mm, angles ±{sc['angle_deg']:g}°" in html
    assert any(r.startswith("offsets+tool+links ← chosen (--model)") for r in _rows(html))
