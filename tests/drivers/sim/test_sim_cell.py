"""The simulated cell: hidden truth, gravity sag, noise, occlusion, cones, seeds, threads."""

import threading

import numpy as np
import pytest

from calib.robot.model import load_robot_model
from drivers.errors import LimitError
from drivers.sim.cell import SimCell, joint_frames
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH, SimConfig, load_sim_config
from drivers.sim.scene import MarkerScene, RobotScene

DEFAULT = load_sim_config(DEFAULT_CONFIG_PATH)
MODEL = load_robot_model(DEFAULT.robot)
ZERO_LINK_ERRORS = {"d_mm": [0.0] * 7, "a_mm": [0.0] * 7, "alpha_deg": [0.0] * 7, "beta_deg": [0.0] * 7}
#: A robot built exactly to its drawing: no zero-offsets, no link errors.
EXACT = {"offsets_deg": [0.0] * 7, "link_errors": ZERO_LINK_ERRORS}
STRETCHED = np.radians([0, 90, 0, 0, 0, 0, 0])  # the arm horizontal along +x, flange facing +x
FACING = np.radians([0, 20, 0, -90, 0, -30, 0])  # the default start: the plate faces both sensors


def make(**changes) -> SimCell:
    """A cell from the default config with nested fields replaced (dicts merge one level)."""
    data = DEFAULT.model_dump()
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return SimCell(SimConfig.model_validate(data), model=MODEL)


def rigid(**changes) -> SimCell:
    return make(deflection={"compliance_rad_per_nm": None}, **changes)


# --- protocol and API ----------------------------------------------------------------------


def test_cell_implements_both_scene_protocols_and_keeps_the_given_clock():
    clock = SimClock(time_scale=20)
    cell = SimCell(DEFAULT, clock=clock, model=MODEL)
    assert isinstance(cell, MarkerScene) and isinstance(cell, RobotScene)
    assert cell.clock is clock
    assert cell.sensor_names == ["mocap", "tracker"]
    assert cell.marker_names == ["smr", "sir"]
    assert cell.sensor_markers("tracker") == ["smr"] and cell.sensor_markers("mocap") == ["sir"]


def test_joint_positions_round_trip_and_are_copies():
    cell = make()
    assert cell.joint_positions() == pytest.approx(FACING)
    q = np.radians([10, 20, 30, -40, 50, -60, 70])
    cell.set_joint_positions(q)
    got = cell.joint_positions()
    got[0] = 99.0
    assert cell.joint_positions() == pytest.approx(q)


@pytest.mark.parametrize(
    "q, error, fragment",
    [
        (np.zeros(6), ValueError, r"shape \(7,\), got \(6,\)"),
        (np.zeros((2, 7)), ValueError, r"shape \(7,\), got \(2, 7\)"),
        (np.array([0, np.nan, 0, 0, 0, 0, 0]), ValueError, "finite"),
        (np.radians([0, 0, 0, 123, 0, 0, 0]), LimitError, r"end stops \(limits ± 2.0°\): A4 123.000° not in \[-122.0, 122.0\]"),
    ],
)
def test_bad_joint_positions_are_refused_with_what_was_given(q, error, fragment):
    cell = make()
    with pytest.raises(error, match=fragment):
        cell.set_joint_positions(q)
    assert cell.joint_positions() == pytest.approx(FACING)


def test_a_small_overshoot_past_a_limit_is_accepted():
    cell = make()
    q = np.radians([0, 0, 0, 121.5, 0, 0, 0])  # 1.5° past A4's limit, inside its end stop
    cell.set_joint_positions(q)
    assert cell.joint_positions() == pytest.approx(q)


def test_unknown_sensor_lists_the_known_ones():
    cell = make()
    with pytest.raises(ValueError, match=r"unknown sensor 'laser'; this cell has \['mocap', 'tracker'\]"):
        cell.observe("laser")
    with pytest.raises(ValueError, match="unknown sensor"):
        cell.true_marker_positions(FACING, frame="laser")


# --- truth -----------------------------------------------------------------------------------


