"""Calibrated arms for the export and compensation tests: a robot whose truth has link errors,
zero-offsets and gravity sag, written as the result files ``acquire fit`` writes.

``with_masses`` gives a model link masses (the KR 6 has none in its file) so that it sags;
``full_result`` writes a ``method: full`` result (every d, a, α, offset changed; Hayati β on an
mdh model; one compliance per axis); ``offsets_result`` a ``remaster.fit/1`` one (offsets, the
link terms under ``diagnostics.link_prior``, compliances under ``diagnostics.compliance``).
"""

from __future__ import annotations

import math

import numpy as np

from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel, robot_model_from_dict

#: Masses (kg) and centres of mass (mm, each joint's DH frame) of a 6-axis arm of the KR 6's size.
MASSES_KG = [20.0, 15.0, 10.0, 5.0, 3.0, 0.5]
COMS_MM = [[0, 0, 100], [-200, 0, 0], [0, 0, 50], [0, 0, -100], [0, 0, 0], [0, 0, 10]]
COMPLIANCE = 2e-5  # rad/(N·m): a 0.1–1 mm sag at full reach


def with_masses(model: RobotModel, tool_mass_kg: float = 2.0) -> RobotModel:
    d = model.model_dump(mode="json")
    for j, m, c in zip(d["joints"], MASSES_KG, COMS_MM):
        j["mass_kg"], j["com_mm"] = m, c
    d["tool"]["mass_kg"], d["tool"]["com_mm"] = tool_mass_kg, [0, 0, 80]
    return robot_model_from_dict(d)


def _changes(model: RobotModel, seed: int) -> dict[str, float]:
    """Parameter name → change (mm, degrees): offsets ~0.1°, d and a ~0.5 mm, α ~0.05°, β on mdh."""
    rng = np.random.default_rng(seed)
    out = {}
    for name in Chain(model).param_names:
        kind = name.rsplit(".", 1)[1]
        scale = {"offset": 0.1, "d": 0.5, "a": 0.5, "alpha": 0.05, "beta": 0.05 if model.convention == "mdh" else 0.0}.get(kind, 0.0)
        if scale:
            out[name] = float(rng.normal(0.0, scale))
    return out


def _compliance_entries(model: RobotModel) -> list[dict]:
    return [{"joint": ax, "unit": "rad/(N·m)", "status": "fitted", "value": COMPLIANCE, "std": 1e-7, "reason": ""}
            for ax in model.axis_names]


def full_result(model: RobotModel, seed: int = 3, compliance: bool = True) -> dict:
    """A ``method: full`` result.json document (see the module text)."""
    chain = Chain(model)
    change = _changes(model, seed)
    params = []
    for i, name in enumerate(chain.param_names):
        kind = name.rsplit(".", 1)[1]
        deg = kind in ("offset", "alpha", "beta")
        nominal = math.degrees(chain.nominal[i]) if deg else float(chain.nominal[i])
        params.append({"name": name, "unit": "deg" if deg else "mm", "nominal": nominal,
                       "value": nominal + change.get(name, 0.0), "identified": name in change})
    doc = {"method": "full", "robot": model.name, "parameters": params}
    if compliance:
        doc["compliance"] = _compliance_entries(model)
    return doc


def offsets_result(model: RobotModel, seed: int = 3, compliance: bool = True) -> dict:
    """A ``remaster.fit/1`` result.json document of an offsets+tool+links(+compliance) fit."""
    change = _changes(model, seed)
    offsets = [{"joint": ax, "index": i + 1, "value_deg": change[f"{ax}.offset"], "status": "fitted", "reason": "",
                "identifiable": True} for i, ax in enumerate(model.axis_names)]
    links = {k: {"mean": v, "std": 0.01} for k, v in change.items() if not k.endswith(".offset")}
    diagnostics = {"link_prior": {"length_mm": 0.5, "angle_deg": 0.05, "parameters": links}}
    if compliance:
        diagnostics["compliance"] = _compliance_entries(model)
    return {"format": "remaster.fit/1", "robot": {"name": model.name, "controller": model.controller, "axes": model.axis_names},
            "joint_offsets": offsets, "tool": {"markers": []}, "diagnostics": diagnostics}
