"""How accurate a robot is as it runs: its controller's nominal arm, scored held out.

What a controller that takes zero offsets runs is its nominal kinematics at the joint angles it
reports (plus whatever was entered, which changes what it reports). ``score_as_running(model,
data)`` measures that robot: per cross-validation fold it fits what any measurement must fit —
each sensor's registration and the tool (the markers, within their prior) — on the other folds'
configurations, with the nominal arm and no offsets, no link errors and no sag, and scores the
fold's configurations by the distance between measured and predicted marker positions. Nothing
scored was fitted on (``calib.fit.model_choice``'s folds: a pose group's branches stay together).

``joint_shift_rad`` scores the arm at the reported angles plus a shift: ``+δ`` is the robot
after entering δ (the controller then reports δ more for the same position), ``−δ`` on a
measurement made after the entry is the robot as found, replayed at the same configurations.

``predict_entry(model, data)`` is the held-out prediction of entering offsets fitted for the
controller (links at nominal, registration and tool free): per fold the offsets are fitted on
the other folds and scored, with their registration and tool refitted, on the fold's
configurations, beside the robot as found. It gives the ``heldout`` document a verification
(``calib.fit.verification``) checks. Units: mm, rad.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib.fit.model_choice import fold_labels
from calib.fit.offsets import FitOptions, fit_mode
from calib.measure.dataset import Dataset
from calib.robot.model import RobotModel

#: Folds of the held-out scores.
FOLDS = 5
#: Tolerance of the fold fits' Levenberg–Marquardt (prediction needs no more).
FOLD_TOL = 1e-8


@dataclass(frozen=True)
class ConfigErrors:
    """Held-out position error per configuration: ``configs`` (c,) ids, ``errors_mm`` (c,) the rms
    over the configuration's rows of |measured − predicted|, mm."""

    configs: np.ndarray
    errors_mm: np.ndarray

    def summary(self) -> dict:
        """``{"rms_mm", "mean_mm", "max_mm", "n"}`` over the configurations."""
        e = self.errors_mm
        return {"rms_mm": float(np.sqrt(np.mean(e**2))), "mean_mm": float(np.mean(e)), "max_mm": float(np.max(e)),
                "n": int(e.size)}

    def aligned(self, other: "ConfigErrors") -> tuple[np.ndarray, np.ndarray]:
        """(self, other) errors (c,) of the configurations both scored, in one order."""
        common, i, j = np.intersect1d(self.configs, other.configs, return_indices=True)
        return self.errors_mm[i], other.errors_mm[j]


def shifted(data: Dataset, joint_shift_rad: np.ndarray | None) -> Dataset:
    """``data`` with every reported joint vector moved by ``joint_shift_rad`` (n,) rad."""
    if joint_shift_rad is None:
        return data
    return replace(data, q_rad=data.q_rad + np.asarray(joint_shift_rad, dtype=float))


