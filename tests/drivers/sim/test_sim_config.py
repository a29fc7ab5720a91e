"""The cell's YAML configuration: the default file, and bad files that say what is wrong."""

from pathlib import Path

import pytest

from calib.io.yamlfile import ConfigError
from drivers.sim.cell import SimCell
from drivers.sim.config import DEFAULT_CONFIG_PATH, SimConfig, load_sim_config


def test_default_config_loads_with_an_existing_robot_and_two_sensors():
    config = load_sim_config(DEFAULT_CONFIG_PATH)
    assert Path(config.robot).is_absolute() and Path(config.robot).is_file()
    assert config.sensor_names == ["mocap", "tracker"]
    assert config.sensors[0].noise_mm == 0.03
    assert (config.sensors[1].noise_mm, config.sensors[1].noise_mm_per_m) == (0.015, 0.006)


def test_default_cell_starts_with_both_markers_in_view():
    cell = SimCell.from_yaml(DEFAULT_CONFIG_PATH)
    for sensor in cell.sensor_names:
        (obs,) = cell.observe(sensor)
        assert obs.visible, sensor


def write(tmp_path, text):
    robot = DEFAULT_CONFIG_PATH.parent.parent / "robots" / "kuka_iiwa14_r820.yaml"
    path = tmp_path / "cell.yaml"
    path.write_text(f"robot: {robot}\n" + text, encoding="utf-8")
    return path


def test_negative_noise_names_line_and_field(tmp_path):
    path = write(
        tmp_path,
        "sensors:\n"
        "  - {name: m, kind: mocap, origin_mm: [2000, 0, 1000], look_at_mm: [0, 0, 500], noise_mm: 0.03}\n"
        "  - name: t\n"
        "    kind: tracker\n"
        "    frame: {xyz: [2000, 0, 900]}\n"
        "    noise_mm: -1\n",
    )
    with pytest.raises(ConfigError) as err:
        load_sim_config(path)
    msg = str(err.value)
    assert "cell.yaml:7:" in msg and "sensors.1.noise_mm" in msg and "-1" in msg


@pytest.mark.parametrize(
    "sensor, fragment",
    [
        ("{name: s, kind: mocap, noise_mm: 0.03}", "exactly one pose"),
        ("{name: s, kind: mocap, noise_mm: 0.03, origin_mm: [1, 2, 3]}", "both origin_mm and look_at_mm"),
        (
            "{name: s, kind: mocap, noise_mm: 0.03, origin_mm: [1, 2, 3], look_at_mm: [0, 0, 0], frame: {}}",
            "exactly one pose",
        ),
        ("{name: s, kind: camera, noise_mm: 0.03, frame: {}}", "mocap"),
    ],
)
def test_sensor_pose_and_kind_are_validated(tmp_path, sensor, fragment):
    with pytest.raises(ConfigError, match=fragment):
        load_sim_config(write(tmp_path, f"sensors:\n  - {sensor}\n"))


def test_duplicate_sensor_names_are_refused(tmp_path):
    s = "{name: s, kind: mocap, noise_mm: 0.03, frame: {}}"
    with pytest.raises(ConfigError, match=r"repeated: \['s'\]"):
        load_sim_config(write(tmp_path, f"sensors:\n  - {s}\n  - {s}\n"))


def base_dict():
    config = load_sim_config(DEFAULT_CONFIG_PATH)
    return config.model_dump()


@pytest.mark.parametrize(
    "path, value, fragment",
    [
        (("truth", "offsets_deg"), [0.1, 0.2], r"truth.offsets_deg: 2 values given, the robot has 7 joints"),
        (("deflection", "compliance_rad_per_nm"), [1e-6] * 6, r"deflection.compliance_rad_per_nm: 6 values"),
        (("occlusion", "link_radii_mm"), [50] * 8, r"occlusion.link_radii_mm: 8 values"),
        (("truth", "link_errors", "d_mm"), [0.0] * 3, r"truth.link_errors.d_mm: 3 values"),
        (("initial_joint_positions_deg",), [0] * 6, r"initial_joint_positions_deg: 6 values"),
    ],
)
def test_per_joint_lists_must_match_the_robot(path, value, fragment):
    data = base_dict()
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    with pytest.raises(ConfigError, match=fragment):
        SimCell(SimConfig.model_validate(data))


def test_unknown_sensor_marker_lists_the_tool_markers():
    data = base_dict()
    data["sensors"][0]["markers"] = ["smr", "nope"]
    with pytest.raises(ConfigError, match=r"unknown markers \['nope'\]; the tool has \['smr', 'sir'\]"):
        SimCell(SimConfig.model_validate(data))


def test_initial_pose_outside_the_limits_is_refused():
    data = base_dict()
    data["initial_joint_positions_deg"] = [0, 130, 0, 0, 0, 0, 0]
    with pytest.raises(ValueError, match=r"A2 130.000° not in \[-122.0, 122.0\]"):
        SimCell(SimConfig.model_validate(data))


def test_seed_override_from_yaml_changes_the_truth():
    a = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=1)
    b = SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=2)
    assert a.truth.seed == 1 and b.truth.seed == 2
    assert not (a.truth.offsets_rad == b.truth.offsets_rad).any()
    with pytest.raises(ValueError, match="non-negative"):
        SimCell.from_yaml(DEFAULT_CONFIG_PATH, seed=-3)
