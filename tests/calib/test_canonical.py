"""Canonical answers: offsets wrapped to (−180°, 180°], mirrored parameter sets mapped back to the
nominal model's branch with the same forward kinematics, and a model whose joint zero is 180° off
reaching the best minimum and reported as such."""

import math

import numpy as np
import pytest

from calib.robot.canonical import canonical_params, wrap_angle, wrap_deg
from calib.robot.controller import controller_values
from calib.fit.identification import IdentOptions, ident_result_dict, identify
from calib.robot.kinematics import Chain
from tests.calib.tracker_sim import CAL_NESTS, observe, tracker_cell


def _dh_flange(model, params, q):
    """Flange frame (4, 4) by an independent product of the convention's 4×4 link matrices."""
    n = model.n_joints

    def rz(t):
        c, s = math.cos(t), math.sin(t)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def rx(t):
        c, s = math.cos(t), math.sin(t)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])

    def ry(t):
        c, s = math.cos(t), math.sin(t)
        return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])

    def tr(x, z):
        t = np.eye(4)
        t[0, 3], t[2, 3] = x, z
        return t

    t = model.base.matrix()
    for i, j in enumerate(model.joints):
        theta = math.radians(j.theta) + j.sign * (q[i] + params[i])
        t = t @ rz(theta) @ tr(0, params[n + i]) @ tr(params[2 * n + i], 0) @ rx(params[3 * n + i]) @ ry(params[4 * n + i])
    return t @ model.flange.matrix()


def test_wrapping_takes_every_angle_to_the_half_open_interval():
    assert abs(wrap_deg(-361.10) + 1.10) < 1e-9  # J5 as reported before
    assert wrap_deg(180.0) == 180.0 and abs(wrap_deg(-180.0) - 180.0) < 1e-9
    assert abs(wrap_deg(539.0) - 179.0) < 1e-9
    a = wrap_angle(np.array([-3 * math.pi, 4.0, -4.0]))
    assert np.all((a > -math.pi) & (a <= math.pi))


def test_a_mirrored_set_is_mapped_back_with_the_same_kinematics():
    """Link J2 and J5 of the Stäubli (mdh) written as their mirrors by hand: (θ + 180°, −a, −α, −β)
    with the next joint's θ − 180° (J2), and (θ + 180°, −a, −α − 180°, β − 180°) (J5), offsets
    one turn off; the mapping gives the original set back, and an independent DH product says
    the flange has not moved."""
    cell = tracker_cell(0)
    chain = Chain(cell.model)
    n = chain.n
    right = cell.truth.copy()
    mirrored = right.copy()
    i = 1  # J2: frame turned about z
    mirrored[i] += math.pi
    mirrored[2 * n + i] *= -1
    mirrored[3 * n + i] *= -1
    mirrored[4 * n + i] *= -1
    mirrored[i + 1] -= math.pi
    i = 4  # J5: the mirrored link
    mirrored[i] += math.pi
    mirrored[2 * n + i] *= -1
    mirrored[3 * n + i] = -mirrored[3 * n + i] - math.pi
    mirrored[4 * n + i] -= math.pi
    mirrored[3] -= 2 * math.pi  # J4 one turn off
    rng = np.random.default_rng(3)
    q = rng.uniform(cell.model.lower_limits_rad, cell.model.upper_limits_rad, (50, n))
    for k in range(5):  # the hand-made mirror is a mirror (independent FK)
        np.testing.assert_allclose(_dh_flange(cell.model, mirrored, q[k]), _dh_flange(cell.model, right, q[k]), atol=1e-9)
    free = set(chain.param_names)
    mapping = canonical_params(chain, mirrored, free, q, list(CAL_NESTS))
    np.testing.assert_allclose(wrap_angle(mapping.params[:n] - right[:n]), 0.0, atol=1e-12)
    np.testing.assert_allclose(mapping.params[n:], right[n:], atol=1e-9)
    assert np.all(np.abs(mapping.params[:n]) <= math.pi)
    assert any(c.startswith("J2:") for c in mapping.changes) and any(c.startswith("J5:") for c in mapping.changes)
    for k in range(5):
        np.testing.assert_allclose(_dh_flange(cell.model, mapping.params, q[k]), _dh_flange(cell.model, mirrored, q[k]),
                                   atol=1e-9)
    assert mapping.fk_change_mm < 1e-9


def test_a_set_already_on_the_nominal_branch_is_only_wrapped():
    cell = tracker_cell(1)
    chain = Chain(cell.model)
    p = cell.truth.copy()
    p[2] += 2 * math.pi
    mapping = canonical_params(chain, p, set(chain.param_names), cell.cal.q_rad, list(CAL_NESTS))
    assert mapping.changes == []
    np.testing.assert_allclose(mapping.params, cell.truth, atol=1e-12)


def _zero_off(joint: int, seed: int):
    cell = tracker_cell(seed)
    chain = Chain(cell.model)
    truth = cell.truth.copy()
    truth[joint] += math.pi
    cal = observe(chain, cell.cal.q_rad[::len(CAL_NESTS)], truth, CAL_NESTS, cell.base2sensor,
                  np.random.default_rng(seed), 0.03, "cal")
    return cell, chain, truth, cal