def _per_config(test: Dataset, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ids, inv = np.unique(test.config, return_inverse=True)
    inv = inv.ravel()
    return ids, np.sqrt(np.bincount(inv, dist**2) / np.bincount(inv))


def _folds(data: Dataset, k: int, seed: int):
    """(train, test) pairs of the cross-validation; ValueError with fewer than two folds."""
    labels, _ = fold_labels(data, k, seed)
    n_folds = int(labels.max()) + 1
    if n_folds < 2:
        raise ValueError(f"{len(np.unique(data.config))} configuration(s) cannot be scored held out: at least two "
                         "pose groups are needed (measure more configurations)")
    for f in range(n_folds):
        train, test = data.subset(labels != f), data.subset(labels == f)
        ok = np.isin(test.marker, np.unique(train.marker)) & np.isin(test.sensor, np.unique(train.sensor))
        if ok.any():
            yield train, test.subset(ok)


def _registration_and_tool(tool_prior_mm: float, seed: int) -> FitOptions:
    """Registration and tool only: no offset, links and sag at nominal."""
    return FitOptions(joints=(), link_tolerance=None, compliance=False, tool_prior_mm=tool_prior_mm, seed=seed)


def _nominal_errors(model: RobotModel, train: Dataset, test: Dataset, options: FitOptions) -> np.ndarray:
    mf = fit_mode(model, train, options, tol=FOLD_TOL)
    return np.linalg.norm(mf.predict_residuals(test), axis=1)


def score_as_running(model: RobotModel, data: Dataset, *, joint_shift_rad: np.ndarray | None = None, k: int = FOLDS,
                     tool_prior_mm: float = 10.0, seed: int = 0) -> ConfigErrors:
    """Held-out errors of the nominal arm at the reported angles (+ ``joint_shift_rad``) of
    ``data``, registration and tool fitted on the other folds (see the module docstring)."""
    data = shifted(data, joint_shift_rad)
    options = _registration_and_tool(tool_prior_mm, seed)
    ids, errs = [], []
    for train, test in _folds(data, k, seed):
        i, e = _per_config(test, _nominal_errors(model, train, test, options))
        ids.append(i)
        errs.append(e)
    return ConfigErrors(np.concatenate(ids), np.concatenate(errs))


def paired_improvement(before: ConfigErrors, after: ConfigErrors, *, metric: str = "mean_mm", n_boot: int = 4000,
                       seed: int = 0) -> dict:
    """``{"value", "ci95": [lo, hi], "metric", "n"}``: ``metric`` (``mean_mm`` or ``rms_mm``) of
    ``before`` less that of ``after`` over the configurations both scored, with a paired bootstrap
    95 % interval over those configurations (mm)."""
    if metric not in ("mean_mm", "rms_mm"):
        raise ValueError(f"metric must be mean_mm or rms_mm, given {metric!r}")
    b, a = before.aligned(after)
    if b.size < 2:
        raise ValueError(f"{b.size} configuration(s) scored before and after: at least two are needed")
    stat = (lambda e: np.mean(e, axis=-1)) if metric == "mean_mm" else (lambda e: np.sqrt(np.mean(e**2, axis=-1)))
    idx = np.random.default_rng(seed).integers(0, b.size, size=(n_boot, b.size))
    boot = stat(b[idx]) - stat(a[idx])
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return {"value": float(stat(b) - stat(a)), "ci95": [float(lo), float(hi)], "metric": metric, "n": int(b.size)}


def predict_entry(model: RobotModel, data: Dataset, *, k: int = FOLDS, tool_prior_mm: float = 10.0,
                  seed: int = 0) -> dict:
    """The held-out prediction of entering offsets fitted for the controller on ``data`` (see the
    module docstring): ``{"scored_on", "as_found", "entered", "improvement_mm", "metric"}``, each
    score ``{"rms_mm", "mean_mm", "max_mm", "n"}`` over configurations, mm."""
    n = model.n_joints
    reg_tool = _registration_and_tool(tool_prior_mm, seed)
    offsets = FitOptions(link_tolerance=None, compliance=False, tool_prior_mm=tool_prior_mm, seed=seed)
    ids, found, entered = [], [], []
    for train, test in _folds(data, k, seed):
        mf = fit_mode(model, train, offsets, tol=FOLD_TOL)
        delta = mf.post.full_vector(mf.theta)[:n]  # fixed (undetermined) offsets are 0: left unchanged
        i, e_found = _per_config(test, _nominal_errors(model, train, test, reg_tool))
        _, e_entered = _per_config(test, _nominal_errors(model, shifted(train, delta), shifted(test, delta), reg_tool))
        ids.append(i)
        found.append(e_found)
        entered.append(e_entered)
    ids = np.concatenate(ids)
    as_found = ConfigErrors(ids, np.concatenate(found))
    after = ConfigErrors(ids, np.concatenate(entered))
    return {
        "scored_on": f"{len(ids)} calibration configurations, {k}-fold cross-validation (offsets, registration and "
                     "tool fitted on the other folds; links at nominal)",
        "as_found": as_found.summary(),
        "entered": after.summary(),
        "improvement_mm": paired_improvement(as_found, after, seed=seed),
        "metric": "mean_mm",
    }
