"""``acquire model``: robot models in and out of URDF.

Examples::

    acquire model import kr6r900_2.urdf -o kr6.yaml
    acquire model import iiwa14.urdf --tip iiwa_link_ee_kuka --axes A1,A2,A3,A4,A5,A6,A7 \\
        --controller sunrise -o iiwa14.yaml
    acquire model export fixtures/robots/kuka_iiwa14_r820.yaml --result result.json -o iiwa14_calibrated.urdf
    acquire model export fixtures/robots/ur10.yaml --result result.json --format ur -o ur10_calibration.yaml

``import`` writes our model YAML (mm, degrees; DH or M-DH as the axes require) from the URDF's
serial chain and proves it: the model's forward kinematics against the URDF's own (yourdfpy) on
random configurations inside the limits; it refuses to write a model that disagrees.
``export`` writes the model — with everything a fit's result found applied when ``--result`` is
given: offsets, link parameters, tool, and the joint compliances (gravity sag) as data beside it —
as a URDF (``--format urdf``), UR's kinematics parameters YAML (``--format ur``) or our model YAML
(``--format model``), reads the file back (URDF through yourdfpy and through ``import``; UR's file
built as ur_description builds its chain) and checks the forward kinematics against the
calibrated model, the sag included. Exit status 1 when a check fails, 2 on bad input. See
docs/export-and-compensation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

#: FK agreement a conversion must reach: positions in mm, rotations in degrees.
FK_TOLERANCE_MM = 1e-6
FK_TOLERANCE_DEG = 1e-6

model_app = typer.Typer(no_args_is_help=True, add_completion=False,
                        help="Robot models in and out of URDF (import a vendor URDF, export a calibrated model).")


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _table(model) -> str:
    w = max(6, *(len(j.axis) + 2 for j in model.joints))
    lines = [f"{'axis':<{w}}{'theta':>9}{'d':>10}{'a':>10}{'alpha':>9}{'beta':>9}{'sign':>5}  limits (deg)   speed (deg/s)"]
    for j in model.joints:
        lines.append(f"{j.axis:<{w}}{j.theta:9.3f}{j.d:10.3f}{j.a:10.3f}{j.alpha:9.3f}{j.beta:9.4f}{j.sign:5d}  "
                     f"[{j.limits[0]:g}, {j.limits[1]:g}]  {j.max_speed:g}")
    return "\n".join(lines)


def _check(label: str, worst: tuple[float, float], n: int) -> bool:
    ok = worst[0] <= FK_TOLERANCE_MM and worst[1] <= FK_TOLERANCE_DEG
    typer.echo(f"FK check {label}, {n} configurations: worst {worst[0]:.3g} mm, {worst[1]:.3g}° "
               f"({'ok' if ok else 'FAILED'}; tolerance {FK_TOLERANCE_MM:g} mm, {FK_TOLERANCE_DEG:g}°)")
    return ok


def import_model(
    urdf: Path = typer.Argument(..., metavar="URDF", help="URDF file (plain URDF; run xacro first for .xacro)."),
    output: Path = typer.Option(..., "-o", "--output", help="Write the robot model YAML here."),
    tip: Optional[str] = typer.Option(None, "--tip", help="Flange link (default: the end link reached through the most joints)."),
    base: Optional[str] = typer.Option(None, "--base", help="Base link (default: the URDF's root link)."),
    convention: str = typer.Option("auto", "--convention", help="dh, mdh (Hayati β for near-parallel axes) or auto."),
    axes: Optional[str] = typer.Option(None, "--axes", help="Controller names of the axes, e.g. A1,A2,A3,A4,A5,A6 (default: URDF joint names)."),
    controller: str = typer.Option("generic", "--controller", help="kss, sunrise, cs8 or generic."),
    tool: Optional[Path] = typer.Option(None, "--tool", help="Take the tool (markers, mass) from this robot model YAML."),
    checks: int = typer.Option(200, "--check", help="Random configurations for the FK check against the URDF."),
) -> None:
    """Import a URDF's serial chain as a robot model YAML, checked against the URDF's own FK."""
    from calib.robot.kinematics import Chain  # noqa: PLC0415
    from calib.robot.model import load_robot_model, model_yaml, robot_model_from_dict  # noqa: PLC0415
    from calib.robot.urdf import UrdfError, fk_difference, import_urdf, load_urdf, random_configurations, urdf_fk  # noqa: PLC0415
    from calib.io.yamlfile import ConfigError  # noqa: PLC0415

    if convention not in ("dh", "mdh", "auto"):
        raise typer.BadParameter(f"expected dh, mdh or auto, given {convention!r}", param_hint="--convention")
    if controller not in ("kss", "sunrise", "cs8", "generic"):
        raise typer.BadParameter(f"expected kss, sunrise, cs8 or generic, given {controller!r}", param_hint="--controller")
    if checks < 1:
        raise typer.BadParameter(f"must be at least 1, given {checks}", param_hint="--check")
    names = [a.strip() for a in axes.split(",")] if axes else None
    if names is not None and (not all(names) or len(set(names)) != len(names)):
        raise typer.BadParameter(f"expected distinct comma-separated names, given {axes!r}", param_hint="--axes")
    tool_layout = None
    if tool is not None:
        try:
            tool_layout = load_robot_model(tool).tool.model_dump(mode="json")
        except ConfigError as exc:
            raise typer.BadParameter(str(exc), param_hint="--tool") from exc
    try:
        imp = import_urdf(urdf, tip=tip, base=base, convention=convention, axes=names, tool=tool_layout)
    except UrdfError as exc:
        _fail(str(exc))
    model = robot_model_from_dict({**imp.model.model_dump(mode="json"), "controller": controller})
    for note in imp.notes:
        typer.echo(note)
    typer.echo(_table(model))
    q = random_configurations(model, checks, seed=0)
    reference = urdf_fk(load_urdf(urdf), imp.joints, imp.base, imp.tip, q)
    worst = fk_difference(Chain(model).fk(q), reference)
    if not _check(f"against the URDF ({imp.base} → {imp.tip}, yourdfpy)", worst, checks):
        _fail("the converted model does not reproduce the URDF; nothing written (please report this URDF)", 1)
    text = model_yaml(model, f"Imported by `acquire model import` from {Path(urdf).name} ({imp.base} → {imp.tip}).\n"
                             f"FK equals the URDF's (yourdfpy) within {worst[0]:.2g} mm / {worst[1]:.2g}° on {checks} "
                             "random configurations.\n" + "\n".join(imp.notes))
    output.write_text(text, encoding="utf-8")
    written = load_robot_model(output)  # what a reader of the file gets, rounding included
    if not _check("of the written file against the URDF", fk_difference(Chain(written).fk(q), reference), checks):
        _fail(f"{output} does not read back to the same model", 1)
    typer.echo(f"wrote {output}")


#: Export formats: name → what is written.
EXPORT_FORMATS = {
    "urdf": "URDF for ROS / MoveIt (joint values = the controller's angles)",
    "ur": "Universal Robots' kinematics parameters YAML (ur_description's kinematics_parameters_file)",
    "model": "our robot model YAML (for `acquire move`, `acquire compensate`, another fit)",
}


def _export_format(fmt: str, output: Path) -> str:
    if fmt == "auto":
        if output.suffix.lower() == ".urdf":
            return "urdf"
        raise typer.BadParameter(f"cannot tell the format from {output.name!r}: give --format "
                                 + " | ".join(f"{k} ({v})" for k, v in EXPORT_FORMATS.items()), param_hint="--format")
    if fmt not in EXPORT_FORMATS:
        raise typer.BadParameter(f"expected auto, {', '.join(EXPORT_FORMATS)}; given {fmt!r}", param_hint="--format")
    return fmt


def entered_shift(doc: dict, model, entered: str, where: str):
    """The offsets (n,) rad entered in the controller since the measurement, by ``--entered``:
    ``auto`` the result's ``entered`` block (the offsets ``acquire fit`` says to enter, ``enter:
    true``) if it has one, else none; ``result`` that block (required); ``none`` nothing entered.
    Returns (offsets, sentence saying which)."""
    import numpy as np  # noqa: PLC0415

    from calib.robot.calibrated import entered_offsets  # noqa: PLC0415

    if entered not in ("auto", "result", "none"):
        raise typer.BadParameter(f"expected auto, result or none, given {entered!r}", param_hint="--entered")
    recorded = None if entered == "none" else entered_offsets(doc, model, where)
    if entered == "result" and recorded is None:
        raise typer.BadParameter(f"{where} records no entered offsets ('entered'); give --entered none if nothing was "
                                 "entered since the measurement", param_hint="--entered")
    if recorded is None or not np.any(recorded):
        why = "--entered none" if entered == "none" else f"{where} records none"
        return np.zeros(model.n_joints), f"controller angles as measured: no offsets entered since ({why})"
    values = ", ".join(f"{ax} {np.degrees(v):+.4f}°" for ax, v in zip(model.axis_names, recorded) if v)
    return recorded, (f"controller angles after entering {values} (the offsets {where} says to enter, taken as entered"
                      + (": give --entered none if they are not on the controller)" if entered == "auto" else ")"))


def calibrated_arm(model, result: Optional[Path], entered: str = "auto", echo=typer.echo):
    """The calibrated arm (``calib.robot.calibrated.Calibrated``) of ``model`` with ``result``
    applied, in the controller's current angles (``entered_shift``); the nominal arm without a
    result. Exits 2 with the reason on a result that does not apply."""
    from calib.robot.calibrated import Calibrated, ResultError, apply_result, read_result  # noqa: PLC0415
    from calib.robot.kinematics import Chain  # noqa: PLC0415

    if result is None:
        return Calibrated(model, Chain(model).nominal)
    try:
        doc = read_result(result)
        cal = apply_result(model, doc, where=str(result))
        shift, said = entered_shift(doc, model, entered, str(result))
    except ResultError as exc:
        _fail(str(exc))
    echo(f"applied from {result}: {', '.join(cal.applied)}")
    for note in cal.notes:
        echo(note)
    echo(said)
    cal = cal.after_entering(shift)
    cal.notes.append(said)
    return cal


def export_model(
    model_path: Path = typer.Argument(..., metavar="MODEL", help="Robot model YAML (the nominal model the fit used)."),
    output: Path = typer.Option(..., "-o", "--output", help="Write the exported model here."),
    result: Optional[Path] = typer.Option(None, "--result", help="A fit's result.json: apply what it found (offsets, links, tool, compliance)."),
    fmt: str = typer.Option("auto", "--format", help="urdf, ur (UR's kinematics parameters YAML) or model (our YAML); "
                                                     "auto: urdf for a .urdf output."),
    entered: str = typer.Option("auto", "--entered", help="Offsets entered in the controller since the measurement: "
                                                         "auto (the offsets the result's 'entered' block says to enter, if any; else none), result, none."),
    checks: int = typer.Option(200, "--check", help="Random configurations for the read-back FK checks."),
) -> None:
    """Export a robot model (calibrated with --result) as URDF, UR calibration YAML or model YAML,
    with the gravity sag beside it as data; every file is checked by reading it back."""
    import numpy as np  # noqa: PLC0415

    from calib.robot.kinematics import Chain  # noqa: PLC0415
    from calib.robot.model import load_robot_model  # noqa: PLC0415
    from calib.robot.urdf import fk_difference, random_configurations  # noqa: PLC0415
    from calib.io.yamlfile import ConfigError  # noqa: PLC0415

    if checks < 1:
        raise typer.BadParameter(f"must be at least 1, given {checks}", param_hint="--check")
    fmt = _export_format(fmt, output)
    try:
        nominal = load_robot_model(model_path)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="MODEL") from exc
    arm = calibrated_arm(nominal, result, entered)
    header = f"Model: {model_path.name} ({nominal.name})."
    if result is not None:
        header += f"\nCalibrated with {result.name}: applied {', '.join(arm.applied)}."
        header += "\n" + "\n".join(arm.notes)
    sag_path = output.with_name(output.stem + ".sag.yaml") if arm.compliance is not None else None
    if sag_path is not None:
        header += (f"\nThe fitted gravity sag (joint compliances) cannot be expressed in this file: it is in {sag_path.name} "
                   "(remaster.sag/1), to be applied on top of these kinematics.")
    try:
        exported = _write_export(fmt, arm.model, output, header)
    except ValueError as exc:
        _fail(str(exc))
    q = random_configurations(arm.model, checks, seed=0)
    ok = True
    for label, fk in exported:
        ok &= _check(label, fk_difference(Chain(arm.model).fk(q), fk(q)), checks)
    if sag_path is not None:
        from calib.robot.sag_file import read_sag_file, write_sag_file  # noqa: PLC0415

        write_sag_file(arm, sag_path, header)
        sag = read_sag_file(sag_path)
        label, fk = exported[0]
        ok &= _check(f"{label} with the sag of {sag_path.name}, against the calibrated arm with its sag",
                     fk_difference(arm.fk(q), fk(q + sag.joint_sag(q))), checks)
        typer.echo(f"the gravity sag cannot be in a {fmt} file: wrote it as data to {sag_path} "
                   "(Δq = sign·k·τ(q), see the file)")
        off = np.linalg.norm(Chain(arm.model).fk(q)[:, :3, 3] - arm.fk(q)[:, :3, 3], axis=-1)
        typer.echo(f"without its sag, the {fmt} file's arm is off the calibrated arm by {np.sqrt(np.mean(off ** 2)):.3f} mm "
                   f"rms, {off.max():.3f} mm at worst ({checks} random configurations): its links were fitted together with "
                   "the sag — apply the sag file, or export a fit without compliance for a consumer that cannot")
    if not ok:
        _fail(f"{output} does not reproduce the calibrated model", 1)
    typer.echo(f"wrote {output}")


def _write_export(fmt: str, model, output: Path, header: str) -> list:
    """Write ``model`` as ``fmt`` and return [(label, fk)] read-back FK functions (q → flange frames)."""
    from calib.robot.kinematics import Chain  # noqa: PLC0415

    if fmt == "urdf":
        from calib.robot.urdf import UrdfError, export_urdf, import_urdf, load_urdf, urdf_fk  # noqa: PLC0415

        export_urdf(model, output, header=header)
        try:
            back = load_urdf(output)
            imp = import_urdf(output, convention=model.convention)
        except UrdfError as exc:
            _fail(f"the written URDF does not read back: {exc}", 1)
        return [("of the URDF read by yourdfpy", lambda q: urdf_fk(back, model.axis_names, "base_link", "flange", q)),
                ("of the URDF re-imported", lambda q: Chain(imp.model).fk(q))]
    if fmt == "ur":
        import numpy as np  # noqa: PLC0415

        from calib.robot.ur_kinematics import read_ur_kinematics, ur_kinematics, write_ur_kinematics  # noqa: PLC0415
        from calib.robot.transforms import matrix_to_euler_zyx  # noqa: PLC0415

        kin = ur_kinematics(model)
        res = kin.residual
        rpy = np.degrees(matrix_to_euler_zyx(res[:3, :3]))[::-1]
        flange = ("the model's flange is wrist_3_link itself" if np.allclose(res, np.eye(4), atol=1e-12) else
                  f"the model's flange is wrist_3_link · (xyz {np.round(res[:3, 3], 6).tolist()} mm, rpy "
                  f"{np.round(rpy, 6).tolist()} deg): the sixth link's a, α, β and the flange frame, which this file cannot "
                  "hold — put them in your tool (TCP) definition")
        text = (header + "\nUniversal Robots kinematics parameters: ur_robot_driver's launch argument kinematics_params_file:=<this file> "
                "(ur_description's xacro argument kinematics_parameters_file); "
                "metres, radians, URDF rpy. tool0 = wrist_3_link · Rz(180°) as ur_description builds it; " + flange + ".\n"
                f"hash {kin.hash}: not the controller's calibration hash — the driver's check that the file matches the "
                "controller's own calibration will report a mismatch, by design (this file is the measured arm).")
        write_ur_kinematics(model, output, text)
        typer.echo(flange)
        try:
            back = read_ur_kinematics(output)
        except ValueError as exc:
            _fail(f"the written file does not read back: {exc}", 1)
        return [("of the UR kinematics file built as ur_description builds it", lambda q: back.wrist3(q) @ res)]
    from calib.robot.model import load_robot_model, model_yaml  # noqa: PLC0415

    output.write_text(model_yaml(model, header), encoding="utf-8")
    back = load_robot_model(output)
    return [("of the model YAML read back", lambda q: Chain(back).fk(q))]


model_app.command("import")(import_model)
model_app.command("export")(export_model)


def register(app: typer.Typer) -> None:
    """Add the ``model`` command group to ``app``."""
    app.add_typer(model_app, name="model")