def test_a_zero_off_by_180_degrees_reaches_the_best_minimum_and_is_reported_wrapped():
    """J2's true zero 180° from the model's (seed 0: before the flip screen every start ended at
    rms 2.7 mm or worse). The fit reaches the best minimum — the one a model with the right zero
    reaches — reports J2's offset as ±180° + δ wrapped to (−180°, 180°], and every link length and
    twist on the nominal model's branch."""
    cell, chain, truth, cal = _zero_off(1, 0)
    result = identify(cell.model, cal)
    d = cell.model.model_dump()
    d["joints"][1]["theta"] += 180.0
    right = identify(type(cell.model).model_validate(d), cal, IdentOptions(n_starts=2))
    assert result.starts[0]["cost"] <= right.starts[0]["cost"] * (1 + 1e-6)
    assert result.rms_mm < 0.04  # tracker noise 0.03 mm
    assert any("J2 zero +180°" in s["label"] for s in result.starts)
    n = chain.n
    off = result.params[:n]
    assert np.all((off > -math.pi) & (off <= math.pi))
    assert abs(abs(math.degrees(off[1])) - 180.0) < 1.0
    assert abs(wrap_angle(off[1] - truth[1])) < 4 * result.std[1]
    doc = ident_result_dict(result, cal)
    entry = {p["name"]: p for p in doc["parameters"]}["J2.offset"]
    assert -180.0 < entry["value"] <= 180.0 and abs(abs(entry["value"]) - 180.0) < 1.0
    lengths = chain.index("a")
    assert np.all(np.abs(result.params[lengths] - chain.nominal[lengths]) < 2.0)
    for kind in ("alpha", "beta"):
        idx = chain.index(kind)
        assert np.all(np.abs(wrap_angle(result.params[idx] - chain.nominal[idx])) < math.radians(1.0))


def test_a_right_nominal_model_solves_no_flipped_start():
    cell = tracker_cell(5)
    result = identify(cell.model, cell.cal)
    assert not [s for s in result.starts if "180°" in s["label"]]
    assert result.canonical == []


def test_controller_values_are_wrapped():
    """A whole turn is no correction: an offset written as −361.10° is entered as −1.10°."""
    cell = tracker_cell(0)
    entries = [{"joint": ax, "index": i + 1, "identifiable": i == 4, "value_deg": -361.10 if i == 4 else None,
                "std_deg": 0.01 if i == 4 else None, "status": "fitted" if i == 4 else "undetermined"}
               for i, ax in enumerate(cell.model.axis_names)]
    values = controller_values(cell.model, entries)
    assert abs(values.axes[4].delta_deg + 1.10) < 1e-9 and abs(values.axes[4].correction_deg - 1.10) < 1e-9


@pytest.mark.slow  # ~30 s: the CLI over the identification whose wrapping the default tests above check directly
def test_acquire_fit_full_reports_the_half_turned_zero_wrapped(tmp_path):
    """The same through the command: result.json, the console line and the corrected model."""
    import json

    from typer.testing import CliRunner

    from acquire.cli import app
    from calib.measure.dataset import write_csv
    from calib.fit.identification import write_model_yaml
    from calib.robot.model import load_robot_model

    cell, chain, truth, cal = _zero_off(3, 1)  # J4; before the flipped-zero starts: mirrored, tool turned
    write_model_yaml(cell.model, tmp_path / "robot.yaml")
    write_csv(cal, tmp_path / "cal.csv")
    out = tmp_path / "full.json"
    res = CliRunner().invoke(app, ["fit", str(tmp_path / "cal.csv"), "--robot", str(tmp_path / "robot.yaml"),
                                   "--method", "full", "-o", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    by = {p["name"]: p for p in doc["parameters"]}
    j4 = by["J4.offset"]["value"]
    # Within 0.1° of the truth (parameters the data cannot separate, kept nominal, bias it by ~0.02°).
    assert -180.0 < j4 <= 180.0 and abs(wrap_deg(j4 - np.degrees(truth[3]))) < 0.1
    assert all(-180.0 < p["value"] <= 180.0 for n, p in by.items() if n.endswith(".offset"))
    assert abs(by["J5.alpha"]["value"] - by["J5.alpha"]["nominal"]) < 1.0
    assert not [w for w in doc["warnings"] if "far outside their prior" in w]
    line = next(x for x in res.output.splitlines() if x.startswith("J4.offset"))
    assert f"{j4:.4f}" in line
    corrected = load_robot_model(doc["model_file"])
    assert abs(wrap_deg(corrected.joints[3].theta - cell.model.joints[3].theta - j4)) < 1e-6
    # The best minimum (the issue saw rms 0.178 against 0.141 mm from this start): no worse than the
    # fit of a model whose J4 zero is right, and every twist on the nominal model's branch.
    d = cell.model.model_dump()
    d["joints"][3]["theta"] += 180.0
    right = identify(type(cell.model).model_validate(d), cal, IdentOptions(n_starts=2))
    assert doc["rms_mm"] <= right.rms_mm * (1 + 1e-6), (doc["rms_mm"], right.rms_mm)
    for name, p in by.items():
        if name.endswith((".alpha", ".beta")):
            assert abs(wrap_deg(p["value"] - p["nominal"])) < 1.0, (name, p)
