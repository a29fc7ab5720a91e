"""Compare the answers of two sets of default fits (``bench_default_fit.py --keep DIR`` of two trees).

    python tests/bench/compare_fits.py BEFORE_DIR AFTER_DIR

For every ``*.default.json`` in both: the chosen model, the verdict per axis (the controller's
action: enter / do not enter / …, and the refusals), and each fitted offset's change in units of
the "before" standard deviation (issue 33: the same model, the same verdicts, offsets within 0.1σ)
— the chosen model's offsets and the controller's (``entered``: fitted for the nominal arm), with
the controller's verdict and its held-out improvement (mean, 95 % interval).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _offsets(doc: dict) -> dict[str, tuple[float | None, float | None, str]]:
    return {j["joint"]: (j["value_deg"], j["std_deg"], j["status"]) for j in doc["joint_offsets"]}


def _entered(doc: dict) -> dict[str, tuple[float | None, float | None, str]]:
    """The controller's offsets (``entered``) as ``_offsets`` gives the model's."""
    return {o["joint"]: (o["value_deg"], o["std_deg"], "enter" if o["enter"] else o["reason"][:40])
            for o in doc.get("entered", {}).get("offsets", [])}


def _changes(ob: dict, oa: dict) -> tuple[float, list[str]]:
    """(largest |after − before| ÷ before's std, one line per axis)."""
    worst, cells = 0.0, []
    for joint, (vb, sb, stb) in ob.items():
        va, sa, sta = oa.get(joint, (None, None, "missing"))
        if vb is None or va is None or not sb:
            cells.append(f"{joint} {stb}→{sta}" if stb != sta else f"{joint} —")
            continue
        z = abs(va - vb) / sb
        worst = max(worst, z)
        cells.append(f"{joint} {vb:+.4f}→{va:+.4f}° ({z:.2f}σ, sd {sb:.4f}→{sa:.4f})")
    return worst, cells


def _improvement(doc: dict) -> str:
    imp = doc.get("entered", {}).get("heldout", {}).get("improvement_mm", {})
    if imp.get("value") is None:
        return "—"
    lo, hi = imp["ci95"]
    return f"{imp['value']:+.4f} mm [{lo:+.4f}, {hi:+.4f}]"


def _actions(doc: dict) -> list[str]:
    return [a.get("action", "?") for a in doc.get("controller", {}).get("axes", [])]


def main() -> None:
    before, after = Path(sys.argv[1]), Path(sys.argv[2])
    worst_all = 0.0
    for b_path in sorted(before.glob("*.default.json")):
        a_path = after / b_path.name
        if not a_path.exists():
            print(f"{b_path.name}: no 'after' result")
            continue
        b, a = json.loads(b_path.read_text()), json.loads(a_path.read_text())
        mb, ma = b["model_choice"]["chosen"], a["model_choice"]["chosen"]
        worst, cells = _changes(_offsets(b), _offsets(a))
        worst_e, cells_e = _changes(_entered(b), _entered(a))
        worst_all = max(worst_all, worst, worst_e)
        same = "same" if mb == ma else "DIFFERENT"
        verdict = "same" if _actions(b) == _actions(a) and bool(b.get("do_not_use")) == bool(a.get("do_not_use")) else "DIFFERENT"
        vb, va = b.get("entered", {}).get("verdict"), a.get("entered", {}).get("verdict")
        print(f"{b_path.stem.replace('.default', '')}: model {mb} → {ma} ({same}); verdicts {_actions(b)} → {_actions(a)} "
              f"({verdict}); largest offset change {worst:.3f}σ")
        for c in cells:
            print(f"    {c}")
        print(f"  the controller's offsets (entered): verdict {vb} → {va} ({'same' if vb == va else 'DIFFERENT'}); "
              f"held-out improvement {_improvement(b)} → {_improvement(a)}; largest offset change {worst_e:.3f}σ")
        for c in cells_e:
            print(f"    {c}")
    print(f"largest offset change over all cases: {worst_all:.3f}σ")


if __name__ == "__main__":
    main()