def test_joint_frames_end_at_the_chain_flange():
    cell = make()
    q = np.random.default_rng(3).uniform(-1.5, 1.5, (20, 7))
    frames = joint_frames(cell.chain, q, cell.truth.params)
    assert frames.shape == (20, 8, 4, 4)
    assert frames[:, -1] @ cell.chain.flange == pytest.approx(cell.chain.fk(q, cell.truth.params), abs=1e-9)


def test_explicit_truth_is_applied_through_the_parameter_vector():
    offsets = [0.477, -0.192, 0.139, 0.099, 0.392, -0.114, 0.936]  # the paper's Table I (mocap)
    cell = rigid(truth={"offsets_deg": offsets, "link_errors": {**ZERO_LINK_ERRORS, "d_mm": [0.3] + [0.0] * 6}})
    assert cell.truth.offsets_deg == pytest.approx(offsets)
    expected = cell.chain.nominal.copy()
    expected[:7] = np.radians(offsets)
    expected[cell.chain.index("d", 0)] += 0.3
    assert cell.truth.params == pytest.approx(expected)
    q = np.random.default_rng(4).uniform(-1.5, 1.5, (30, 7))
    assert cell.true_marker_positions(q) == pytest.approx(cell.chain.marker_positions(q, expected), abs=1e-9)
    # The nominal model is off by millimetres: the offsets are not a rounding error.
    miss = np.linalg.norm(cell.true_marker_positions(q) - cell.chain.marker_positions(q), axis=-1)
    assert miss.mean() > 2.0


def test_drawn_truth_has_the_configured_sizes():
    offsets, d_err, alpha_err, beta_err = [], [], [], []
    for seed in range(40):
        truth = make(seed=seed).truth
        offsets.append(truth.offsets_deg)
        err = truth.param_errors
        d_err.append(err[7:14])
        alpha_err.append(np.degrees(err[21:28]))
        beta_err.append(err[28:35])
    n = 40 * 7
    tol = 4 / np.sqrt(2 * n)  # relative standard error of a sample std, 4σ
    assert np.std(offsets) == pytest.approx(0.3, rel=tol)
    assert np.std(d_err) == pytest.approx(0.2, rel=tol)
    assert np.std(alpha_err) == pytest.approx(0.02, rel=tol)
    assert np.all(np.array(beta_err) == 0.0)  # a standard-DH model draws no β


def test_marker_positions_in_a_sensor_frame_use_the_true_sensor_pose():
    cell = make()
    q = np.random.default_rng(5).uniform(-1, 1, (10, 7))
    base = cell.true_marker_positions(q)
    for name in cell.sensor_names:
        t = cell.truth.base2sensor[name]
        assert cell.true_marker_positions(q, frame=name) == pytest.approx(base @ t[:3, :3].T + t[:3, 3])
    # The default tracker is about 2 m from the robot, below the motion-capture bar.
    origin = np.linalg.inv(cell.truth.base2sensor["tracker"])[:3, 3]
    assert origin == pytest.approx([2000, 0, 900])


# --- gravity sag -----------------------------------------------------------------------------


def sag(cell: SimCell, q: np.ndarray) -> np.ndarray:
    """Marker displacement by the sag, (..., m, 3) mm."""
    return cell.true_marker_positions(q) - cell.chain.marker_positions(q, cell.truth.params)


def test_sag_vanishes_with_the_arm_vertical():
    cell = make(truth=EXACT)
    q = np.zeros(7)
    assert cell.gravity_torques(q) == pytest.approx(np.zeros(7), abs=1e-9)
    assert sag(cell, q) == pytest.approx(np.zeros((2, 3)), abs=1e-9)
    # Turning the vertical axes changes nothing either.
    q = np.radians([40, 0, -70, 0, 100, 0, 30])
    assert np.abs(sag(cell, q)).max() < 1e-9


