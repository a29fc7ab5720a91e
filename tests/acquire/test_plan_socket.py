"""The plan's socket section: validated with file:line errors; resolved into approach
configurations that put the nominal ball at each socket, seeded, favouring different gravity
loads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from acquire.plan.schema import load_plan, resolve_configurations, resolve_plan
from calib.robot.kinematics import Chain
from calib.io.yamlfile import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def plan_file(tmp_path: Path, mutate=None) -> Path:
    doc = yaml.safe_load((ROOT / "fixtures" / "plans" / "example-socket.yaml").read_text())
    doc["robot"] = str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    doc["fake"]["sim_config"] = str(ROOT / "fixtures" / "sim" / "socket.yaml")
    doc["output"]["folder"] = str(tmp_path / "runs")
    doc["socket"]["configurations"] = 4
    if mutate:
        mutate(doc)
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_socket_plan_resolves_to_approaches_that_put_the_nominal_ball_at_each_socket(tmp_path):
    lp = load_plan(plan_file(tmp_path))
    rp = resolve_plan(lp)
    assert rp.source == "socket"
    assert rp.pose_groups == ["front/0", "front/1", "left_back/0", "left_back/1", "raised_left/0", "raised_left/1"]
    chain = Chain(lp.model)
    ball = np.array(lp.plan.socket.ball_mm)
    where = {f"{p.name}/{s.name}": np.array(s.xyz_mm) for p in lp.plan.socket.placements for s in p.sockets}
    for c in rp.configs:
        assert c.config_id.startswith(f"{c.socket[0]}-s{c.socket[1]}-k")
        flange = chain.fk(c.q_rad)
        np.testing.assert_allclose(flange[:3, :3] @ ball + flange[:3, 3], where[c.pose], atol=1e-6)
        assert lp.model.within_limits(c.q_rad, lp.commander_margin_rad)
    # seeded: the same plan gives the same configurations
    again = resolve_configurations(lp)
    assert [c.config_id for c in again] == [c.config_id for c in rp.configs]
    assert all(np.array_equal(a.q_rad, b.q_rad) for a, b in zip(again, rp.configs))


def test_approaches_spread_the_gravity_load(tmp_path):
    """The configurations kept load the joints more differently than the same number of
    candidates taken at random (what lets a fit tell sag from an offset)."""
    from calib.robot.gravity import gravity_torques
    from calib.robot.model import load_robot_model
    from calib.plan.socket_poses import socket_approaches

    model = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
    chain = Chain(model)
    kept = np.array([a.q for a in socket_approaches(model, [600, 0, 150], [0, 0, 60], 6, seed=2)])
    pool = np.array([a.q for a in socket_approaches(model, [600, 0, 150], [0, 0, 60], 40, seed=2, candidates=48)])
    spread_kept = gravity_torques(chain, kept).std(axis=0).sum()
    rng = np.random.default_rng(0)
    spread_random = np.mean([gravity_torques(chain, pool[rng.choice(len(pool), 6, replace=False)]).std(axis=0).sum()
                             for _ in range(50)])
    assert spread_kept > spread_random


def _set(path, value):
    def mutate(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return mutate


@pytest.mark.parametrize("mutate, fragment", [
    (lambda d: d.__setitem__("poses", {"joints": [[0, 20, 0, -90, 0, -30, 0]]}), "socket: a plan visits poses or sockets"),
    (lambda d: d["sensors"][0].__setitem__("markers", {"sir": "x"}), "sensors.0.markers: a socket sensor records joint angles"),
    (lambda d: d.pop("socket"), "sensors.0.driver: a socket sensor needs a socket section"),
    (_set(["socket", "placements", 0, "sockets", 1, "xyz_mm"], [600, 150, 150]),
     "socket.placements.0.sockets.1.xyz_mm: 150 mm from socket '0', but distance_mm is 50"),
    (_set(["socket", "configurations"], 2), "socket.configurations: "),
    (_set(["sensors", 0, "url"], "socket://127.0.0.1:1"), "the socket driver takes a operator:// URL"),
    (lambda d: d["sensors"].append({"name": "mocap", "driver": "natnet", "url": "natnet://127.0.0.1",
                                     "markers": {"sir": "ms:tool:sir"}, "noise_mm": 0.03}),
     "sensors: a socket plan records with exactly one socket sensor"),
    (lambda d: (d["commander"].update(driver="rsi", url="rsi://127.0.0.1:49152"),
                d["sensors"][0].update(url="operator://none?input=MediaFlange.UserButton")),
     "sensors.0.url: input=MediaFlange.UserButton confirms with a controller input, which the 'rsi' commander does not read"),
])
def test_bad_socket_plans_name_file_line_and_field(tmp_path, mutate, fragment):
    path = plan_file(tmp_path, mutate)
    with pytest.raises(ConfigError) as err:
        load_plan(path)
    text = str(err.value)
    assert fragment in text
    line = next(l for l in text.splitlines() if fragment in l)
    assert line.startswith(f"{path}:") and line.split(":")[1].isdigit()


def test_unreachable_socket_points_at_its_line(tmp_path):
    far = _set(["socket", "placements", 0, "sockets", 0, "xyz_mm"], [2500, 0, 150])
    lp = load_plan(plan_file(tmp_path, lambda d: (far(d), _set(["socket", "distance_mm"], None)(d))))
    with pytest.raises(ConfigError, match=r"plan.yaml:\d+:\d+: socket.placements.0.sockets.0.xyz_mm: only 0 of"):
        resolve_configurations(lp)
