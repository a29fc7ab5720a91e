"""The noise of data that state no spreads, estimated from the data (never a silent fixed weight).

A row's spread (``Dataset.std_mm``; ``att_std_rad`` for a measured orientation) sets two things:
the weight of attitude rows against position rows (``calib.fit.attitude``: σ_position / σ_attitude)
and the noise the held-out error is checked against ("enter" is earned, ``calib.robot.controller``).
A file without std columns (a plain CSV, an IPA series without ``measurement_std_*``) gets them here:

per sensor and per kind (position, attitude), the rms residual per axis of the richest offsets
model — zero-offsets, registration, tool, every link parameter under a wide prior (``LINK_PRIOR``:
1 mm, 0.1°) and, where the robot model gives link masses, the joints' compliance — with the free
parameters' share of the degrees of freedom taken out: σ² = Σ r² / (3·rows − p·rows/all rows).
The attitude weight depends on the estimate and the estimate on the fit, so the two are iterated
(``ROUNDS``; the weight settles within a few per cent).

What the estimate is: an **upper bound** on the sensor's noise — it also holds robot error that
model does not describe (backlash, temperature, sag beyond one compliance per joint). It is printed
with the fit and written to ``result.json`` (``noise_estimate``), and the rows carry it as their
spread (``count`` 1).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from calib.fit.offsets import FitOptions, fit_mode
from calib.measure.dataset import Dataset
from calib.robot.model import RobotModel

#: Link prior (mm, deg) of the model whose residuals estimate the noise.
LINK_PRIOR = (1.0, 0.1)
#: Fits of the estimate (the attitude weight follows the previous round's estimate).
ROUNDS = 3


def needs_estimate(data: Dataset) -> bool:
    """Whether some row lacks a spread (a position spread, or an attitude spread where orientation is measured)."""
    if not np.all(np.isfinite(data.std_mm) & (data.std_mm > 0)):
        return True
    if data.has_orientation:
        att = data.att_std_rad[data.oriented]
        return not np.all(np.isfinite(att) & (att > 0))
    return False


def _per_sensor(post, theta: np.ndarray) -> dict[str, dict]:
    """Per sensor: position σ (mm per axis) and, with orientation, attitude σ (rad per axis)."""
    data = post.data
    r_pos = post.position_residuals(theta)  # (k, 3) mm
    rows_att = post.attitude.rows if post.attitude is not None else np.zeros(0, int)
    r_att = (post.attitude.residuals(post, post.full_vector(theta)) / post.attitude.weight[:, None]
             if post.attitude is not None else np.zeros((0, 3)))
    n_all = len(data) + rows_att.size
    share = post.dim / n_all  # free parameters per row
    out = {}
    for s in data.sensors:
        pos = data.sensor == s
        att = data.sensor[rows_att] == s
        entry = {"rows": int(pos.sum()),
                 "position_mm": math.sqrt(float(np.sum(r_pos[pos] ** 2)) / max(3 * pos.sum() - share * pos.sum(), 1.0))}
        if att.any():
            entry["attitude_rows"] = int(att.sum())
            entry["attitude_rad"] = math.sqrt(float(np.sum(r_att[att] ** 2)) / max(3 * att.sum() - share * att.sum(), 1.0))
        out[s] = entry
    return out


def _with_spreads(data: Dataset, sigma: dict[str, dict], keep: Dataset) -> Dataset:
    """``data`` with the estimated spreads where ``keep`` (the original) has none."""
    std = keep.std_mm.copy()
    count = keep.count.copy()
    missing = ~(np.isfinite(std) & (std > 0))
    for s, e in sigma.items():
        rows = missing & (keep.sensor == s)
        std[rows], count[rows] = e["position_mm"], 1
    att = keep.att_std_rad
    if keep.has_orientation:
        att = att.copy()
        gap = keep.oriented & ~(np.isfinite(att) & (att > 0))
        for s, e in sigma.items():
            if "attitude_rad" in e:
                att[gap & (keep.sensor == s)] = e["attitude_rad"]
    return replace(data, std_mm=std, count=count, att_std_rad=att)


def estimate_noise(model: RobotModel, data: Dataset, base: FitOptions = FitOptions()) -> tuple[Dataset, dict] | None:
    """(``data`` with estimated spreads where it has none, the estimate's document) or None when
    every row states its spread. Document: {"how", "sensors": {name: {"position_mm", "attitude_deg"?,
    "rows", "attitude_rows"?}}, "attitude_weight_mm_per_rad"?}."""
    if not needs_estimate(data):
        return None
    options = replace(base, method="laplace", link_tolerance=LINK_PRIOR, compliance=model.has_dynamics)
    current = data
    sigma: dict[str, dict] = {}
    for _ in range(ROUNDS):
        mf = fit_mode(model, current, options, tol=1e-8)
        sigma = _per_sensor(mf.post, mf.theta)
        current = _with_spreads(data, sigma, data)
    model_name = "offsets+tool+links" + ("+compliance" if model.has_dynamics else "")
    doc = {"how": (f"estimated from the data: per sensor and kind, the rms residual per axis of the {model_name} fit "
                   f"(link prior ±{LINK_PRIOR[0]:g} mm, ±{LINK_PRIOR[1]:g}°; degrees of freedom of its free parameters "
                   "taken out) — an upper bound on the sensor's noise (robot error no model describes is in it)"),
           "sensors": {s: {k: (math.degrees(v) if k == "attitude_rad" else v) for k, v in e.items()} for s, e in sigma.items()}}
    for e in doc["sensors"].values():
        if "attitude_rad" in e:
            e["attitude_deg"] = e.pop("attitude_rad")
    weights = [e["position_mm"] / e["attitude_rad"] for e in sigma.values() if e.get("attitude_rad")]
    if weights:
        doc["attitude_weight_mm_per_rad"] = float(np.median(weights))
    return current, doc


def format_estimate(doc: dict) -> str:
    """One line per sensor for the terminal."""
    lines = ["noise: the data state no spreads — " + doc["how"]]
    for s, e in doc["sensors"].items():
        att = (f", attitude {e['attitude_deg'] * 3600:.2f}″ ({e['attitude_deg']:.5f}°) per axis over {e['attitude_rows']} rows"
               if "attitude_deg" in e else "")
        lines.append(f"  sensor {s}: position {e['position_mm']:.4f} mm per axis over {e['rows']} rows{att}")
    if "attitude_weight_mm_per_rad" in doc:
        lines.append(f"  attitude rows weighted {doc['attitude_weight_mm_per_rad']:.0f} mm/rad (σ_position / σ_attitude)")
    return "\n".join(lines)