def test_sag_matches_a_hand_computed_single_joint_case():
    """Only A2 yields; arm horizontal along +x: τ = g Σ m r over the links beyond the shoulder."""
    k = 5e-6
    cell = make(
        truth=EXACT,
        deflection={"compliance_rad_per_nm": [0, k, 0, 0, 0, 0, 0]},
    )
    # Lever arms (m) from the A2 axis: link 3 mid-upper-arm 0.21, link 4 the elbow 0.42, link 5
    # mid-forearm 0.62, link 6 the wrist 0.82, link 7 mid-wrist 0.883, tool 0.946 + 0.015.
    masses = [3.0, 2.7, 1.7, 1.8, 0.3, 0.4]
    levers = [0.21, 0.42, 0.62, 0.82, 0.883, 0.961]
    tau = 9.81 * sum(mm * r for mm, r in zip(masses, levers))
    assert cell.gravity_torques(STRETCHED)[1] == pytest.approx(tau, rel=1e-9)
    # A small rotation kτ about the A2 axis (through the shoulder at z = 360) moves each marker
    # straight down by kτ times its horizontal distance from the axis (to first order: the
    # second-order term is (kτ)²·r/2 ≈ 2e-5 mm).
    markers = cell.chain.marker_positions(STRETCHED)
    expected = np.zeros_like(markers)
    expected[:, 2] = -k * tau * markers[:, 0]
    expected[:, 0] = k * tau * (markers[:, 2] - 360.0)
    assert sag(cell, STRETCHED) == pytest.approx(expected, abs=1e-4)
    assert np.abs(expected).max() > 0.2


def test_sag_grows_as_the_arm_leans_over_and_peaks_horizontal():
    cell = make(truth=EXACT)
    a2 = np.radians(np.arange(0, 121, 10))
    q = np.zeros((len(a2), 7))
    q[:, 1] = a2
    size = np.linalg.norm(sag(cell, q), axis=-1).mean(axis=-1)
    peak = np.argmax(size)
    assert a2[peak] == pytest.approx(np.radians(90))
    assert np.all(np.diff(size[: peak + 1]) > 0) and np.all(np.diff(size[peak:]) < 0)
    # Rigid-link lever arms: the A2 torque goes as sin(A2), so 30° gives half of 90°.
    torque = cell.gravity_torques(q)[:, 1]
    assert torque[3] / torque[9] == pytest.approx(0.5, rel=1e-6)
    # Default config: a few tenths of a millimetre at full stretch.
    assert 0.2 < size[peak] < 0.6


def test_sag_depends_on_the_whole_configuration():
    cell = make()
    rng = np.random.default_rng(6)
    q = rng.uniform(-1.5, 1.5, (200, 7))
    dq = cell.deflection(q)
    assert dq.shape == (200, 7)
    assert np.all(dq[:, 0] == 0.0)  # A1's axis is vertical: gravity never loads it
    # Several joints sag, and their sag varies with the pose — no constant offset absorbs it.
    spread = np.std(dq, axis=0)
    assert np.sum((spread > 1e-6) & (spread > 0.5 * np.abs(dq).mean(axis=0))) >= 3
    size = np.linalg.norm(sag(cell, q), axis=-1)
    assert np.percentile(size, 90) > 4 * np.percentile(size, 10)


# --- noise -----------------------------------------------------------------------------------


@pytest.mark.parametrize("sensor, base_std, per_m", [("mocap", 0.03, 0.0), ("tracker", 0.015, 0.006)])
def test_noise_has_the_configured_size(sensor, base_std, per_m):
    cell = make(seed=11)
    n = 3000
    samples = np.array([cell.observe(sensor)[0].position_mm for _ in range(n)])
    truth = cell.true_marker_positions(cell.joint_positions(), frame=sensor)[cell.marker_names.index(cell.sensor_markers(sensor)[0])]
    origin = np.linalg.inv(cell.truth.base2sensor[sensor])[:3, 3]
    range_m = np.linalg.norm(cell.true_marker_positions(cell.joint_positions())[0] - origin) / 1000
    expected = base_std + per_m * range_m
    assert range_m > 1.0
    std = samples.std(axis=0, ddof=1)
    assert std == pytest.approx(np.full(3, expected), rel=4 / np.sqrt(2 * n))
    assert samples.mean(axis=0) == pytest.approx(truth, abs=4 * expected / np.sqrt(n))
    # Axes are independent.
    corr = np.corrcoef(samples.T)
    assert np.abs(corr[np.triu_indices(3, 1)]).max() < 4 / np.sqrt(n)


