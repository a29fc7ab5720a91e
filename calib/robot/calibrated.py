"""The calibrated model: a nominal robot model with a fit's ``result.json`` applied.

Understood results (all written by ``acquire fit``):

* ``format: remaster.fit/1`` (the zero-offset fit: the default ``auto`` fit's offsets models,
  ``--method fast`` and ``paper``): ``joint_offsets[i].value_deg`` of every offset whose status is
  ``fitted``, the fitted marker positions of ``tool.markers``, the link parameters the fit
  estimated alongside (``diagnostics.link_prior.parameters``: posterior mean deviations from
  nominal, mm and degrees — the ``+links`` candidates, and fast's marginalised link prior) and the
  joint compliances (``diagnostics.compliance``, the ``+compliance`` candidates);
* ``method: full`` (full identification, also the ``auto`` fit's ``full`` candidate): every
  ``parameters`` entry with ``identified: true`` (offsets, d, a, α, β, marker positions), absolute
  values, and ``compliance``;
* ``kind: socket``: its ``parameters`` (free kinematic parameters) — offsets only where
  ``joint_offsets`` says ``fitted``; the fitted ball is not a marker of the model's tool — and
  ``compliance``.

Compliance (gravity sag, ``calib.robot.gravity``) is not a parameter of the kinematic chain: it is
carried beside the model as ``Calibrated.compliance`` (n,) rad/(N·m). The calibrated arm then
reaches, for controller angles q, the chain's pose at q + Δq(q) with
``Δq_i = sign_i · k_i · τ_i(q)`` and τ the gravity torques of the calibrated arm at q — the sag
model of the fitters and of the simulated cell (``Calibrated.joint_sag``, ``Calibrated.fk``).

A zero-offset δ folds into the DH angle offset, ``theta' = theta + sign·δ``: the result describes
the robot as it is *before* the offsets are entered in the controller (after entering them, the
nominal model holds again). Offsets that are undetermined or "do not enter" stay nominal and are
listed in the notes. The model must be the one the result was fitted to: its name, axes and
(where the result records them) nominal values are checked.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel

_ANGLE_KINDS = ("offset", "alpha", "beta")


class ResultError(ValueError):
    """A result file that cannot be applied to this model; the message says why and what to do."""


@dataclass
class Calibrated:
    """``model`` with the result applied; ``params`` its full ``Chain`` vector (P,) relative to the
    *nominal* model (offsets in rad); ``applied`` / ``kept`` parameter names, with reasons for the
    kept ones in ``notes``."""

    model: RobotModel
    params: np.ndarray
    applied: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: (n,) joint compliances, rad/(N·m) (0 where not fitted); None: the result has no sag model.
    compliance: np.ndarray | None = None

    @cached_property
    def chain(self) -> Chain:
        """The calibrated model's chain (its nominal vector is the calibrated arm)."""
        return Chain(self.model)

    @property
    def has_sag(self) -> bool:
        return self.compliance is not None and bool(np.any(self.compliance))

    def joint_sag(self, q: np.ndarray) -> np.ndarray:
        """Δq (..., n) rad the arm yields under its weight at controller angles q (..., n) rad:
        ``sign_i · k_i · τ_i(q)``, zeros without a sag model."""
        q = np.asarray(q, dtype=float)
        if not self.has_sag:
            return np.zeros_like(q)
        from calib.robot.gravity import gravity_torques  # noqa: PLC0415

        return self.chain.sign * self.compliance * gravity_torques(self.chain, q)

    def fk(self, q: np.ndarray) -> np.ndarray:
        """Flange frames (..., 4, 4) mm the calibrated arm reaches at controller angles q (..., n)
        rad, its sag included."""
        q = np.asarray(q, dtype=float)
        return self.chain.fk(q + self.joint_sag(q))

    def after_entering(self, entered_rad: np.ndarray) -> Calibrated:
        """The same arm in the controller's angles after the zero-offsets ``entered_rad`` (n,) rad
        were entered: the controller then shows q + δ_entered where it showed q, so the arm's
        offsets become δ − δ_entered (the sag, a function of the arm's real pose, is unchanged)."""
        entered = np.asarray(entered_rad, dtype=float)
        if not np.any(entered):
            return self
        d = self.model.model_dump()
        for j, joint, e in zip(d["joints"], self.model.joints, entered):
            j["theta"] = float(joint.theta - joint.sign * math.degrees(e))
        d["source"] = f"{self.model.source}; with the entered offsets {np.round(np.degrees(entered), 6).tolist()} deg"
        params = self.params.copy()
        params[: self.model.n_joints] -= entered
        return Calibrated(RobotModel.model_validate(d), params, list(self.applied),
                          self.notes + ["in the controller's angles after entering the offsets"], self.compliance)


