"""Full identification and the socket fit take the compliance sag at the fitted arm.

The sag's first-order term is ∂p/∂δ · sign·k·τ(q). Both fits already took the lever ∂p/∂δ at the
arm being evaluated, but the torques τ at the data sheet's arm: a cell that lost its mastering
(zeros off by 1–2°) with links off by tenths of a millimetre carries torques a few % off the
nominal ones, and with an iiwa's compliance that is a systematic error of the size of the noise.
The true measurements here are made by walking the true chain at the sagged angles
(``tests.calib.nuisance_cells``, ``tests.calib.socket_sim``), independently of the fits' sag term.
Each test fails with the torques at the nominal arm (checked on the code before the change).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.fit.identification import IdentOptions, _Problem, identify
from calib.fit.socket import ball_positions, fit_socket
from calib.robot.kinematics import Chain
from calib.robot.model import load_robot_model
from tests.calib.nuisance_cells import nuisance_cell
from tests.calib.socket_sim import equivalent_ball, simulate, true_params

IIWA = Path(__file__).resolve().parents[2] / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e ** 2)))


def _lost_mastering_cell():
    """Nuisance cell 0 with zeros ~N(0, 1°): A2 2.35° off, the tool 28 mm off its drawing, link
    errors of a Panda's size, sag; tracker rows of 0.0045 mm per axis."""
    cell = nuisance_cell(0, outlier=False, offset_deg=1.0)
    assert abs(np.degrees(cell.truth[1])) > 2 and cell.tool_mm > 25
    return cell


def test_identification_predicts_the_sagging_arm_at_its_true_parameters():
    cell = _lost_mastering_cell()
    chain, data = Chain(cell.model), cell.cal
    (sensor,) = data.sensors
    problem = _Problem(chain, data, {sensor: cell.base2sensor}, None, 100.0, compliance=True)
    x = np.zeros(len(problem.names))
    x[: problem.P] = cell.truth
    x[problem.comp_start: problem.comp_start + chain.n] = cell.compliance * 1e6
    r, _ = problem.residuals_and_jacobian(x, want_jac=False)
    predicted = data.xyz_mm - r.reshape(-1, 3)
    # torques at the nominal arm: 0.0045 mm rms per axis, the noise of a row; at the true arm: 1e-5
    assert _rms(predicted - cell.true_positions(data.q_rad, data.marker)) < 0.05 * cell.noise_mm


def test_identification_with_compliance_covers_the_true_offsets_of_a_cell_that_lost_its_mastering():
    cell = _lost_mastering_cell()
    n = cell.model.n_joints
    result = identify(cell.model, cell.cal, IdentOptions(compliance=True, n_starts=1))
    fitted = np.isfinite(result.std[:n])
    assert fitted[1:6].all()  # A1 is the registration's, A7 the tool's
    z = (result.params[:n] - cell.truth[:n])[fitted] / result.std[:n][fitted]
    # at the nominal arm A2 came out at z = −3.1 (noise-free: −4.4); now every offset is inside its 95 % interval
    assert np.all(np.abs(z) < 1.96), z
    loaded = np.isfinite(result.compliance_std)
    zc = (result.compliance - cell.compliance)[loaded] / result.compliance_std[loaded]
    assert loaded.sum() >= 3 and np.all(np.abs(zc) < 1.96), zc


def _sagging_socket_cell(play_mm: float, seed: int = 101):
    """A simulated iiwa socket cell (3 placements × 2 sockets × 20) with zeros ~N(0, 1°) (seed
    101: A2 2.03° off), links off by 0.5 mm / 0.3° (sd), a ball 40 mm out and compliances of the size the
    real iiwa sockets show (fitted there: 3e-5–1.1e-4 rad/(N·m) on A2–A4)."""
    model = load_robot_model(IIWA)
    chain = Chain(model)
    rng = np.random.default_rng(seed)
    truth = true_params(chain, rng, offset_deg=1.0, link_mm=0.5, twist_deg=0.3)
    compliance = np.array([6e-5] * 4 + [1.2e-4] * 3) * rng.uniform(0.5, 1.5, chain.n)
    ds, points = simulate(model, truth, rng, play_mm=play_mm, compliance=compliance)
    return model, chain, truth, compliance, ds, points


