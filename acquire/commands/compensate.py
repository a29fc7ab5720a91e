"""``acquire compensate``: pre-correct Cartesian targets so the controller's nominal arm lands where
the calibrated model says the target is.

Example::

    acquire compensate program.dat --robot fixtures/robots/kuka_kr6_r900_2.yaml --result result.json \\
        --tool 0,0,150,0,0,0 -o program_compensated.dat

For every target the calibrated arm's inverse kinematics (offsets, links, tool, gravity sag —
everything in ``--result``) gives the controller angles at which the real TCP is on the target;
the corrected target is what the controller's nominal kinematics calls those angles
(``calib.ik.compensation``). Formats (``calib.io.targets``): a CSV of poses (``name,x,y,z,a,b,c``
[``,q1…qn``]), a KUKA ``.dat`` (E6POS/POS declarations; S and T kept) and an ABB RAPID module
(robtargets; confdata and external axes kept); everything else in the file is written back byte
for byte. The configuration each target is reached in is the one the file names (KUKA: T's axis
signs; ABB: cf1, cf4, cf6; CSV: the q columns) or, where that leaves a choice, the one nearest the
previous target's. The written file is read back and every target driven through the controller's
nominal inverse kinematics onto the calibrated arm: exit 1 if one misses. Bad input exits 2 with
file, line and field, and nothing is written.

Targets are TCP poses in the robot's base frame (KUKA: BASE = $ROBROOT, ABB: wobj0) for the tool
``--tool`` (the controller's TCP in the flange frame); the offsets entered since the measurement
are taken from the result's record (``--entered``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

#: Read-back tolerance: how far a compensated target, as written (rounded), may land from its target.
READBACK_TOLERANCE_MM = 1e-3
READBACK_TOLERANCE_DEG = 1e-4


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def parse_pose(text: str, option: str):
    """``X,Y,Z,A,B,C`` (mm, ZYX Euler degrees) → (4, 4) mm."""
    import numpy as np  # noqa: PLC0415

    from calib.robot.transforms import pose_to_matrix  # noqa: PLC0415

    try:
        v = [float(p) for p in text.split(",")]
    except ValueError:
        raise typer.BadParameter(f"expected X,Y,Z,A,B,C (mm, degrees), given {text!r}", param_hint=option) from None
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise typer.BadParameter(f"expected 6 finite numbers X,Y,Z,A,B,C (mm, degrees), given {text!r}", param_hint=option)
    return pose_to_matrix(np.array(v[:3]), np.radians(v[3:]))


def target_pose(fmt: str, values):
    """The (4, 4) pose of a target's numbers (``calib.io.targets.Target.values``)."""
    import numpy as np  # noqa: PLC0415

    from calib.robot.transforms import homogeneous, pose_to_matrix, quat_to_matrix  # noqa: PLC0415

    if fmt == "rapid":
        return homogeneous(quat_to_matrix(np.array(values[3:])), np.array(values[:3]))
    return pose_to_matrix(np.array(values[:3]), np.radians(values[3:]))


def pose_values(fmt: str, pose, like):
    """A pose's numbers in the format's layout; a quaternion keeps the sign of ``like``'s."""
    import numpy as np  # noqa: PLC0415

    from calib.robot.transforms import matrix_to_euler_zyx, matrix_to_quat  # noqa: PLC0415

    xyz = tuple(float(v) for v in pose[:3, 3])
    if fmt == "rapid":
        q = matrix_to_quat(pose[:3, :3])
        if float(np.dot(q, like[3:])) < 0:
            q = -q
        return xyz + tuple(float(v) for v in q)
    abc = np.degrees(matrix_to_euler_zyx(pose[:3, :3]))
    return xyz + tuple(float(v) for v in abc)


def _turn_bits(q) -> int:
    """KUKA Turn: bit i set when axis i+1 is negative."""
    return sum(1 << i for i, v in enumerate(q) if v < 0)


def _quadrants(q) -> list[int]:
    """ABB cf1, cf4, cf6: ⌊angle / 90°⌋ of axes 1, 4, 6."""
    return [math.floor(math.degrees(q[i]) / 90.0) for i in (0, 3, 5)]