def test_tracker_noise_grows_with_range():
    cell = make()
    assert cell.noise_std_mm("tracker", [1000.0, 5000.0]) == pytest.approx([0.021, 0.045])
    assert cell.noise_std_mm("mocap", [1000.0, 5000.0]) == pytest.approx([0.03, 0.03])


# --- occlusion and cones ------------------------------------------------------------------------


def test_a_link_between_sensor_and_marker_occludes_it():
    """A low sensor 2 m out along A1 = −20°; the arm stretched towards it, then turned by A1 to
    the opposite side, so the base column and the arm stand between the sensor and the plate.
    Cones are opened fully so only bodies can hide the marker."""
    a = np.radians(-20)
    origin = [2000 * np.cos(a), 2000 * np.sin(a), 200]
    sensor = {"name": "low", "kind": "mocap", "origin_mm": origin, "look_at_mm": [0, 0, 300], "noise_mm": 0.03}
    wide = {"retroreflector": 180, "infrared": 180, "other": 180}
    cell = make(sensors=[sensor], cones_deg=wide, truth=EXACT)
    towards = STRETCHED + np.radians([-20, 0, 0, 0, 0, 0, 0])
    away = STRETCHED + np.radians([160, 0, 0, 0, 0, 0, 0])
    assert cell.visibility(np.stack([towards, away]), "low").tolist() == [[True], [False]]
    cell.set_joint_positions(away)
    (obs,) = cell.observe("low")
    assert not obs.visible and np.isnan(obs.position_mm).all()
    cell.set_joint_positions(towards)
    (obs,) = cell.observe("low")
    assert obs.visible and np.isfinite(obs.position_mm).all()
    # Without link bodies the same turned-away pose is in plain sight: the links did it.
    ghost = make(sensors=[sensor], cones_deg=wide, occlusion={"link_radii_mm": None})
    assert ghost.visibility(away, "low").tolist() == [True]


def test_an_obstacle_in_the_cell_breaks_the_beam():
    post = {"a_mm": [1200, 0, 0], "b_mm": [1200, 0, 2000], "radius_mm": 60}
    clear = make()
    blocked = make(occlusion={"obstacles": [post]})
    assert clear.visibility(FACING, "tracker").tolist() == [True]
    assert blocked.visibility(FACING, "tracker").tolist() == [False]


def test_acceptance_cones_of_the_retroreflector_and_the_infrared_marker():
    """Sensors placed around the markers at known angles from the plate normal (flange z)."""
    base = rigid(truth={"link_errors": ZERO_LINK_ERRORS})
    q = STRETCHED
    smr, sir = base.true_marker_positions(q)
    normal = base.chain.fk(q, base.truth.params)[:3, 2]
    assert normal == pytest.approx([1, 0, 0], abs=0.02)

    def around(point, deg, kind, name):
        a = np.radians(deg)
        direction = np.array([np.cos(a), np.sin(a), 0.0])  # turned about base z from +x
        origin = point + 1500 * direction
        return {"name": name, "kind": kind, "origin_mm": origin.tolist(), "look_at_mm": point.tolist(), "noise_mm": 0.01}

    sensors = [
        around(smr, 20, "tracker", "t20"),
        around(smr, 40, "tracker", "t40"),
        around(sir, -50, "mocap", "m50"),
        around(sir, -70, "mocap", "m70"),
    ]
    cell = rigid(sensors=sensors, truth={"link_errors": ZERO_LINK_ERRORS})
    seen = {name: cell.visibility(q, name).tolist() for name in cell.sensor_names}
    assert seen == {"t20": [True], "t40": [False], "m50": [True], "m70": [False]}


