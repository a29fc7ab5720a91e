"""Scoring poses held out: position and attitude errors of rows a zero-offset fit never saw,
predicted with that fit's registration, tool and target frames (nothing re-fitted on them), and
the paper's EACPE/EMCPE/EACAE/EMCAE before and after.

Kept apart from ``calib.fit.attitude`` (the attitude rows of a posterior): scoring builds
posteriors and uses the identification's metrics, which themselves build on the attitude rows.
"""

from __future__ import annotations

import numpy as np

from calib.fit.identification import comprehensive_errors
from calib.fit.posterior import OffsetPosterior
from calib.measure.dataset import Dataset


def fitted_frames(post, theta: np.ndarray) -> dict[str, np.ndarray]:
    """Marker name → R_flange←target (3, 3) at the free vector ``theta`` of a posterior with attitude
    rows: the model's where known, else the profiled (weighted chordal mean) frame."""
    att = post.attitude
    if att is None:
        return {}
    frames = att.frames(att._sensor_flange(post, post.full_vector(theta)))
    return {m: frames[np.flatnonzero(att.frame_index == f)[0]] for f, m in enumerate(att.frame_markers)}


def held_out_pose_errors(mode_fit, data: Dataset, frames: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Position errors (k,) mm and attitude errors (ko,) rad of other rows ``data`` predicted by a
    zero-offset fit (``calib.fit.offsets.ModeFit``) with its own registration, tool and the target
    frames ``frames`` (e.g. ``fitted_frames`` of the calibration): nothing is re-fitted on ``data``.
    The attitude errors are of the rows that carry an orientation (none: an empty array)."""
    return pose_errors_at(mode_fit.post, mode_fit.theta, mode_fit.b2s0, data, frames)


def pose_errors_at(post, theta: np.ndarray, b2s0: dict[str, np.ndarray], data: Dataset,
                   frames: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """As ``held_out_pose_errors`` for a posterior ``post`` at its free vector ``theta`` (initial
    registrations ``b2s0``)."""
    other = OffsetPosterior(post.chain, data, b2s0, post.mask, error=post.error, nu=post.nu,
                            link_prior=dict(zip(post.link_idx.tolist(), post.link_sd.tolist())), compliance=bool(post.C),
                            sag_params=post.sag_params if post.C else None, orientation=data.has_orientation)
    pos = np.linalg.norm(other.position_residuals(theta), axis=-1)
    att = other.attitude
    if att is None:
        return pos, np.zeros(0)
    missing = sorted(set(att.frame_markers) - set(frames))
    if missing:
        raise ValueError(f"no target frame for marker(s) {missing}: give the calibration's (fitted_frames)")
    att.frame0 = np.stack([frames[m] for m in att.frame_markers])
    att.known = np.ones(len(att.frame_markers), bool)
    e = att.residuals(other, other.full_vector(theta)) / att.weight[:, None]
    return pos, np.linalg.norm(e, axis=-1)


def pose_metrics(post, theta: np.ndarray, b2s0: dict[str, np.ndarray], cal: Dataset, val: Dataset | None) -> dict:
    """EACPE/EMCPE (mm) and EACAE/EMCAE (°) before and after a zero-offset fit with attitude rows,
    on the calibration rows and, if given, the validation rows — both scored with the calibration's
    registration, tool and target frames (nothing re-fitted on the validation). "before": the
    nominal robot (all corrections zero) with the initial registration and the target frame the
    calibration's orientations give for it. ``post``: the fit's posterior on ``cal``; ``theta`` its
    free vector (the mode)."""
    out = {}
    zero = np.zeros_like(theta)
    frames = {"before": fitted_frames(post, zero), "after": fitted_frames(post, theta)}
    for part, data in (("calibration", cal), ("validation", val)):
        if data is None or len(data) == 0:
            continue
        entry = {}
        for when, t in (("before", zero), ("after", theta)):
            p, a = pose_errors_at(post, t, b2s0, data, frames[when])
            entry[when] = comprehensive_errors(p, a if a.size else None)
        out[part] = entry
    return out