def test_socket_ball_positions_carry_the_sag_of_the_arm_they_are_given():
    """``ball_positions`` (the fit's held-out predictions and every cross-validation fold's) at the
    true arm puts the sagging ball in its socket (rms per axis): without the sag 1.04 mm off, with
    the torques at the nominal arm 0.066 mm, at the true arm 0.0016 mm (the first-order term's own
    error: sags of up to 4 mrad)."""
    model, chain, truth, compliance, ds, points = _sagging_socket_cell(play_mm=0.0)
    assert _rms(ball_positions(chain, ds.q_rad, truth) - points[ds.group]) > 0.5
    assert _rms(ball_positions(chain, ds.q_rad, truth, compliance) - points[ds.group]) < 0.005  # a tenth of the play


def test_socket_fit_with_compliance_covers_the_true_offsets_of_a_cell_that_lost_its_mastering():
    model, chain, truth, compliance, ds, _ = _sagging_socket_cell(play_mm=0.05)
    n = chain.n
    assert abs(np.degrees(truth[1])) > 2
    fit = fit_socket(model, ds, tolerance=(0.5, 0.3), compliance=True)
    ms = chain.marker_slice()
    truth[ms.start: ms.start + 3] = equivalent_ball(chain, truth)  # the last link's errors are the ball's
    fitted = np.isfinite(fit.std[:n])
    assert fitted[1:6].all()
    z = (fit.params[:n] - truth[:n])[fitted] / fit.std[:n][fitted]
    # at the nominal arm A2 came out at z = −4.7; now every offset is inside its 95 % interval
    assert np.all(np.abs(z) < 1.96), z
    loaded = np.isfinite(fit.compliance_std)
    zc = (fit.compliance - compliance)[loaded] / fit.compliance_std[loaded]
    assert loaded.sum() >= 3 and np.all(np.abs(zc) < 1.96), zc


@pytest.mark.slow  # a coverage study: 16 tracker cells and 16 socket cells (~1 CPU-minute)
def test_over_many_cells_that_lost_their_mastering_the_offsets_intervals_hold():
    """16 nuisance tracker cells (zeros ~N(0, 1°)) by full identification and 16 sagging socket
    cells as above by the socket fit, with compliance. With the torques at the nominal arm:
    11 of 80 identified offsets outside their 95 % interval, and a socket offset at 4.7σ; at the
    fitted arm 4 of 80 (largest 3.0σ) and 1 of 80 (largest 2.2σ)."""
    z_ident, z_socket = [], []
    for seed in range(16):
        cell = nuisance_cell(seed, outlier=False, offset_deg=1.0)
        n = cell.model.n_joints
        r = identify(cell.model, cell.cal, IdentOptions(compliance=True, n_starts=1))
        z = (r.params[:n] - cell.truth[:n]) / r.std[:n]
        z_ident += list(z[np.isfinite(z)])
        model, chain, truth, compliance, ds, _ = _sagging_socket_cell(0.05, seed=100 + seed)
        fit = fit_socket(model, ds, tolerance=(0.5, 0.3), compliance=True)
        ms = chain.marker_slice()
        truth[ms.start: ms.start + 3] = equivalent_ball(chain, truth)
        z = (fit.params[:n] - truth[:n]) / fit.std[:n]
        z_socket += list(z[np.isfinite(z)])
    z_ident, z_socket = np.abs(z_ident), np.abs(z_socket)
    assert z_ident.size == z_socket.size == 80
    # 95 % intervals: 4 ± 2 of 80 expected outside; 8 or fewer (the nominal arm's torques: 11)
    assert np.sum(z_ident > 1.96) <= 8 and np.sum(z_socket > 1.96) <= 8, (np.sort(z_ident)[-12:], np.sort(z_socket)[-12:])
    assert z_socket.max() < 3.5, np.sort(z_socket)[-5:]  # the nominal arm's: 4.7