def configuration_filter(fmt: str, target, n: int):
    """(predicate on controller angles, what it asks for) from what the file says about the
    configuration; None where it says nothing usable."""
    import numpy as np  # noqa: PLC0415

    if fmt == "kuka" and "T" in target.config:
        t = target.config["T"]
        return (lambda q: _turn_bits(q) == t), f"T {t} (axis signs)"
    if fmt == "rapid" and n >= 6:
        cf = target.config["cf"][:3]
        return (lambda q: _quadrants(q) == cf), f"cf1, cf4, cf6 = {cf}"
    if fmt == "csv" and "joints_deg" in target.config:
        hint = np.radians(target.config["joints_deg"])
        if hint.size != n:
            return None
        return (lambda q: bool(np.max(np.abs(q - hint)) < math.radians(1.0))), "the q columns (within 1°)"
    return None


def _predicted(result: Path) -> str:
    """The fit's own held-out figures for the full model (what compensation delivers) and the robot
    as found, where the result has them (``entered.heldout``); '' otherwise."""
    from calib.robot.calibrated import read_result  # noqa: PLC0415

    held = ((read_result(result).get("entered") or {}).get("heldout") or {})
    full, found = held.get("full_model"), held.get("as_found")
    if not isinstance(full, dict) or not isinstance(found, dict) or "rms_mm" not in full or "rms_mm" not in found:
        return ""
    return (f"predicted by the fit, held out ({held.get('scored_on', '?')}): the compensated robot lands within "
            f"{full['rms_mm']:.4f} mm rms (as found: {found['rms_mm']:.4f} mm)")


