"""The gravity sag of a calibrated arm as a data file beside an exported model.

URDF, UR's kinematics file and our model YAML describe rigid kinematics; a fit with joint
compliances (``--compliance``, the ``+compliance`` candidates) also found how far each joint
yields under the arm's weight. That goes into ``<export>.sag.yaml`` (format ``remaster.sag/1``)::

    format: remaster.sag/1
    formula: Δq_i = sign_i · k_i · τ_i(q) …       # in words, for a reader
    compliance_rad_per_nm: {J1: 0.0, J2: 5.3e-06, …}
    model: {…}                                    # the calibrated arm (our model layout: DH table,
                                                  # link masses and centres of mass, tool, gravity)

A consumer applies it by computing, at the controller angles q, the gravity torque τ_i on each
joint from the masses of the links beyond it (``calib.robot.gravity``: τ_i = z_{i−1} · Σ_{j≥i}
(c_j − o_{i−1}) × m_j g, N·m, frames of ``model`` at q) and commanding/predicting the arm at
q + Δq. ``read_sag_file`` gives back the ``Calibrated`` arm that does this.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.robot.calibrated import Calibrated
from calib.robot.kinematics import Chain
from calib.robot.model import robot_model_from_dict

FORMAT = "remaster.sag/1"
FORMULA = ("at controller angles q (rad) the arm stands at q + Δq with Δq_i = sign_i · k_i · τ_i(q): k_i the compliance "
           "below (rad/(N·m)), sign_i the model's axis sign, τ_i the gravity torque about joint i (N·m) of every mass beyond "
           "it — link masses and centres of mass (mass_kg, com_mm in each joint's DH frame) and the tool's (flange frame) — "
           "under gravity_m_s2, all from `model` at q")


class SagFileError(ValueError):
    """A file that is not a readable sag file; the message names the file and the field."""


def write_sag_file(arm: Calibrated, path: str | Path, header: str = "") -> Path:
    """Write ``arm``'s compliances and model as ``remaster.sag/1`` YAML."""
    import yaml  # noqa: PLC0415

    if arm.compliance is None:
        raise ValueError("the arm has no compliance model: nothing to write")
    doc = {"format": FORMAT, "formula": FORMULA,
           "compliance_rad_per_nm": {ax: float(k) for ax, k in zip(arm.model.axis_names, arm.compliance)},
           "model": arm.model.model_dump(mode="json", exclude_none=True)}
    lines = [f"# {line}".rstrip() for line in header.strip().splitlines()] if header.strip() else []
    path = Path(path)
    path.write_text("\n".join(lines + [yaml.safe_dump(doc, sort_keys=False, allow_unicode=True, width=100)]), encoding="utf-8")
    return path


def read_sag_file(path: str | Path) -> Calibrated:
    """The calibrated arm of a sag file (its model and compliances); ``SagFileError`` if unreadable."""
    import yaml  # noqa: PLC0415

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise SagFileError(f"{path}: cannot read as YAML: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise SagFileError(f"{path}: not a sag file (expected format: {FORMAT})")
    try:
        model = robot_model_from_dict(doc["model"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SagFileError(f"{path}: field 'model' is not a robot model: {exc}") from None
    k = doc.get("compliance_rad_per_nm")
    if not isinstance(k, dict) or set(k) != set(model.axis_names) or not all(isinstance(v, (int, float)) for v in k.values()):
        raise SagFileError(f"{path}: compliance_rad_per_nm must give a number for each axis {model.axis_names}")
    return Calibrated(model, Chain(model).nominal, ["compliance"], [], np.array([float(k[a]) for a in model.axis_names]))
