"""The fleet's pages in a real browser (headless Chromium, skipped where none is installed): on a
phone-wide screen (390 px) the figures scale down, so the drifted run's red marker — drawn near the
right edge of a 760 px figure — is on screen, and the page does not scroll sideways."""

import shutil
import subprocess

import numpy as np
import pytest

from acquire.station.fleet import write_pages
from acquire.station.history import add_entry

pytestmark = pytest.mark.slow
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
RED = np.array([0xD6, 0x27, 0x28])


def _entry(run_id, day, a1, kind):
    return {"run_id": run_id, "finished": f"2026-02-{day:02d}T00:00:00+00:00", "site": "plant-a", "cell": "c1",
            "kind": kind, "n_configurations": 40 if kind == "calibration" else 8, "entered": kind == "calibration",
            "joints": ["A1", "A2"], "offsets_deg": [a1, 0.0], "std_deg": [0.01, 0.01], "ci95_deg": [None, None],
            "accuracy_mm": {"before": 0.4, "after": 0.3}, "drift": None}


def _screenshot(page, out, width: int):
    subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--window-size={width},1400", f"--screenshot={out}", page.as_uri()],
                   check=True, capture_output=True, timeout=120)
    image = pytest.importorskip("PIL.Image", reason="Pillow reads the screenshot")
    return np.asarray(image.open(out).convert("RGB")).astype(int)


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (apt-get install chromium)")
def test_a_robot_page_fits_a_phone_and_shows_the_drifted_run(tmp_path):
    add_entry(tmp_path, "R-1", _entry("cal1", 1, -0.186, "calibration"))
    add_entry(tmp_path, "R-1", _entry("chk1", 20, 0.2, "check"))
    (tmp_path / "html").mkdir()
    write_pages(tmp_path, tmp_path / "html")
    phone = _screenshot(tmp_path / "html" / "R-1.html", tmp_path / "phone.png", 390)
    assert phone.shape[1] == 390
    red = np.all(np.abs(phone - RED) < 30, axis=2)
    _, xs = np.nonzero(red)
    # The check sits at 699 px of the 760 px figure: unscaled it would be off a 390 px screen; scaled, ~345 px.
    assert ((xs > 300) & (xs < 390)).any(), "the drifted run's red marker is not on a 390 px screen"
    index = _screenshot(tmp_path / "html" / "index.html", tmp_path / "index.png", 390)
    assert (index < 200).any(axis=2).sum() > 1000   # text was drawn