def compensate(
    targets: Path = typer.Argument(..., metavar="TARGETS", help="Targets: .csv, KUKA .dat or ABB .mod/.modx/.prg."),
    robot: Path = typer.Option(..., "--robot", help="The nominal robot model YAML the fit used (the controller's kinematics)."),
    result: Path = typer.Option(..., "--result", help="The fit's result.json (the calibrated model)."),
    output: Path = typer.Option(..., "-o", "--output", help="Write the compensated targets here (same format)."),
    fmt: str = typer.Option("auto", "--format", help="auto (by suffix), csv, kuka or rapid."),
    tool: Optional[str] = typer.Option(None, "--tool", help="The controller's TCP in the flange frame X,Y,Z,A,B,C (mm, "
                                                            "ZYX degrees); default the flange."),
    entered: str = typer.Option("auto", "--entered", help="Offsets entered in the controller since the measurement: auto "
                                                          "(the offsets the result's 'entered' block says to enter, if any; else none), result, none."),
    near: Optional[str] = typer.Option(None, "--near", help="J1,…,Jn degrees: where the first target's configuration is "
                                                            "chosen from when the file leaves a choice (default: all zero)."),
    joint_targets: Optional[Path] = typer.Option(None, "--joint-targets", help="Also write the joint targets (controller "
                                                                               "angles, degrees) as CSV here."),
) -> None:
    """Pre-correct Cartesian targets so the controller's nominal arm lands where the calibrated model says."""
    import numpy as np  # noqa: PLC0415

    from acquire.commands.model import calibrated_arm  # noqa: PLC0415
    from calib.ik.compensation import CompensationError, Compensator, pose_error  # noqa: PLC0415
    from calib.io.targets import TargetFileError, read_targets, target_format, write_csv, write_patched  # noqa: PLC0415
    from calib.io.yamlfile import ConfigError  # noqa: PLC0415
    from calib.robot.model import load_robot_model  # noqa: PLC0415

    tool_pose = parse_pose(tool, "--tool") if tool is not None else np.eye(4)
    try:
        model = load_robot_model(robot)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--robot") from exc
    previous = np.zeros(model.n_joints)
    if near is not None:
        try:
            previous = np.radians([float(v) for v in near.split(",")])
        except ValueError:
            raise typer.BadParameter(f"expected {model.n_joints} angles in degrees, given {near!r}", param_hint="--near") from None
        if previous.size != model.n_joints:
            raise typer.BadParameter(f"expected {model.n_joints} angles in degrees, given {near!r}", param_hint="--near")
    try:
        out_fmt = target_format(output, fmt)
        tf = read_targets(targets, fmt)
    except TargetFileError as exc:
        _fail(str(exc))
    if out_fmt != tf.format:
        _fail(f"{output}: the output is written in the input's format ({tf.format}); give it a matching suffix")
    if model.n_joints != 6 and tf.format != "csv":
        _fail(f"{targets}: {model.name} has {model.n_joints} axes; {tf.format} targets are written here for 6-axis arms — "
              "give the targets as CSV (a 7-axis arm's corrected pose comes with the arm angle it holds only at)")
    arm = calibrated_arm(model, result, entered)
    comp = Compensator(model, arm, tool_pose)
    done, errors = [], []
    for t in tf.targets:
        where = f"{targets}:{t.line}: {t.name}"
        pose = target_pose(tf.format, t.values)
        sols = comp.controller_solutions(pose)
        if len(sols) == 0:
            errors.append(f"{where}: the controller cannot reach it ({sols.status}: {sols.message})")
            continue
        rows = sols.q
        wanted = configuration_filter(tf.format, t, model.n_joints)
        if wanted is not None:
            keep, asked = wanted
            rows = rows[[keep(q) for q in rows]]
            if len(rows) == 0:
                errors.append(f"{where}: no solution of the controller's kinematics has {asked}")
                continue
        q_nom = rows[int(np.argmin(np.max(np.abs(rows - previous), axis=1)))]
        try:
            c = comp.compensate(pose, q_nom)
        except CompensationError as exc:
            errors.append(f"{where}: {exc}")
            continue
        if wanted is not None and not wanted[0](c.joints):
            errors.append(f"{where}: the compensated joints no longer have {wanted[1]} (an axis at its boundary): "
                          "re-teach the target a little away from it")
            continue
        previous = c.joints
        done.append((t, pose, c))
    if errors:
        for e in errors:
            typer.echo(f"error: {e}", err=True)
        _fail(f"{len(errors)} of {len(tf.targets)} targets cannot be compensated; nothing written")
    new = {t.name: pose_values(tf.format, c.corrected, t.values) for t, _, c in done}
    try:
        if tf.format == "csv":
            write_csv(output, [(t.name, new[t.name], np.degrees(c.joints).tolist(), c.shift_mm, c.arm_angle) for t, _, c in done],
                  model.axis_names)
        else:
            write_patched(tf, new, output)
    except TargetFileError as exc:
        _fail(str(exc))
    if joint_targets is not None:
        write_csv(joint_targets, [(t.name, pose_values("csv", c.corrected, None), np.degrees(c.joints).tolist(), c.shift_mm,
                                   c.arm_angle) for t, _, c in done], model.axis_names)
    # Read back what was written and drive it through the controller onto the calibrated arm.
    back = {t.name: t for t in read_targets(output, tf.format).targets}
    worst_mm = worst_deg = 0.0
    before = []
    typer.echo(f"{'target':<16}{'shift (mm)':>11}{'turn (°)':>10}{'uncompensated miss (mm)':>25}")
    for t, pose, c in done:
        landed = comp.true_pose(c.nominal_joints)
        miss = float(np.linalg.norm(pose_error(pose, landed)[0]))
        before.append(miss)
        typer.echo(f"{t.name:<16}{c.shift_mm:11.4f}{c.shift_deg:10.5f}{miss:25.4f}")
        written = target_pose(tf.format, back[t.name].values)
        sols = comp.controller_solutions(written, c.arm_angle).q
        q = sols[int(np.argmin(np.max(np.abs(sols - c.joints), axis=1)))] if len(sols) else c.joints
        dp, dw = pose_error(pose, comp.true_pose(q))
        worst_mm = max(worst_mm, float(np.linalg.norm(dp)))
        worst_deg = max(worst_deg, float(np.degrees(np.linalg.norm(dw))))
    typer.echo(f"{len(done)} targets: the calibrated arm misses them by {np.mean(before):.4f} mm on average "
               f"(worst {np.max(before):.4f}) uncompensated")
    predicted = _predicted(result)
    if predicted:
        typer.echo(predicted)
    ok = worst_mm <= READBACK_TOLERANCE_MM and worst_deg <= READBACK_TOLERANCE_DEG
    typer.echo(f"read back {output}: through the controller's nominal kinematics the calibrated arm lands within "
               f"{worst_mm:.2g} mm, {worst_deg:.2g}° of every target ({'ok' if ok else 'FAILED'}; tolerance "
               f"{READBACK_TOLERANCE_MM:g} mm, {READBACK_TOLERANCE_DEG:g}°)")
    if not ok:
        _fail(f"{output} does not land on its targets", 1)
    typer.echo(f"wrote {output}" + (f" and {joint_targets}" if joint_targets is not None else ""))


def register(app: typer.Typer) -> None:
    """Add the ``compensate`` sub-command to ``app``."""
    app.command("compensate")(compensate)