def read_result(path: str | Path) -> dict:
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ResultError(f"{path}: no such result file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultError(f"{path}: not a JSON result file ({exc}); give the result.json that `acquire fit -o` wrote") from exc
    if not isinstance(doc, dict):
        raise ResultError(f"{path}: not a result file (top level is {type(doc).__name__}, expected an object)")
    return doc


def _check_robot(doc: dict, model: RobotModel, where: str) -> None:
    robot = doc.get("robot")
    name = robot.get("name") if isinstance(robot, dict) else robot
    if name != model.name:
        raise ResultError(f"{where}: fitted to robot {name!r}, the model is {model.name!r}: give the nominal model "
                          "the fit used (not a corrected model, which already has the result in it)")
    axes = robot.get("axes") if isinstance(robot, dict) else None
    if axes is not None and list(axes) != model.axis_names:
        raise ResultError(f"{where}: axes {axes} differ from the model's {model.axis_names}")


def _to_internal(kind: str, value: float) -> float:
    return math.radians(value) if kind in _ANGLE_KINDS else float(value)


def apply_result(model: RobotModel, doc: dict, where: str = "result") -> Calibrated:
    """The calibrated model (see the module text). Raises ``ResultError`` when the result does not
    belong to ``model`` or has nothing that may be applied."""
    chain = Chain(model)
    names = chain.param_names
    params = chain.nominal.copy()
    applied: list[str] = []
    notes: list[str] = []
    _check_robot(doc, model, where)
    offsets_ok: set[str] | None = None
    if "joint_offsets" in doc:
        offsets_ok = set()
        for entry in doc["joint_offsets"]:
            axis, status = entry.get("joint"), entry.get("status", "")
            if axis not in model.axis_names:
                raise ResultError(f"{where}: joint_offsets names axis {axis!r}; the model's axes are {model.axis_names}")
            if status == "fitted" and entry.get("value_deg") is not None:
                offsets_ok.add(f"{axis}.offset")
            else:
                why = "; ".join(x for x in (status or "not fitted", entry.get("reason") or "") if x)
                notes.append(f"{axis}.offset kept nominal ({why.replace('; ', ': ', 1)})")
    if doc.get("format") == "remaster.fit/1":
        for entry in doc["joint_offsets"]:
            name = f"{entry['joint']}.offset"
            if name in offsets_ok:
                params[names.index(name)] = math.radians(float(entry["value_deg"]))
                applied.append(name)
        for entry in (doc.get("tool") or {}).get("markers") or []:
            marker = entry.get("marker")
            if marker not in chain.marker_names:
                raise ResultError(f"{where}: tool marker {marker!r} is not on this model's tool {chain.marker_names}")
            i = names.index(f"{marker}.x")
            if np.max(np.abs(np.subtract(entry["nominal_mm"], chain.nominal[i:i + 3]))) > 1e-6:
                raise ResultError(f"{where}: marker {marker} was at {entry['nominal_mm']} mm in the model the fit used, this "
                                  f"model has {chain.nominal[i:i + 3].tolist()}: give the nominal model the fit used")
            params[i:i + 3] = entry["value_mm"]
            applied += [f"{marker}.{c}" for c in "xyz"]
        link = (doc.get("diagnostics") or {}).get("link_prior") or {}
        for name, entry in (link.get("parameters") or {}).items():
            if name not in names or _is_marker(chain, names.index(name)):
                raise ResultError(f"{where}: link parameter {name!r} is not one of this model's ({model.name})")
            kind = name.rsplit(".", 1)[1]
            params[names.index(name)] = chain.nominal[names.index(name)] + _to_internal(kind, entry["mean"])
            applied.append(name)
        compliance_entries = (doc.get("diagnostics") or {}).get("compliance")
    elif doc.get("method") == "full" or doc.get("kind") == "socket":
        socket = doc.get("kind") == "socket"
        for entry in doc.get("parameters", []):
            name = entry.get("name")
            if name not in names:
                raise ResultError(f"{where}: parameter {name!r} is not one of this model's ({model.name})")
            kind = name.rsplit(".", 1)[1]
            i = names.index(name)
            nominal = entry.get("nominal")
            if nominal is not None and i < chain.marker_slice().start:
                if abs(_to_internal(kind, nominal) - chain.nominal[i]) > 1e-6:
                    raise ResultError(f"{where}: {name} was {nominal} {entry.get('unit', '')} in the model the fit used, "
                                      f"this model has {math.degrees(chain.nominal[i]) if kind in _ANGLE_KINDS else chain.nominal[i]:.6g}: "
                                      "give the nominal model the fit used")
            if not socket and not entry.get("identified"):
                continue
            if kind == "offset" and offsets_ok is not None and name not in offsets_ok:
                continue
            if socket and i >= chain.marker_slice().start:
                continue
            params[i] = _to_internal(kind, entry["value"])
            applied.append(name)
        if socket:
            notes.append("the socket fit's ball is not one of this tool's markers: markers kept")
        compliance_entries = doc.get("compliance")
    else:
        raise ResultError(f"{where}: not a result this version understands (expected format 'remaster.fit/1', "
                          "method 'full' or kind 'socket', as `acquire fit -o` writes)")
    compliance = _compliance(model, compliance_entries, where, notes)
    if compliance is not None and np.any(compliance):
        applied += [f"{e['joint']}.compliance" for e in compliance_entries if e.get("status") == "fitted"]
    if not applied:
        raise ResultError(f"{where}: nothing in it may be applied (" + "; ".join(notes or ["no fitted parameters"]) + ")")
    return Calibrated(corrected(model, params, doc_source=where), params, applied, notes, compliance)


def entered_offsets(doc: dict, model: RobotModel, where: str = "result") -> np.ndarray | None:
    """The zero-offsets (n,) rad a result records as entered in the controller (its ``entered``
    section, read by ``calib.robot.entered.entered_values``), or None when it records no entry."""
    from calib.robot.entered import entered_values

    if doc.get("entered") is None:
        return None
    if not isinstance(doc["entered"], dict) or not isinstance(doc["entered"].get("offsets"), list):
        raise ResultError(f"{where}: 'entered' must be an object with a list 'offsets' "
                          "([{joint, value_deg, enter}, …]), as `acquire fit` writes it")
    out = np.zeros(model.n_joints)
    for axis in entered_values(doc).axes:
        if axis.axis not in model.axis_names:
            raise ResultError(f"{where}: entered offsets name axis {axis.axis!r}; the model's axes are {model.axis_names}")
        out[model.axis_names.index(axis.axis)] = math.radians(axis.delta_deg)
    return out


def _is_marker(chain: Chain, index: int) -> bool:
    """Whether chain parameter ``index`` is a marker coordinate."""
    return index >= chain.marker_slice().start


def _compliance(model: RobotModel, entries, where: str, notes: list[str]) -> np.ndarray | None:
    """(n,) rad/(N·m) from a result's compliance entries (fitted ones; 0 with a note elsewhere),
    None when the result has no compliance model."""
    if not entries:
        return None
    if not model.has_dynamics:
        raise ResultError(f"{where}: the result has joint compliances but the model {model.name!r} has no link masses: "
                          "give the nominal model the fit used")
    out = np.zeros(model.n_joints)
    for entry in entries:
        axis = entry.get("joint")
        if axis not in model.axis_names:
            raise ResultError(f"{where}: compliance names axis {axis!r}; the model's axes are {model.axis_names}")
        if entry.get("status") == "fitted" and entry.get("value") is not None:
            out[model.axis_names.index(axis)] = float(entry["value"])
        else:
            notes.append(f"{axis}.compliance kept 0 ({entry.get('status') or 'not fitted'}"
                         + (f": {entry['reason']}" if entry.get("reason") else "") + ")")
    return out


def corrected(model: RobotModel, params: np.ndarray, doc_source: str = "") -> RobotModel:
    """``model`` with the ``Chain`` parameter vector ``params`` (P,) written in: offsets fold into
    theta (``theta + sign·δ``), d, a, α, β and marker positions replace the nominal ones."""
    chain = Chain(model)
    n = model.n_joints
    d = model.model_dump()
    for i, j in enumerate(d["joints"]):
        j["theta"] = float(j["theta"] + model.joints[i].sign * math.degrees(params[i]))
        j["d"] = float(params[n + i])
        j["a"] = float(params[2 * n + i])
        j["alpha"] = float(math.degrees(params[3 * n + i]))
        j["beta"] = float(math.degrees(params[4 * n + i]))
    mk = params[chain.marker_slice()].reshape(-1, 3)
    for i, m in enumerate(d["tool"]["markers"]):
        m["xyz"] = tuple(float(v) for v in mk[i])
    d["name"] = f"{model.name} (calibrated)"
    d["source"] = f"{model.source}; calibrated by remaster with {doc_source}".strip("; ")
    if model.convention == "dh" and np.any(np.abs(params[4 * n : 5 * n]) > 0):
        d["convention"] = "mdh"
    return RobotModel.model_validate(d)
