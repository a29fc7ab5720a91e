"""What a controller that takes zero-offsets gets (KUKA KSS ``$MAMES``, Sunrise, ABB, UR, generic):
offsets fitted *for that controller*, and a held-out comparison of the robot it will run.

The controller keeps its nominal arm; all the operator can change is each axis's zero. So:

1. **The offsets to enter** are fitted with the links at nominal: zero-offsets, the registration
   and the measured markers' positions on the flange (the tool) free, no link parameters, no
   compliance (``entered_options``; the ``offsets+tool`` candidate of ``calib.fit.model_choice``).
   An axis whose offset is undetermined, or not significant (|δ| < 1.96·std, the std the larger
   of the posterior's and the model-robust sandwich one), is left unchanged, and the offsets are
   fitted again with those axes held at zero — the values must belong to the robot that is scored.
2. **Three robots, held out** (``Heldout``), each an ``Arm`` (a chain vector and joint compliances):
   *as found* — the nominal arm, zero offsets; *offsets entered* — the nominal arm plus the entered
   offsets; *full model* — the arm the chosen model describes (what compensation would deliver).
   Every robot gets its own registration and tool fitted by least squares with its kinematics
   held fixed (``place``), never the drawing's tool.

   * With validation data: each robot is placed on the validation configurations (registration and
     tool only: nothing about the arm is refitted on the scored points) and scored there
     (``heldout_on_validation``).
   * Without: K-fold cross-validation by configuration, the folds of the model choice
     (``calib.fit.model_choice.fold_labels``): the offsets fitted on the other folds, each robot placed
     on the other folds and scored on the held-out one (``heldout_by_folds``).

   The score of one configuration is the rms distance |measured − predicted| over its rows, mm
   (positions only; attitude rows, where measured, are not scored here).
3. **"Enter" is earned** when the offsets-entered robot beats the robot as found by more than its
   uncertainty: the paired per-configuration differences (as found − entered) have a mean whose
   95 % interval (mean ± 1.96 standard errors) lies above zero. Otherwise "do not enter", with the
   reason; the guards of ``calib.robot.controller.do_not_enter_reasons`` (convergence, a σ far above
   the sensor's noise) also refuse.

``entered_document`` gives the ``"entered"`` key of ``result.json`` (shape in ``docs/what-to-enter.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

from calib.fit.model_choice import CV_TOL, config_errors, fold_labels
from calib.fit.offsets import FitOptions, FitResult, ModeFit, fit_mode, fit_offsets
from calib.fit.registration import register_least_squares
from calib.measure.dataset import Dataset
from calib.robot.canonical import wrap_deg
from calib.robot.gravity import gravity_torques
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.robot.transforms import exp_so3, skew, so3_left_jacobian

#: z of the two-sided 95 % interval, and the significance an offset needs to be entered.
Z95 = 1.96


# --- a robot as it runs ------------------------------------------------------------------------
@dataclass(frozen=True)
class Arm:
    """A robot as it runs: ``params`` (P,) the ``Chain`` vector (zero-offsets in rad, added to the
    reported angles; links; the tool's markers, a starting place only) and ``compliance`` (n,)
    rad/(N·m) joint compliances (None: rigid; the sag sign·k·τ(q) with the torques at ``params``)."""

    params: np.ndarray
    compliance: np.ndarray | None = None

    def flange(self, chain: Chain, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flange rotation (k, 3, 3) and position (k, 3) mm in the base frame at reported angles (k, n)."""
        if self.compliance is not None and np.any(self.compliance):
            q_rad = q_rad + chain.sign * self.compliance * gravity_torques(chain, q_rad, self.params)
        return chain.flange_pose(q_rad, self.params)


def nominal_arm(chain: Chain, offsets_rad: np.ndarray | None = None) -> Arm:
    """The controller's nominal arm with ``offsets_rad`` (n,) entered (None: as found)."""
    return Arm(chain.with_offsets(np.zeros(chain.n) if offsets_rad is None else offsets_rad))


def fitted_arm(post, theta: np.ndarray) -> Arm:
    """The arm an offsets posterior (``calib.fit.posterior.OffsetPosterior``) describes at free
    parameters ``theta`` (dim,), e.g. its mode: offsets, links where the model has them, fitted
    markers, compliances (µrad/(N·m) in the posterior) where fitted."""
    full = post.full_vector(theta)
    comp = full[post.n_full - post.C:] * 1e-6 if post.C else None
    return Arm(post.chain_params(full), comp)


def identified_arm(ident) -> Arm:
    """The arm of a full identification (``calib.fit.identification.IdentResult``)."""
    return Arm(np.asarray(ident.params, dtype=float), None if ident.compliance is None else np.asarray(ident.compliance))


@dataclass
class Placement:
    """Where a robot stands in the sensor's frame and what it carries: ``base2sensor`` (4, 4) per
    sensor and each measured marker's position on the flange, mm (flange frame)."""

    base2sensor: dict[str, np.ndarray]
    markers_mm: dict[str, np.ndarray]


def _rows(chain: Chain, data: Dataset) -> tuple[list[str], np.ndarray, list[str], np.ndarray]:
    sensors, markers = data.sensors, sorted(set(data.marker.tolist()))
    return (sensors, np.array([sensors.index(s) for s in data.sensor]), markers,
            np.array([markers.index(m) for m in data.marker]))


def place(chain: Chain, arm: Arm, data: Dataset, *, free_tool: bool = True) -> Placement:
    """Least-squares registration per sensor and (``free_tool``) marker positions on the flange for
    ``arm``, its kinematics held fixed: min Σ |T_s·(R_f·m + p_f) − y|² over the rows of ``data``.
    Starts from the arm's markers and the SVD registration; Levenberg–Marquardt on the rest, with the
    analytic Jacobian."""
    rot, pos = arm.flange(chain, data.q_rad)
    sensors, s_idx, markers, m_idx = _rows(chain, data)
    start = chain.marker_slice().start
    m0 = np.array([arm.params[start + 3 * chain.marker_names.index(m): start + 3 * chain.marker_names.index(m) + 3]
                   for m in markers])
    p_base = np.einsum("kij,kj->ki", rot, m0[m_idx]) + pos
    t0 = [register_least_squares(p_base[s_idx == i], data.xyz_mm[s_idx == i]).base2sensor for i in range(len(sensors))]
    n_s = len(sensors)

    def unpack(x: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        regs = []
        for i in range(n_s):
            t = np.eye(4)
            t[:3, :3] = exp_so3(x[6 * i: 6 * i + 3]) @ t0[i][:3, :3]
            t[:3, 3] = t0[i][:3, 3] + x[6 * i + 3: 6 * i + 6]
            regs.append(t)
        m = m0 + (x[6 * n_s:].reshape(-1, 3) if free_tool else 0.0)
        return regs, m

    def residuals(x: np.ndarray) -> np.ndarray:
        regs, m = unpack(x)
        t = np.stack(regs)[s_idx]
        pb = np.einsum("kij,kj->ki", rot, m[m_idx]) + pos
        return (np.einsum("kij,kj->ki", t[:, :3, :3], pb) + t[:, :3, 3] - data.xyz_mm).ravel()

    def jacobian(x: np.ndarray) -> np.ndarray:
        """∂ residuals / ∂ x (3k, len(x)): a sensor's turn w moves R_s·p by −[R_s·p]× J_l(w)
        (``so3_left_jacobian``), its shift by I, a marker by R_s·R_f."""
        regs, m = unpack(x)
        r_s = np.stack(regs)[s_idx, :3, :3]  # (k, 3, 3)
        turned = np.einsum("kij,kj->ki", r_s, np.einsum("kij,kj->ki", rot, m[m_idx]) + pos)
        j = np.zeros((len(data), 3, x.size))
        for i in range(n_s):
            rows = s_idx == i
            j[rows, :, 6 * i: 6 * i + 3] = -skew(turned[rows]) @ so3_left_jacobian(x[6 * i: 6 * i + 3])
            j[rows, :, 6 * i + 3: 6 * i + 6] = np.eye(3)
        if free_tool:
            moved = r_s @ rot  # (k, 3, 3)
            for c in range(len(markers)):
                j[m_idx == c, :, 6 * n_s + 3 * c: 6 * n_s + 3 * c + 3] = moved[m_idx == c]
        return j.reshape(-1, x.size)

    x0 = np.zeros(6 * n_s + (3 * len(markers) if free_tool else 0))
    sol = least_squares(residuals, x0, jac=jacobian, method="lm", xtol=1e-12, ftol=1e-12,
                        x_scale=np.r_[np.tile([1e-3] * 3 + [1.0] * 3, n_s), np.ones(x0.size - 6 * n_s)])
    regs, m = unpack(sol.x)
    return Placement(dict(zip(sensors, regs)), dict(zip(markers, m)))


def distances(chain: Chain, arm: Arm, placement: Placement, data: Dataset) -> np.ndarray:
    """|measured − predicted| per row (k,) mm of ``arm`` placed by ``placement``."""
    rot, pos = arm.flange(chain, data.q_rad)
    m = np.stack([placement.markers_mm[k] for k in data.marker])
    t = np.stack([placement.base2sensor[s] for s in data.sensor])
    pb = np.einsum("kij,kj->ki", rot, m) + pos
    return np.linalg.norm(np.einsum("kij,kj->ki", t[:, :3, :3], pb) + t[:, :3, 3] - data.xyz_mm, axis=1)


# --- the offsets to enter ----------------------------------------------------------------------
def entered_options(base: FitOptions) -> FitOptions:
    """The fit of the offsets for the nominal arm: the user's options (method, joints, registration,
    error model, tool prior, seed) with no link parameters and no compliance."""
    return replace(base, link_tolerance=None, compliance=False)


@dataclass
class EnteredFit:
    """The offsets fitted for the nominal arm. ``result``: that fit; ``offsets``: one entry per axis
    (``joint``, ``index``, ``value_deg``, ``std_deg``, ``significant``, ``reason``); ``std_factor``: the
    factor the stds were widened by (the held-out misfit of this model, where above 1)."""

    result: FitResult
    offsets: list[dict]
    std_factor: float = 1.0

    @property
    def offsets_rad(self) -> np.ndarray:
        """(n,) what the controller gets: the significant offsets, 0 elsewhere."""
        return np.array([math.radians(o["value_deg"]) if o["significant"] else 0.0 for o in self.offsets])

    @property
    def joints(self) -> tuple[int, ...]:
        return tuple(o["index"] for o in self.offsets if o["significant"])


def _axis_entries(result: FitResult, factor: float, dropped: dict[int, str]) -> list[dict]:
    # The model-robust (sandwich) std where it is the wider: the errors are not what the model assumes.
    ratios = dict(zip(result.posterior.free_names, result.diagnostics.get("sandwich_std_ratio", [])))
    out = []
    for i, (ax, status) in enumerate(zip(result.model.axis_names, result.offset_status)):
        entry = {"joint": ax, "index": i + 1, "value_deg": None, "std_deg": None, "significant": False, "reason": ""}
        if i in dropped:
            entry["reason"] = dropped[i]
        elif status != "fitted":
            entry["reason"] = status
        else:
            std = float(result.offsets_std_rad[i]) * max(1.0, ratios.get(f"{ax}.offset") or 1.0) * factor
            value = wrap_deg(math.degrees(float(result.offsets_rad[i])))
            entry.update(value_deg=value, std_deg=math.degrees(std))
            if abs(value) < Z95 * math.degrees(std):
                entry["reason"] = (f"not significant: |δ| = {abs(value):.4f}° < {Z95}·std ({Z95 * math.degrees(std):.4f}°) "
                                   "— no evidence the zero is off")
            else:
                entry["significant"] = True
        out.append(entry)
    return out


def fit_entered(model: RobotModel, cal: Dataset, base: FitOptions, *, std_factor: float = 1.0,
                start: ModeFit | None = None, reuse: FitResult | None = None) -> EnteredFit:
    """The offsets to enter (module text, step 1). ``std_factor``: widen the stds by this (≥ 1).
    ``start``: a mode on ``cal`` where the solves start (``fit_mode``; the model choice's fit of
    ``offsets+tool``, or of a neighbour of it: the mode is the same, reached in fewer steps);
    ``reuse``: the fit of ``entered_options(base)`` on ``cal`` already made (the model choice chose
    ``offsets+tool``: the default fit's own posterior), used instead of fitting it again."""
    options = entered_options(base)
    result = reuse if reuse is not None else fit_offsets(model, cal, options, start=start)
    offsets = _axis_entries(result, std_factor, {})
    joints = tuple(o["index"] for o in offsets if o["significant"])
    fitted = tuple(o["index"] for o in offsets if o["value_deg"] is not None)
    if joints and joints != fitted:  # fit again with the axes left unchanged held at zero
        dropped = {o["index"] - 1: o["reason"] for o in offsets if not o["significant"]}
        result = fit_offsets(model, cal, replace(options, joints=joints), start=start)
        again = _axis_entries(result, std_factor, dropped)
        for o, first in zip(again, offsets):
            if o["index"] - 1 in dropped:  # left unchanged: its value and std as first fitted, for the record
                o.update(value_deg=first["value_deg"], std_deg=first["std_deg"])
            elif not o["significant"] and o["value_deg"] is not None:  # lost significance with the others refitted
                o["reason"] += " (after the others were left unchanged)"
        offsets = again
    return EnteredFit(result, offsets, std_factor)


# --- held-out scores ---------------------------------------------------------------------------
ROBOTS = ("as_found", "entered", "full_model")


class HeldoutError(ValueError):
    """The robots could not be scored held out (too few configurations to fit on the other folds)."""


@dataclass
class Heldout:
    """Per held-out configuration (``configs``) the error of each robot (mm); ``scored_on``:
    "validation" or "cross-validation"; ``how``: one line on what was fitted where."""

    scored_on: str
    how: str
    configs: np.ndarray
    errors: dict[str, np.ndarray] = field(default_factory=dict)

    def improvement(self) -> tuple[float, float, float]:
        """Mean of (as found − entered) per configuration, mm, and its 95 % interval (± 1.96 se)."""
        d = self.errors["as_found"] - self.errors["entered"]
        if d.size < 2:
            return float(d.mean()) if d.size else math.nan, -math.inf, math.inf
        se = float(d.std(ddof=1) / math.sqrt(d.size))
        return float(d.mean()), float(d.mean() - Z95 * se), float(d.mean() + Z95 * se)

    def to_dict(self) -> dict:
        """The ``heldout`` document; statistics None where nothing was scored."""
        out: dict = {"scored_on": self.scored_on, "how": self.how}
        for name in ROBOTS:
            e = self.errors.get(name, np.zeros(0))
            if not e.size:
                out[name] = {"rms_mm": None, "mean_mm": None, "max_mm": None, "n": 0}
                continue
            out[name] = {"rms_mm": float(np.sqrt(np.mean(e**2))), "mean_mm": float(e.mean()), "max_mm": float(e.max()),
                         "n": int(e.size)}
        value, lo, hi = self.improvement() if self.errors else (math.nan, math.nan, math.nan)
        out["improvement_mm"] = {"value": _stat(value), "ci95": [_stat(lo), _stat(hi)], "metric": "mean_mm",
                                 "test": "paired per-configuration differences (as found − offsets entered): mean ± "
                                         f"{Z95} standard errors"}
        return out


def _stat(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def heldout_on_validation(chain: Chain, arms: dict[str, Arm], val: Dataset, *, free_tool: bool = True) -> Heldout:
    """Each robot of ``arms`` (keys ``ROBOTS``) placed on ``val`` (registration and tool only) and scored there."""
    errors = {}
    for name, arm in arms.items():
        errors[name] = config_errors(val, distances(chain, arm, place(chain, arm, val, free_tool=free_tool), val))
    how = ("on the validation data: each robot's registration and tool fitted on it with the robot's kinematics "
           "fixed (nothing about the arm refitted on the scored points)")
    return Heldout("validation", how, np.unique(val.config), errors)


def heldout_by_folds(model: RobotModel, data: Dataset, options: FitOptions, entered_joints: tuple[int, ...], *,
                     k: int = 5, full_model: Callable[[Dataset], Arm] | dict[str, float] | None = None,
                     free_tool: bool = True, start: ModeFit | None = None,
                     fold_offsets: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> Heldout:
    """K-fold scores (the folds of ``fold_labels(data, k, options.seed)``): per fold the offsets of
    ``entered_joints`` fitted on the other folds by the posterior mode of ``options`` (``entered_options``
    of the user's, or an offsets-only fit's own; none: the entered robot is the robot as found), every
    robot placed on the other folds and scored on the held-out one.
    ``full_model``: per fold the arm of the full model (a function of the training data), or the
    held-out errors the model choice already scored for it (configuration → mm, the same folds); None:
    the full model is the entered robot (an offsets-only fit).
    ``start``: a mode on ``data`` where the folds' solves start (``fit_mode``); ``fold_offsets``: fold →
    (offsets (n,) rad, fitted axes (n,) bool) of this model already fitted on that fold's other
    folds (``calib.fit.model_choice.ModelChoice.entered_folds``, the same folds): used instead of
    fitting the fold again where its fitted axes are ``entered_joints``."""
    chain = Chain(model)
    labels, grouping = fold_labels(data, k, options.seed)
    options = replace(options, joints=entered_joints)
    wanted = np.isin(np.arange(1, chain.n + 1), entered_joints)
    names, errors = [], {r: [] for r in ROBOTS}
    for f in range(int(labels.max()) + 1):
        train, test = data.subset(labels != f), data.subset(labels == f)
        ok = np.isin(test.marker, np.unique(train.marker)) & np.isin(test.sensor, np.unique(train.sensor))
        if not ok.any():
            continue
        test = test.subset(ok)
        arms = {"as_found": nominal_arm(chain)}
        known = (fold_offsets or {}).get(f)
        if entered_joints and known is not None and np.array_equal(known[1], wanted):
            arms["entered"] = nominal_arm(chain, known[0])
        elif entered_joints:
            try:
                mf = fit_mode(model, train, options, tol=CV_TOL, start=start)
            except (ValueError, np.linalg.LinAlgError) as exc:
                raise HeldoutError(f"fold {f + 1}: the offsets could not be fitted on the other folds: {exc}") from exc
            arms["entered"] = nominal_arm(chain, mf.post.full_vector(mf.theta)[: chain.n])
        else:
            arms["entered"] = arms["as_found"]
        if callable(full_model):
            arms["full_model"] = full_model(train)
        for name, arm in arms.items():
            dist = distances(chain, arm, place(chain, arm, train, free_tool=free_tool), test)
            errors[name].append(config_errors(test, dist))
        names.append(np.unique(test.config))
    configs = np.concatenate(names)
    out = {name: np.concatenate(v) for name, v in errors.items() if v}
    if isinstance(full_model, dict):
        missing = [c for c in configs if c not in full_model]
        if missing:
            raise ValueError(f"the model choice scored no held-out error for configuration(s) {missing[:3]}")
        out["full_model"] = np.array([full_model[c] for c in configs])
    elif full_model is None:
        out["full_model"] = out["entered"]
    how = (f"{int(labels.max()) + 1}-fold cross-validation by {grouping}: the offsets (and the full model) fitted on the "
           "other folds; each robot's registration and tool fitted on the other folds and the held-out fold scored")
    return Heldout("cross-validation", how, configs, out)


# --- the verdict and the document ------------------------------------------------------------------
def verdict_reasons(entered: EnteredFit, heldout: Heldout, guards: list[str]) -> list[str]:
    """Why not to enter ([] when "enter" is earned): the guards, no significant axis, or no
    held-out improvement beyond its uncertainty."""
    reasons = list(guards)
    if not entered.joints:
        reasons.append("no axis's offset is determined and significantly different from zero: nothing to enter")
        return reasons
    if not heldout.errors:
        reasons.append(f"the robots could not be scored held out ({heldout.how})")
        return reasons
    value, lo, hi = heldout.improvement()
    if not lo > 0.0:
        a, e = heldout.errors["as_found"].mean(), heldout.errors["entered"].mean()
        reasons.append(f"the offsets entered on the nominal arm do not beat the robot as found held out ({heldout.scored_on}): "
                       f"{a:.3f} → {e:.3f} mm mean, improvement {value:+.3f} mm, 95 % [{lo:+.3f}, {hi:+.3f}] includes or "
                       "lies below zero")
    return reasons


def entered_document(model: RobotModel, entered: EnteredFit, heldout: Heldout, guards: list[str], *,
                     fitted_model: str) -> dict:
    """The ``"entered"`` key of ``result.json`` (``docs/what-to-enter.md``). ``fitted_model``: the
    name of the model whose figures are the full model's (the chosen one)."""
    reasons = verdict_reasons(entered, heldout, guards)
    verdict = "do not enter" if reasons else "enter"
    offsets = []
    for o in entered.offsets:
        go = verdict == "enter" and o["significant"]
        why = "" if go else (o["reason"] or "do not enter: " + "; ".join(reasons))
        offsets.append({"joint": o["joint"], "index": o["index"], "value_deg": o["value_deg"], "std_deg": o["std_deg"],
                        "enter": go, "reason": why})
    return {"controller": model.controller, "verdict": verdict, "reasons": reasons, "offsets": offsets,
            "heldout": heldout.to_dict(), "fitted_for": "the controller's nominal arm (links at nominal; registration and "
            "tool fitted; no compliance)", "full_model": fitted_model, "std_factor": entered.std_factor}


def controller_entries(doc: dict) -> list[dict]:
    """The ``"entered"`` offsets as ``joint_offsets``-style entries for
    ``calib.robot.controller.controller_values``: only the axes to enter are "fitted"."""
    out = []
    for o in doc["offsets"]:
        out.append({"joint": o["joint"], "index": o["index"], "identifiable": o["enter"], "value_deg": o["value_deg"],
                    "std_deg": o["std_deg"], "status": "fitted" if o["enter"] else o["reason"]})
    return out


def format_heldout(doc: dict) -> str:
    """The three held-out robots side by side, the verdict and its reason, for the terminal."""
    h = doc["heldout"]
    lines = [f"what the controller gets: offsets fitted for its nominal arm, scored held out ({h['scored_on']})",
             f"  {h['how']}",
             f"  {'robot':<44}{'rms (mm)':>10}{'mean (mm)':>11}{'max (mm)':>10}{'n':>7}"]
    label = {"as_found": "as found (zero offsets; registration, tool fitted)",
             "entered": "offsets entered on the nominal arm",
             "full_model": f"full model ({doc.get('full_model', 'chosen')}; via compensation)"}
    for name in ROBOTS:
        s = h[name]
        if not s["n"]:
            lines.append(f"  {label[name]:<44}{'—':>10}{'—':>11}{'—':>10}{0:>7}")
            continue
        lines.append(f"  {label[name]:<44}{s['rms_mm']:>10.4f}{s['mean_mm']:>11.4f}{s['max_mm']:>10.4f}{s['n']:>7}")
    imp = h["improvement_mm"]
    if imp["value"] is not None:
        lines.append(f"  improvement as found → entered: {imp['value']:+.4f} mm mean, 95 % [{imp['ci95'][0]:+.4f}, "
                     f"{imp['ci95'][1]:+.4f}] ({imp['test']})")
    lines.append(f"  verdict: {doc['verdict'].upper()}" + ("" if not doc["reasons"] else " — " + "; ".join(doc["reasons"])))
    return "\n".join(lines)


def guards(entered: EnteredFit, cal: Dataset) -> list[str]:
    """The verdict machinery of ``calib.robot.controller`` that applies to the offsets fitted for the
    controller: convergence, a σ far above the sensor's noise, a tool far outside its prior. (A
    sandwich std above the posterior's is not a refusal here: it already widened the stds the
    significance test uses.)"""
    from calib.fit.result import result_dict
    from calib.robot.controller import do_not_enter_reasons, tool_reasons

    doc = result_dict(entered.result, cal)
    return do_not_enter_reasons(doc, sandwich=False) + tool_reasons(doc)


def for_controller(model: RobotModel, cal: Dataset, val: Dataset | None, base: FitOptions, *,
                   full_arm: Arm | None, full_folds: Callable[[Dataset], Arm] | dict[str, float] | None,
                   fitted_model: str, std_factor: float = 1.0, k: int = 5,
                   own: FitResult | None = None, more_guards: list[str] = (), start: ModeFit | None = None,
                   reuse: FitResult | None = None,
                   fold_offsets: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> tuple[dict, EnteredFit]:
    """The offsets to enter and their held-out verdict: (the ``"entered"`` document, the fit).
    ``full_arm``: the full model fitted on ``cal`` (None: an offsets-only fit, the entered robot);
    ``full_folds``: its cross-validated scores or per-fold fit (``heldout_by_folds``), used without
    ``val``; ``own``: an offsets-only fit (``--method fast`` / ``paper``, fitted with ``base``) whose
    offsets are the controller's as they are — the folds then refit that fit's model; ``more_guards``:
    further reasons not to enter (that fit's own guards). What the default fit already has, so that
    nothing is fitted twice: ``start``, ``reuse`` (``fit_entered``) and ``fold_offsets``
    (``heldout_by_folds``)."""
    chain = Chain(model)
    free_tool = base.tool_prior_mm > 0
    if own is not None:
        entered, fold_options = EnteredFit(own, _axis_entries(own, std_factor, {}), std_factor), base
    else:
        entered = fit_entered(model, cal, base, std_factor=std_factor, start=start, reuse=reuse)
        fold_options = entered_options(base)
    if val is not None and len(val):
        arms = {"as_found": nominal_arm(chain), "entered": nominal_arm(chain, entered.offsets_rad)}
        arms["full_model"] = full_arm if full_arm is not None else arms["entered"]
        heldout = heldout_on_validation(chain, arms, val, free_tool=free_tool)
    else:
        try:
            heldout = heldout_by_folds(model, cal, fold_options, entered.joints, k=k, full_model=full_folds,
                                       free_tool=free_tool, start=start if own is None else None,
                                       fold_offsets=fold_offsets if own is None else None)
        except HeldoutError as exc:
            heldout = Heldout("cross-validation", f"not scored: {exc}", np.zeros(0, dtype=str), {})
    refusals = guards(entered, cal)
    refusals += [r for r in more_guards if r not in refusals]
    return entered_document(model, entered, heldout, refusals, fitted_model=fitted_model), entered


def refused_document(model: RobotModel, reason: str, scored_on: str) -> dict:
    """The ``"entered"`` document when the offsets for the controller could not be fitted at all:
    "do not enter", every axis left unchanged, nothing scored."""
    heldout = Heldout(scored_on, "not scored", np.zeros(0, dtype=str), {}).to_dict()
    why = f"the offsets for the controller's nominal arm could not be fitted: {reason}"
    offsets = [{"joint": ax, "index": i + 1, "value_deg": None, "std_deg": None, "enter": False, "reason": why}
               for i, ax in enumerate(model.axis_names)]
    return {"controller": model.controller, "verdict": "do not enter", "reasons": [why], "offsets": offsets,
            "heldout": heldout, "fitted_for": "the controller's nominal arm (links at nominal; registration and tool "
            "fitted; no compliance)", "full_model": None, "std_factor": 1.0}


def as_found_markers(model: RobotModel, cal: Dataset) -> dict[str, np.ndarray]:
    """The markers' positions on the flange (mm) of the robot as found (nominal arm, zero offsets),
    fitted with its registration on ``cal``: the tool of the "before" of every comparison, never the drawing's."""
    chain = Chain(model)
    return place(chain, nominal_arm(chain), cal).markers_mm


def attach(model: RobotModel, doc: dict, entered: dict) -> tuple[list[str], str]:
    """Write ``entered`` (``for_controller``) into the result document ``doc`` as ``"entered"``, and the
    values to type (``"controller"``) from it, not from the model's offsets; returns (why not to enter,
    [] when earned; the text for the terminal: the three robots held out and the values)."""
    from calib.robot.controller import controller_values

    doc["entered"] = entered
    values = controller_values(model, controller_entries(entered))
    doc["controller"] = values.to_dict()
    refused = list(entered["reasons"]) if entered["verdict"] != "enter" else []
    return refused, format_heldout(entered) + "\n\n" + values.format()