def test_a_camera_does_not_see_outside_its_field_of_view():
    cell = make()
    # Turned by A1, the plate leaves the bar's 28° view cone (and the tracker's 30° cone).
    q = FACING + np.radians([120, 0, 0, 0, 0, 0, 0])
    assert cell.visibility(q, "mocap").tolist() == [False]
    narrow = make(sensors=[{**DEFAULT.sensors[0].model_dump(), "field_of_view_deg": 1.0}])
    assert narrow.visibility(FACING, "mocap").tolist() == [False]
    assert make().visibility(FACING, "mocap").tolist() == [True]


def test_visibility_is_batched_over_configurations():
    cell = make()
    q = np.random.default_rng(7).uniform(-1.5, 1.5, (300, 7))
    batch = cell.visibility(q, "mocap")
    assert batch.shape == (300, 1)
    single = np.array([cell.visibility(x, "mocap") for x in q[:40]])
    assert np.array_equal(batch[:40], single)
    assert 0 < batch.sum() < 300


# --- reproducibility and threads -----------------------------------------------------------------


def observations(cell, k=20):
    out = []
    for i in range(k):
        cell.set_joint_positions(FACING + 0.001 * i)
        out.extend(o.position_mm for s in cell.sensor_names for o in cell.observe(s))
    return np.array(out)


def test_same_seed_same_cell_and_samples_other_seed_differs():
    a, b, c = make(seed=5), make(seed=5), make(seed=6)
    assert np.array_equal(a.truth.params, b.truth.params)
    assert np.array_equal(observations(a), observations(b))
    assert not np.array_equal(a.truth.params, c.truth.params)
    assert not np.allclose(observations(make(seed=5)), observations(c), atol=1e-6)


def test_adding_a_sensor_does_not_change_the_robot_truth_or_other_noise():
    extra = {"name": "spare", "kind": "mocap", "frame": {"xyz": [0, 2000, 1000]}, "noise_mm": 0.05}
    a = make(seed=9)
    b = make(seed=9, sensors=[*DEFAULT.model_dump()["sensors"], extra])
    assert np.array_equal(a.truth.params, b.truth.params)
    assert np.array_equal(a.observe("tracker")[0].position_mm, b.observe("tracker")[0].position_mm)


def test_concurrent_writer_and_readers_see_consistent_states():
    cell = make(seed=3)
    n_writes, n_reads = 1500, 150
    steps = np.radians(np.linspace(0, 10, n_writes))
    targets = FACING + steps[:, None] * np.array([1, 0.5, -1, 0.5, 1, -0.5, 1])
    start = threading.Barrier(4)
    errors: list[BaseException] = []
    seen_q: list[np.ndarray] = []
    seen_obs: list[np.ndarray] = []

    def writer():
        start.wait(timeout=10)
        for q in targets:
            cell.set_joint_positions(q)

    def reader(sensor):
        start.wait(timeout=10)
        try:
            for _ in range(n_reads):
                seen_q.append(cell.joint_positions())
                (obs,) = cell.observe(sensor)
                if obs.visible:
                    seen_obs.append((sensor, obs.position_mm))
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            errors.append(exc)

    threads = [threading.Thread(target=writer)] + [
        threading.Thread(target=reader, args=(s,)) for s in ("mocap", "tracker", "mocap")
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads)
    assert not errors
    # Every joint vector read is one that was written whole (no torn reads).
    allowed = np.vstack([FACING, targets])
    for q in seen_q:
        assert np.min(np.abs(allowed - q).max(axis=1)) == 0.0
    # Every observation is one written pose's marker, within noise (no pose/geometry mix-ups).
    assert len(seen_obs) > 50
    for sensor in ("mocap", "tracker"):
        idx = cell.marker_names.index(cell.sensor_markers(sensor)[0])
        truth = cell.true_marker_positions(allowed, frame=sensor)[:, idx]
        for name, p in seen_obs:
            if name == sensor:
                assert np.min(np.linalg.norm(truth - p, axis=1)) < 0.3
