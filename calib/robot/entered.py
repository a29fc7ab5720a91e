"""What a fit result tells the operator to enter, read back from ``result.json``.

``entered_values(doc)`` gives the per-axis values the operator enters on the controller and the
held-out prediction of what that does, as ``EnteredValues``:

- a result with an ``"entered"`` section (the offsets fitted *for the controller*: links at
  nominal, scored held out on the nominal arm) gives its axes and its ``heldout`` prediction,
  ``{"scored_on", "as_found": {"rms_mm", "mean_mm", "max_mm", "n"}, "entered": {…},
  "full_model": {…}, "improvement_mm": {"value", "ci95": [lo, hi]}}``;
- an older result gives the ``joint_offsets`` whose status is ``fitted`` (what the operator was
  told to enter) and no prediction (``heldout`` None).

Each axis carries δ (deg, ``true angle = reported angle + δ``) and the correction −δ that the
controller's zero takes (``calib.robot.controller``). Axes left unchanged are not listed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from calib.robot.canonical import wrap_deg


@dataclass(frozen=True)
class EnteredAxis:
    """One axis to change: name, 1-based index, δ and the correction −δ (deg)."""

    axis: str
    index: int
    delta_deg: float
    correction_deg: float


@dataclass(frozen=True)
class EnteredValues:
    """What a result enters. source: ``"entered"`` or ``"joint_offsets"`` (an older result);
    heldout: the prediction (see the module docstring) or None; refused: the result's reasons
    not to enter (``do_not_enter``), [] when none."""

    axes: list[EnteredAxis]
    source: str
    heldout: dict | None
    refused: list[str]

    def delta_deg(self, axis_names) -> list[float]:
        """δ per axis of ``axis_names`` (0 where nothing is entered), deg."""
        by = {a.axis: a.delta_deg for a in self.axes}
        return [by.get(name, 0.0) for name in axis_names]


def _axis(entry: dict) -> EnteredAxis | None:
    """An axis from an ``entered.offsets`` entry (value_deg, ``enter``), a ``joint_offsets`` one
    (value_deg, status) or a controller-values one (delta_deg, action); None when it is not entered."""
    value = entry.get("delta_deg", entry.get("value_deg"))
    enter = entry.get("enter", True) and entry.get("action", "enter") == "enter" \
        and entry.get("status", "fitted") == "fitted" and entry.get("identifiable", True)
    if value is None or not enter:
        return None
    d = wrap_deg(float(value))
    return EnteredAxis(str(entry.get("joint", entry.get("axis"))), int(entry["index"]), d, -d)


def entered_values(doc: dict) -> EnteredValues:
    """The values ``doc`` (a ``result.json`` document) tells the operator to enter; see the module."""
    if not isinstance(doc, dict) or not ("entered" in doc or "joint_offsets" in doc):
        raise ValueError("not a fit result: it has neither 'entered' nor 'joint_offsets' "
                         "(give the result.json that `acquire run` or `acquire fit` wrote)")
    refused = list(doc.get("do_not_enter") or [])
    entered = doc.get("entered")
    if isinstance(entered, dict):
        rows = entered.get("offsets") or []  # calib.fit.entered writes [{joint, index, value_deg, std_deg, enter, reason}]
        if entered.get("verdict", "enter") != "enter":
            refused += [r for r in entered.get("reasons") or [] if r not in refused] or ["the result says: do not enter"]
        return EnteredValues([a for a in map(_axis, rows) if a is not None], "entered", entered.get("heldout"), refused)
    return EnteredValues([a for a in map(_axis, doc["joint_offsets"]) if a is not None], "joint_offsets", None, refused)


def read_entered(path: str | Path) -> EnteredValues:
    """``entered_values`` of the result file ``path``; ValueError naming the file when it is not one."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read a fit result: {exc}") from exc
    try:
        return entered_values(doc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
