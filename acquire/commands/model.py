"""``acquire model``: robot models in and out of URDF.

Examples::

    acquire model import kr6r900_2.urdf -o kr6.yaml
    acquire model import iiwa14.urdf --tip iiwa_link_ee_kuka --axes A1,A2,A3,A4,A5,A6,A7 \\
        --controller sunrise -o iiwa14.yaml
    acquire model export fixtures/robots/kuka_iiwa14_r820.yaml --result result.json -o iiwa14_calibrated.urdf

``import`` writes our model YAML (mm, degrees; DH or M-DH as the axes require) from the URDF's
serial chain and proves it: the model's forward kinematics against the URDF's own (yourdfpy) on
random configurations inside the limits; it refuses to write a model that disagrees.
``export`` writes the model — with a fit's result applied when ``--result`` is given — as a URDF,
reads the file back through yourdfpy and through ``import``, and checks both give the same
forward kinematics. Exit status 1 when a check fails, 2 on bad input.
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


def export_model(
    model_path: Path = typer.Argument(..., metavar="MODEL", help="Robot model YAML (the nominal model the fit used)."),
    output: Path = typer.Option(..., "-o", "--output", help="Write the URDF here."),
    result: Optional[Path] = typer.Option(None, "--result", help="A fit's result.json: apply its offsets / identified parameters."),
    checks: int = typer.Option(200, "--check", help="Random configurations for the read-back FK checks."),
) -> None:
    """Export a robot model (calibrated with --result) as URDF, checked by reading it back."""
    from calib.robot.calibrated import ResultError, apply_result, read_result  # noqa: PLC0415
    from calib.robot.kinematics import Chain  # noqa: PLC0415
    from calib.robot.model import load_robot_model  # noqa: PLC0415
    from calib.robot.urdf import UrdfError, export_urdf, fk_difference, import_urdf, load_urdf, random_configurations, urdf_fk  # noqa: PLC0415
    from calib.io.yamlfile import ConfigError  # noqa: PLC0415

    if checks < 1:
        raise typer.BadParameter(f"must be at least 1, given {checks}", param_hint="--check")
    try:
        model = load_robot_model(model_path)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="MODEL") from exc
    header = f"Model: {model_path.name} ({model.name})."
    if result is not None:
        try:
            cal = apply_result(model, read_result(result), where=str(result))
        except ResultError as exc:
            _fail(str(exc))
        typer.echo(f"applied from {result}: {', '.join(cal.applied)}")
        for note in cal.notes:
            typer.echo(note)
        model = cal.model
        header += f"\nCalibrated with {result.name}: applied {', '.join(cal.applied)}."
        if cal.notes:
            header += "\n" + "\n".join(cal.notes)
        header += ("\nDescribes the robot before the offsets are entered in the controller "
                   "(joint values = the controller's angles as they are now).")
    export_urdf(model, output, header=header)
    q = random_configurations(model, checks, seed=0)
    ours = Chain(model).fk(q)
    try:
        back = load_urdf(output)
        ok = _check("of the URDF read by yourdfpy", fk_difference(ours, urdf_fk(back, model.axis_names, "base_link", "flange", q)), checks)
        imp = import_urdf(output, convention=model.convention)
        ok &= _check("of the URDF re-imported", fk_difference(ours, Chain(imp.model).fk(q)), checks)
    except UrdfError as exc:
        _fail(f"the written URDF does not read back: {exc}", 1)
    if not ok:
        _fail(f"{output} does not reproduce the model", 1)
    typer.echo(f"wrote {output}")


model_app.command("import")(import_model)
model_app.command("export")(export_model)


def register(app: typer.Typer) -> None:
    """Add the ``model`` command group to ``app``."""
    app.add_typer(model_app, name="model")
