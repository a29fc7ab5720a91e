"""``acquire move``: move a robot to one joint target through its real-time commander, safely.

Example::

    acquire move --robot fixtures/robots/kuka_kr6_r900_2.yaml \\
        --commander rsi://0.0.0.0:49152 --to 0,-90,90,0,45,0 --speed 0.1
    acquire move --robot fixtures/robots/kuka_kr6_r900_2.yaml --result result.json \\
        --commander rsi://0.0.0.0:49152 --pose 500,0,600,0,90,0 --tool 0,0,150,0,0,0

``--pose X,Y,Z,A,B,C`` (mm, ZYX Euler degrees; the TCP ``--tool`` in the robot's base frame)
instead of ``--to``: the joint target is the calibrated arm's inverse kinematics (``--result``:
offsets, links, tool, gravity sag; without it the nominal model, said so) in the branch nearest
the measured joints; a pose no branch reaches within the limits is refused before anything moves.

Connects (waits for the controller's packets), shows the link's state and timing (cycle,
jitter, answer latency, measured position), checks the target against the model's limits,
asks for confirmation unless ``--yes``, moves along a jerk-limited synchronised trajectory,
waits until the measured position has settled, prints it and the residual per axis, and (by
default) ends the RSI session with the Stop flag. Settled is not on target: a robot that stopped
short (brakes held, a drive that does not follow) exits 3 with the residual of every axis outside
``--target-tolerance``. Angles on the command line are degrees in the controller's convention.

Exit codes: 0 on target; 1 not confirmed; 2 usage or device error; 3 settled off target.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional
from urllib.parse import urlsplit

import numpy as np
import typer

from calib.robot.model import load_robot_model
from calib.io.yamlfile import ConfigError
from drivers.errors import DriverError
from drivers.protocols import JointLimits
from drivers.registry import load_driver
from drivers.trajectory import motion_time, scaled_limits

#: Default of ``--target-tolerance``: degrees per axis between the settled position and the target.
DEFAULT_TARGET_TOLERANCE_DEG = 0.05
#: Exit code of a move that settled, but not on its target.
EXIT_OFF_TARGET = 3


def _target(text: str, n: int) -> np.ndarray:
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise typer.BadParameter(f"expected {n} comma-separated angles in degrees, given {text!r}", param_hint="--to") from None
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise typer.BadParameter(
            f"expected {n} comma-separated angles in degrees (the robot has {n} axes), given {text!r}",
            param_hint="--to",
        )
    return np.radians(values)


def _fmt(values_rad, names) -> str:
    return "  ".join(f"{a}={v:9.4f}" for a, v in zip(names, np.degrees(values_rad)))


def _off_target(residual_rad, names, tolerance_deg: float) -> str:
    """The axes whose residual (settled − target) exceeds ``tolerance_deg``, as text; '' if none."""
    err = np.degrees(np.asarray(residual_rad, dtype=float))
    return ", ".join(f"{a} {e:+.4f}°" for a, e in zip(names, err) if not abs(e) <= tolerance_deg)


def _link_report(cmd, names) -> str:
    """The commander's link figures (``LinkStats.report``) and the measured position."""
    lines = cmd.link_stats().report()
    lines.append(f"measured (deg): {_fmt(cmd.joint_state().position_rad, names)}")
    return "\n".join(lines)


