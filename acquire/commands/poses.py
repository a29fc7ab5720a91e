"""``acquire poses``: plan the remastering poses and every IK configuration of each.

Example::

    acquire poses --robot fixtures/robots/kuka_iiwa14_r820.yaml --sensor-origin 1500,0,500 \\
        -n 60 --seed 1 --radius 200,500 --height 400,800 --angle 0,360 --roll 0,360 -o configs.csv

Prints the candidate count, the valid poses (flange xyz in mm, ZYX Euler A, B, C in degrees),
the configurations (degrees, controller convention) and the dropped poses with their reasons;
with ``-o`` writes the configurations file described in ``calib.plan.poses``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np
import typer

from calib.io.yamlfile import ConfigError

if TYPE_CHECKING:
    from calib.plan.poses import PosePlan


def _numbers(text: str, count: int, option: str, what: str) -> list[float]:
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise typer.BadParameter(f"expected {what}, given {text!r}", param_hint=option) from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise typer.BadParameter(f"expected {what}, given {text!r}", param_hint=option)
    return values


def _range(text: str, option: str, unit: str) -> tuple[float, float]:
    lo, hi = _numbers(text, 2, option, f"LOW,HIGH in {unit} (two numbers)")
    if lo > hi:
        raise typer.BadParameter(f"LOW must not exceed HIGH, given {text!r}", param_hint=option)
    return lo, hi


def format_plan(plan: PosePlan) -> str:
    """Human-readable report of ``plan``: counts, valid poses, configurations, dropped poses."""
    c = plan.candidates
    xyz, zyx = c.xyz_mm, np.degrees(c.zyx_rad)
    lines = [
        f"robot: {plan.robot}",
        f"sensor origin (mm, robot base): {', '.join(f'{v:.1f}' for v in c.sensor_origin_mm)}",
        f"seed: {c.seed}",
        f"candidate poses: {c.n}",
        f"valid poses: {len(plan.valid)}",
        f"configurations: {len(plan.configurations)}",
        f"dropped poses: {len(plan.dropped)}",
        "",
        "valid poses (flange in robot base; x y z mm, A B C = ZYX Euler deg):",
        f"{'pose':>5} {'x':>9} {'y':>9} {'z':>9} {'A':>8} {'B':>8} {'C':>8} {'configs':>7}",
    ]
    per_pose: dict[int, int] = {}
    for cfg in plan.configurations:
        per_pose[cfg.pose] = per_pose.get(cfg.pose, 0) + 1
    for k in plan.valid:
        lines.append(
            f"{k:>5} {xyz[k, 0]:9.1f} {xyz[k, 1]:9.1f} {xyz[k, 2]:9.1f} "
            f"{zyx[k, 0]:8.2f} {zyx[k, 1]:8.2f} {zyx[k, 2]:8.2f} {per_pose.get(k, 0):>7}"
        )
    lines += ["", "configurations (deg):", f"{'config':>6} {'pose':>5} {'branch':<30} " + " ".join(f"{a:>8}" for a in plan.axis_names)]
    for cfg in plan.configurations:
        lines.append(f"{cfg.config:>6} {cfg.pose:>5} {cfg.branch:<30} " + " ".join(f"{v:8.2f}" for v in np.degrees(cfg.q)))
    lines += ["", "dropped poses:"]
    if not plan.dropped:
        lines.append("  (none)")
    for d in plan.dropped:
        lines.append(f"  pose {d.pose}: {d.reason}")
    return "\n".join(lines)


def poses(
    robot: Path = typer.Option(..., "--robot", help="Robot model YAML file (fixtures/robots/...)."),
    sensor_origin: str = typer.Option(
        ..., "--sensor-origin", help="Sensor origin X,Y,Z in mm in the robot base frame; the flange z-axis aims at it."
    ),
    n: int = typer.Option(60, "-n", "--candidates", help="Number of Latin-hypercube candidate poses."),
    seed: int = typer.Option(1, "--seed", help="Random seed (same seed, same plan)."),
    radius: str = typer.Option("200,500", "--radius", help="Radius range LOW,HIGH in mm (base X-Y plane)."),
    height: str = typer.Option("400,800", "--height", help="Height range LOW,HIGH in mm (base z)."),
    angle: str = typer.Option("0,360", "--angle", help="Base angle range LOW,HIGH in degrees about base z."),
    roll: str = typer.Option("0,360", "--roll", help="Tool roll range LOW,HIGH in degrees about the aimed z-axis."),
    arm_angle: Optional[list[float]] = typer.Option(
        None, "--arm-angle", help="7-axis arms: also solve at this arm angle (deg); repeat for several."
    ),
    min_solutions: int = typer.Option(2, "--min-solutions", help="Drop poses with fewer feasible IK solutions."),
    margin: float = typer.Option(0.0, "--margin", help="Keep configurations this far (deg) inside the joint limits."),
    whole_turn_twins: bool = typer.Option(
        False, "--whole-turn-twins", help="Also plan configurations that differ only by whole turns of a joint."
    ),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Write the configurations file (CSV) here."),
) -> None:
    """Plan the paper's poses: Latin hypercube aimed at the sensor, every IK solution of each."""
    from calib.robot.model import load_robot_model  # scipy.stats (the Latin hypercube) loads only when planning
    from calib.plan.poses import PoseRanges, plan_poses, write_configurations

    try:
        model = load_robot_model(robot)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--robot") from exc
    origin = _numbers(sensor_origin, 3, "--sensor-origin", "X,Y,Z in mm (three numbers)")
    if n < 1:
        raise typer.BadParameter(f"must be at least 1, given {n}", param_hint="-n")
    if min_solutions < 1:
        raise typer.BadParameter(f"must be at least 1, given {min_solutions}", param_hint="--min-solutions")
    if margin < 0:
        raise typer.BadParameter(f"must be ≥ 0 degrees, given {margin}", param_hint="--margin")
    r_lo, r_hi = _range(radius, "--radius", "mm")
    if r_lo < 0:
        raise typer.BadParameter(f"a radius must be ≥ 0, given {radius!r}", param_hint="--radius")
    ranges = PoseRanges(
        radius_mm=(r_lo, r_hi),
        height_mm=_range(height, "--height", "mm"),
        angle_rad=tuple(math.radians(v) for v in _range(angle, "--angle", "degrees")),
        roll_rad=tuple(math.radians(v) for v in _range(roll, "--roll", "degrees")),
    )
    extra = [math.radians(a) for a in (arm_angle or [])]
    if extra and model.n_joints != 7:
        raise typer.BadParameter(f"arm angles apply to 7-axis arms; {model.name} has {model.n_joints} axes", param_hint="--arm-angle")
    try:
        plan = plan_poses(
            model,
            origin,
            n=n,
            seed=seed,
            ranges=ranges,
            extra_arm_angles_rad=extra,
            min_solutions=min_solutions,
            limit_margin_rad=math.radians(margin),
            whole_turn_twins=whole_turn_twins,
        )
    except ValueError as exc:  # e.g. a sampled position on the sensor origin, a model the IK cannot solve
        raise typer.BadParameter(str(exc)) from exc
    typer.echo(format_plan(plan))
    if output is not None:
        try:
            write_configurations(plan, output)
        except ConfigError as exc:
            raise typer.BadParameter(str(exc), param_hint="-o") from exc
        typer.echo(f"\nwrote {len(plan.configurations)} configurations to {output}")


def register(app: typer.Typer) -> None:
    """Add the ``poses`` sub-command to ``app``."""
    app.command("poses")(poses)
