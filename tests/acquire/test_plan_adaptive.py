"""The plan's ``adaptive`` section: a stop rule a metrologist states, refused with file, line,
field and what is allowed when it cannot be followed."""

from __future__ import annotations

import pytest

from acquire.plan.schema import load_plan
from calib.io.yamlfile import ConfigError
from tests.acquire.test_plan import minimal, write


def _load(tmp_path, adaptive, **extra):
    return load_plan(write(tmp_path, minimal(adaptive=adaptive, **extra)))


def test_a_valid_adaptive_section(tmp_path):
    lp = _load(tmp_path, {"stop_when": {"interval_deg": 0.01, "workspace_within_pct": 10}, "max_configurations": 30})
    ad = lp.plan.adaptive
    assert (ad.stop_when.interval_deg, ad.stop_when.workspace_within_pct, ad.max_configurations,
            ad.min_configurations) == (0.01, 10, 30, None)


@pytest.mark.parametrize("adaptive, field, allowed", [
    ({"stop_when": {}}, "adaptive.stop_when", "interval_deg: (0, 1], region_error_mm: (0, 100]"),
    ({"stop_when": {"region_error_mm": 0}}, "adaptive.stop_when.region_error_mm", "allowed (0, 100]"),
    ({"stop_when": {"joint_space_within_pct": -5}}, "adaptive.stop_when.joint_space_within_pct", "allowed [0, 1000]"),
    ({"stop_when": {"joint_space_error_mm": 0.1}, "joint_space": {"ranges_deg": [[-90, 90] for _ in range(6)]}},
     "adaptive.joint_space.ranges_deg", "has 7 joints (given 6 ranges; allowed one [low, high] per joint"),
    ({"stop_when": {"joint_space_error_mm": 0.1}, "joint_space": {"ranges_deg": [[-90, 90] for _ in range(6)] + [[-200, 90]]}},
     "adaptive.joint_space.ranges_deg.6", "allowed within [-175, 175] degrees"),
    ({"stop_when": {"joint_space_error_mm": 0.1}, "joint_space": {"ranges_deg": [[-90, 90] for _ in range(6)] + [[10, 10]]}},
     "adaptive.joint_space.ranges_deg.6", "allowed [low, high], low < high"),
    ({"stop_when": {"joint_space_error_mm": 0.1}, "joint_space": {"samples": 3}}, "adaptive.joint_space.samples",
     "allowed [10, 5000]"),
    ({"stop_when": {"interval_deg": -1}}, "adaptive.stop_when.interval_deg", "allowed (0, 1]"),
    ({"stop_when": {"interval_deg": 0.01}, "max_configurations": 0}, "adaptive.max_configurations", "allowed [1, 10000]"),
    ({"stop_when": {"interval_deg": 0.01}, "min_configurations": 20, "max_configurations": 10},
     "adaptive.max_configurations", "allowed ≥ 20"),
    ({"stop_when": {"intervall_deg": 0.01}}, "adaptive.stop_when", "keys interval_deg, workspace_within_pct, held_out_within_pct"),
    ({"max_configurations": 10}, "adaptive.stop_when", "Field required"),
])
def test_bad_adaptive_sections_name_file_line_field_and_what_is_allowed(tmp_path, adaptive, field, allowed):
    path = write(tmp_path, minimal(adaptive=adaptive))
    with pytest.raises(ConfigError) as info:
        load_plan(path)
    text = str(info.value)
    assert f"{path}:" in text and field in text and allowed in text, text
    line = [ln for ln in text.splitlines() if field in ln][0]
    assert int(line.split(":")[1]) > 1  # points into the file, at the adaptive section


def test_min_configurations_beyond_the_plan_is_refused_before_anything_moves(tmp_path):
    from acquire.run.adaptive import stop_rule

    lp = _load(tmp_path, {"stop_when": {"interval_deg": 0.01}, "min_configurations": 50})
    with pytest.raises(ConfigError, match=r"adaptive.min_configurations: more than the plan's 30 configurations"):
        stop_rule(lp, 30)
    lp = _load(tmp_path, {"stop_when": {"interval_deg": 0.01}, "min_configurations": 2})
    with pytest.raises(ConfigError, match=r"fewer than the fit needs"):
        stop_rule(lp, 30)
    rule = stop_rule(_load(tmp_path, {"stop_when": {"interval_deg": 0.01}, "max_configurations": 99}), 30)
    assert rule.max_configurations == 30 and rule.min_configurations >= 12


def test_a_socket_plan_cannot_be_adaptive(tmp_path):
    import yaml

    from tests.acquire.test_plan import PLANS, ROOT

    doc = yaml.safe_load((PLANS / "example-socket.yaml").read_text())
    doc["robot"] = str(ROOT / "fixtures" / "robots" / doc["robot"].split("/")[-1])
    doc.pop("fake", None)
    doc["adaptive"] = {"stop_when": {"interval_deg": 0.01}}
    path = tmp_path / "socket.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(ConfigError, match=r"socket.yaml:\d+:\d+: adaptive: an adaptive order applies to pose plans"):
        load_plan(path)
