"""The fit's result file: ``FitResult`` (plus metrics and controller values) → ``result.json``.

Layout (``format: "remaster.fit/1"``; angles in degrees, lengths in mm)::

    robot            name, controller, axes
    data             source, n_measurements, n_configurations, sensors, markers
    joint_offsets    per joint: joint, value_deg, std_deg, ci95_deg [lo, hi], identifiable,
                     status ("fitted" | "undetermined" | "fixed"), reason, sandwich_std_ratio
                     (model-robust std ÷ posterior std, ``calib.fit.offsets.sandwich_std``)
    registration     per sensor: base2sensor (4×4, p_sensor = M · p_base, mm),
                     base2sensor_initial, corrections {x_mm, y_mm, z_mm, alpha_deg, beta_deg,
                     gamma_deg: {value, std, free}} (T* = Trans(x,y,z)·Rz(α)Ry(β)Rx(γ), applied
                     on the left of the initial registration, eq. 8)
    tool             prior_mm (0: the model's markers taken as exact), markers: per fitted marker
                     {marker, nominal_mm, value_mm, std_mm, ci95_mm [[lo, hi] ×3], prior_mm} in the
                     flange frame; degeneracies: sentences naming what only the priors decide
    sigma_mm         per sensor: {value, std}
    diagnostics      method, sampler, chains, draws, acceptance, rhat/ess per parameter,
                     rhat_max, ess_min, timings (s)
    identifiability  start / estimate: singular values (mm per scaled unit), condition number,
                     rank, undetermined combinations, directions [{combination, loadings,
                     singular_value_mm, exact, verdict, why, std_mm, condition}]; fixed_parameters [{parameter, reason}]
                     (fixed before sampling); undetermined_at_estimate [{parameter, reason}]
                     (sampled, but the posterior is too wide to enter a value)
    metrics          see ``calib.fit.metrics.accuracy_metrics`` (each metric: before / after with
                     mean, p2_5, p97_5, max in mm)
    controller       see ``calib.robot.controller``

An offset that the data cannot determine is written with ``value_deg: null``, ``std_deg: null``,
``identifiable: false`` and the reason; an offset excluded from the fit is ``value_deg: 0``
(kept nominal) with ``identifiable: false``. Neither ever carries a standard deviation.
JSON has no NaN: non-finite numbers are written as ``null``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from calib.measure.dataset import Dataset
from calib.fit.offsets import FitResult
from calib.plan.identifiability import Identifiability, verdicts
from calib.fit.posterior import REG_NAMES

FORMAT = "remaster.fit/1"
_REG_KEYS = ("x_mm", "y_mm", "z_mm", "alpha_deg", "beta_deg", "gamma_deg")


def _num(v: float | None) -> float | None:
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def jsonable(obj):
    """Recursively convert numpy values and non-finite floats to JSON-safe Python values."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        return _num(obj)
    return obj


def split_status(status: str) -> tuple[str, str]:
    """``"undetermined: why"`` → ("undetermined", "why"); ``"fitted"`` → ("fitted", "")."""
    kind, _, reason = status.partition(": ")
    return kind, reason


def joint_offsets(result: FitResult) -> list[dict]:
    """Per-joint entries of ``joint_offsets`` (degrees; values in (−180°, 180°])."""
    from calib.robot.canonical import wrap_angle

    out = []
    ratios = dict(zip(result.posterior.free_names, result.diagnostics.get("sandwich_std_ratio", [])))
    for i, (axis, status) in enumerate(zip(result.model.axis_names, result.offset_status)):
        kind, reason = split_status(status)
        fitted = kind == "fitted"
        # Reported in (−180°, 180°]; the interval moves with the value (whole turns only).
        turn = wrap_angle(result.offsets_rad[i]) - result.offsets_rad[i] if fitted else 0.0
        entry = {
            "joint": axis,
            "index": i + 1,
            "value_deg": math.degrees(result.offsets_rad[i] + turn) if fitted else (0.0 if kind == "fixed" else None),
            "std_deg": math.degrees(result.offsets_std_rad[i]) if fitted else None,
            "ci95_deg": [math.degrees(v + turn) for v in result.offsets_ci95_rad[i]] if fitted else None,
            "identifiable": fitted,
            "sandwich_std_ratio": ratios.get(f"{axis}.offset") if fitted else None,
            "status": kind,
            "reason": reason,
        }
        out.append(entry)
    return out


def registration(result: FitResult) -> dict:
    """Per sensor: final and initial base2sensor, corrections with std (mm, deg)."""
    post = result.posterior
    full = result.full_samples
    n = post.n
    out = {}
    for k, s in enumerate(post.sensors):
        cols = full[:, n + 6 * k : n + 6 * k + 6]
        free = post.mask.registration[k]
        corr = {}
        for j, (name, key) in enumerate(zip(REG_NAMES, _REG_KEYS)):
            unit = 1.0 if key.endswith("_mm") else 180.0 / math.pi
            corr[key] = {
                "value": float(cols[:, j].mean() * unit),
                "std": float(cols[:, j].std(ddof=1) * unit) if free[j] else None,
                "free": bool(free[j]),
            }
            if not free[j]:
                corr[key]["reason"] = post.mask.reasons.get(f"{s}.{name}", "")
        out[s] = {
            "base2sensor": result.base2sensor[s],
            "base2sensor_initial": result.base2sensor0[s],
            "corrections": corr,
        }
    return out