def move(
    robot: Path = typer.Option(..., "--robot", help="Robot model YAML file (fixtures/robots/...)."),
    commander: str = typer.Option(
        "rsi://0.0.0.0:49152", "--commander", help="Commander URL, e.g. rsi://0.0.0.0:49152?cycle_ms=4."
    ),
    to: Optional[str] = typer.Option(None, "--to", help="Target J1,…,Jn in degrees (controller convention)."),
    pose: Optional[str] = typer.Option(None, "--pose", help="Target TCP pose X,Y,Z,A,B,C (mm, ZYX Euler degrees) in the "
                                                            "robot's base frame, reached with the calibrated model (--result)."),
    result: Optional[Path] = typer.Option(None, "--result", help="--pose: the fit's result.json (the calibrated arm)."),
    tool: Optional[str] = typer.Option(None, "--tool", help="--pose: the TCP in the flange frame X,Y,Z,A,B,C (mm, degrees); "
                                                            "default the flange."),
    entered: str = typer.Option("auto", "--entered", help="--pose: offsets entered in the controller since the measurement "
                                                         "(auto, result, none; see acquire compensate)."),
    speed: float = typer.Option(0.1, "--speed", help="Fraction (0, 1] of the model's speed; acceleration scales with its square."),
    yes: bool = typer.Option(False, "--yes", "-y", help="Do not ask for confirmation."),
    tolerance: float = typer.Option(0.01, "--tolerance", help="Settled when every axis stays within this many degrees."),
    window: float = typer.Option(0.2, "--window", help="… for this many seconds."),
    target_tolerance: float = typer.Option(
        DEFAULT_TARGET_TOLERANCE_DEG, "--target-tolerance",
        help="On target when every settled axis is within this many degrees of the target (else exit 3).",
    ),
    timeout: float = typer.Option(120.0, "--timeout", help="Give up on the move (and on settling) after this many seconds."),
    end_session: bool = typer.Option(
        True, "--end-session/--keep-session",
        help="End the commander's session at the end (RSI: the Stop flag, so the controller's program continues).",
    ),
) -> None:
    """Move the robot to one joint target, safely, and print where it settled."""
    try:
        model = load_robot_model(robot)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--robot") from exc
    limits = JointLimits.from_model(model)
    names = limits.names or tuple(f"J{i + 1}" for i in range(limits.n_axes))
    if (to is None) == (pose is None):
        raise typer.BadParameter("give exactly one target: --to J1,…,Jn (degrees) or --pose X,Y,Z,A,B,C", param_hint="--to/--pose")
    if pose is None and (result is not None or tool is not None):
        raise typer.BadParameter("--result and --tool apply to --pose", param_hint="--result/--tool")
    target = _target(to, limits.n_axes) if to is not None else None
    solver = _pose_solver(model, pose, result, tool, entered) if pose is not None else None
    if not 0 < speed <= 1:
        raise typer.BadParameter(f"must be in (0, 1], given {speed}", param_hint="--speed")
    if tolerance <= 0 or window <= 0 or timeout <= window:
        raise typer.BadParameter(
            f"need tolerance > 0, window > 0 and timeout > window; given {tolerance}, {window}, {timeout}"
        )
    if not target_tolerance > 0:
        raise typer.BadParameter(f"must be > 0 degrees, given {target_tolerance}", param_hint="--target-tolerance")
    scheme = urlsplit(commander).scheme
    try:
        cls = load_driver(scheme)
        cmd = cls.from_url(commander, limits=limits)
    except (ValueError, TypeError, DriverError) as exc:
        raise typer.BadParameter(str(exc), param_hint="--commander") from exc
    try:
        cmd.connect()
        cmd.first_state(15.0)  # the controller streams
        time.sleep(0.5)  # half a second of cycles for the timing figures
        typer.echo(f"robot: {model.name} ({limits.n_axes} axes), commander {commander}")
        typer.echo(_link_report(cmd, names))
        start = cmd.joint_state().position_rad
        if solver is not None:
            target = solver(start)
        checked = cmd.check_target(target, speed)  # refuse before asking
        v, a, j = scaled_limits(limits.max_velocity_rad_s, limits.max_acceleration_rad_s2, speed)
        duration = motion_time(start, checked, v, a, j)
        typer.echo(f"target   (deg): {_fmt(checked, names)}")
        typer.echo(f"move: speed {speed:g}, {duration:.2f} s, largest axis motion {np.degrees(np.abs(checked - start)).max():.3f}°")
        if not yes and not typer.confirm("Move the robot now?", default=False):
            typer.echo("not moved")
            raise typer.Exit(1)
        cmd.move_to(checked, speed, timeout)
        final = cmd.wait_settled(math.radians(tolerance), window, timeout)
        typer.echo(f"settled  (deg): {_fmt(final.position_rad, names)}")
        residual = final.position_rad - checked
        typer.echo(f"error    (deg): {_fmt(residual, names)}")
        st = cmd.link_stats()
        typer.echo(f"link after the move: late answers {st.late_answers}, missing cycles {st.gaps}"
                   + ("" if st.delay is None else f", Delay {st.delay}"))
        if end_session:
            cmd.stop()
        off = _off_target(residual, names, target_tolerance)
        if off:
            typer.echo(f"error: settled off target: {off} (allowed ±{target_tolerance:g}° per axis, "
                       "--target-tolerance); the robot stopped short: check drives, brakes and the "
                       "controller's messages before moving again", err=True)
            raise typer.Exit(EXIT_OFF_TARGET)
        typer.echo(f"on target: every axis within ±{target_tolerance:g}°")
    except DriverError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    finally:
        cmd.close()


def _pose_solver(model, pose_text: str, result: Optional[Path], tool_text: Optional[str], entered: str):
    """A function current joints (n,) rad → the joint target (n,) rad that puts the calibrated arm's
    TCP on ``--pose``: the branch nearest the current joints. Exits 2 (before anything moves) when
    no branch reaches the pose within the limits."""
    from acquire.commands.compensate import parse_pose  # noqa: PLC0415
    from acquire.commands.model import calibrated_arm  # noqa: PLC0415
    from calib.ik.compensation import Compensator, pose_error  # noqa: PLC0415

    target = parse_pose(pose_text, "--pose")
    tool = parse_pose(tool_text, "--tool") if tool_text is not None else np.eye(4)
    arm = calibrated_arm(model, result, entered)
    if result is None:
        typer.echo("no --result: the pose is reached with the nominal model (uncalibrated)")
    comp = Compensator(model, arm, tool)
    rows, why = comp.calibrated_solutions(target)
    if not len(rows):
        raise typer.BadParameter(f"{pose_text}: refused, no configuration reaches it within the joint limits ({why})",
                                 param_hint="--pose")

    def solve(current: np.ndarray) -> np.ndarray:
        best = rows[int(np.argmin(np.max(np.abs(rows - current), axis=1)))]
        dp, dw = pose_error(target, comp.true_pose(best))
        typer.echo(f"pose {pose_text}: {len(rows)} configuration(s) reach it; nearest the measured joints chosen "
                   f"(calibrated arm on the pose within {np.linalg.norm(dp):.2g} mm, {np.degrees(np.linalg.norm(dw)):.2g}°)")
        return best

    return solve


def register(app: typer.Typer) -> None:
    """Add the ``move`` sub-command to ``app``."""
    app.command("move")(move)