def diagnostics(result: FitResult) -> dict:
    """Sampler settings and convergence: R-hat and ESS per parameter, their worst values."""
    d = dict(result.diagnostics)
    names = d.get("parameters", [])
    if "rhat" in d:
        d["rhat"] = dict(zip(names, d["rhat"]))
        d["rhat_max"] = max(d["rhat"].values())
    if "ess" in d:
        d["ess"] = dict(zip(names, d["ess"]))
        d["ess_min"] = min(d["ess"].values())
    return d


def registration_statistics(result: FitResult, alpha: float = 0.05) -> dict:
    """Per sensor, the registration seed's spatial correlation (``calib.fit.regstats``, Sec. IV-A):
    Pearson r between each row's position error at the posterior mode (mm) and its distance from
    the sensor's origin (mm). A significant positive r says the error grows across the sensor's
    volume — a registration or scale error, or a sensor that loses accuracy with range — which the
    offsets' intervals (independent errors) do not describe. Sensors with fewer than 3 rows or
    constant distances are left out."""
    from calib.fit.regstats import spatial_correlation

    post = result.posterior
    dim = post.dim
    errors = np.linalg.norm(post.position_residuals(result.mode[:dim]), axis=-1)
    out = {}
    for s in post.sensors:
        rows = post.data.sensor == s
        try:
            c = spatial_correlation(errors[rows], post.data.xyz_mm[rows], alpha=alpha)
        except ValueError:
            continue
        out[s] = {"r": c.r, "p_value": c.p_value, "n": c.n, "significant": c.significant, "decision": c.decision}
    return out


def graded(ident: Identifiability, result: FitResult) -> dict:
    """``ident.to_dict()`` with each direction graded against the fit's σ (``calib.plan.identifiability.verdicts``):
    verdict, why, std_mm (scaled mm: angles × the lever arm), condition (s_max / s)."""
    out = ident.to_dict()
    lever = float(result.diagnostics.get("lever_arm_mm") or 1000.0)
    limit = lever * math.radians(float(result.diagnostics.get("max_std_deg") or 1.0))
    out["sigma_mm"] = result.pooled_sigma_mm
    out["undetermined_limit_mm"] = limit
    for d, v in zip(out["directions"], verdicts(ident.singular_values, ident.shape, result.pooled_sigma_mm, limit)):
        d.update(verdict=v.verdict, why=v.why, std_mm=v.std_mm, condition=v.condition)
    return out


def identifiability(result: FitResult) -> dict:
    fixed = [
        {"parameter": name, "reason": reason}
        for name, reason in result.posterior.mask.reasons.items()
    ]
    reasons = result.posterior.mask.reasons
    too_wide = [
        {"parameter": f"{axis}.offset", "reason": split_status(status)[1]}
        for axis, status in zip(result.model.axis_names, result.offset_status)
        if status.startswith("undetermined") and f"{axis}.offset" not in reasons
    ]
    return {
        "start": graded(result.identifiability_start, result),
        "estimate": graded(result.identifiability, result),
        "fixed_parameters": fixed,
        "undetermined_at_estimate": too_wide,
    }


def result_dict(
    result: FitResult,
    data: Dataset,
    *,
    metrics: dict | None = None,
    controller: dict | None = None,
) -> dict:
    """The whole ``result.json`` document (JSON-safe)."""
    model = result.model
    doc = {
        "format": FORMAT,
        "robot": {"name": model.name, "controller": model.controller, "axes": model.axis_names},
        "data": {
            "source": data.source,
            "n_measurements": len(data),
            "n_configurations": int(np.unique(data.q_rad, axis=0).shape[0]),
            "sensors": data.sensors,
            "markers": sorted(set(data.marker.tolist())),
        },
        "joint_offsets": joint_offsets(result),
        "registration": registration(result),
        "tool": {"prior_mm": result.diagnostics.get("tool_prior_mm"), "markers": result.tool,
                 "degeneracies": result.diagnostics.get("tool_degeneracies", [])},
        "sigma_mm": {s: {"value": v[0], "std": v[1]} for s, v in result.sigma_mm.items()},
        "diagnostics": diagnostics(result),
        "identifiability": identifiability(result),
        "metrics": metrics or {},
    }
    if controller is not None:
        doc["controller"] = controller
    return jsonable(doc)


def write_result(path: str | Path, doc: dict) -> Path:
    """Write ``doc`` (from ``result_dict``) as indented UTF-8 JSON; returns the path."""
    path = Path(path)
    path.write_text(json.dumps(jsonable(doc), indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path
