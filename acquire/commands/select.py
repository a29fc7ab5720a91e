"""``acquire select``: choose the most informative configurations by an observability index."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import typer

from calib.plan.observability import INDICES
from calib.io.yamlfile import ConfigError


def select(
    robot: Path = typer.Option(..., "--robot", help="Robot model YAML."),
    candidates: Path = typer.Option(..., "--candidates", help="Configurations file (from `acquire poses -o`)."),
    m: int = typer.Option(50, "-m", help="How many configurations to choose."),
    index: str = typer.Option("O6", "--index", help=f"Observability index: {', '.join(INDICES)}."),
    k: float | None = typer.Option(None, "--k", help="Weight of O3 in O6 = O1 + k·O3 (default: O1/O3 of the start set)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the random start and exchanges."),
    output: Path | None = typer.Option(None, "-o", "--output", help="Write the chosen configurations here."),
    orientation: str | None = typer.Option(
        None, "--orientation", metavar="SIGMA_MM,SIGMA_DEG",
        help="The sensor measures the tool's orientation too (a 6-DoF target at the model's first marker): its "
             "position and attitude noise per axis, e.g. 0.024,0.01; selection then uses position + attitude rows."),
) -> None:
    """Choose m configurations from a candidate set with the IOOPS exchange algorithm."""
    from calib.fit.identification import information_blocks  # the fitters load only when selecting
    from calib.robot.model import load_robot_model
    from calib.plan.observability import indices_from_eigenvalues, ioops
    from calib.plan.poses import FILE_MAGIC, read_configurations

    if index not in INDICES:
        raise typer.BadParameter(f"{index!r} is not an index; choose one of {', '.join(INDICES)}", param_hint="--index")
    try:
        model = load_robot_model(robot)
        cand = read_configurations(candidates, model)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    n = len(cand.configurations)
    if not 1 <= m < n:
        raise typer.BadParameter(f"cannot choose {m} of {n} candidates; use 1 ≤ m < {n}", param_hint="-m")
    attitude = None
    if orientation is not None:
        try:
            sigma_mm, sigma_deg = (float(v) for v in orientation.split(","))
        except ValueError:
            raise typer.BadParameter(f"expected SIGMA_MM,SIGMA_DEG (e.g. 0.024,0.01), given {orientation!r}",
                                     param_hint="--orientation") from None
        if not (0 < sigma_mm <= 10 and 0 < sigma_deg <= 10):
            raise typer.BadParameter(f"expected 0 < SIGMA_MM ≤ 10 and 0 < SIGMA_DEG ≤ 10, given {orientation!r}",
                                     param_hint="--orientation")
        attitude = sigma_mm / np.radians(sigma_deg)
    blocks, names, excluded = information_blocks(model, cand.q_rad, attitude_mm_per_rad=attitude)
    sel = ioops(blocks, m, index=index, k=k, seed=seed)
    all_idx = indices_from_eigenvalues(np.linalg.eigvalsh(blocks[sel.chosen].sum(axis=0)), m, sel.k)
    typer.echo(f"{n} candidates, {len(names)} identifiable parameters ({len(excluded)} excluded)"
               + (f"; position + attitude rows ({attitude:.4g} mm/rad)" if attitude else ""))
    typer.echo(f"IOOPS on {index}: {sel.start_value:.6g} (random start) → {sel.value:.6g} in {sel.iterations} iterations")
    typer.echo("indices of the chosen set: " + ", ".join(f"{key}={v:.4g}" for key, v in all_idx.items()))
    rows = [cand.configurations[i] for i in sel.chosen]
    typer.echo("chosen: " + " ".join(str(c.config) for c in rows))
    if output is not None:
        out = io.StringIO()
        out.write(FILE_MAGIC + "\n")
        for key, value in cand.header.items():
            out.write(f"# {key}: {value}\n")
        out.write(f"# selected: {m} of {n} by IOOPS on {index} (k={sel.k:.4g}, seed={seed}), value {sel.value:.6g}\n")
        w = csv.writer(out, lineterminator="\n")
        w.writerow(["config", "pose", "branch"] + [f"q{i + 1}" for i in range(model.n_joints)])
        for c in rows:
            w.writerow([c.config, c.pose, c.branch] + [f"{v:.6f}" for v in np.degrees(c.q)])
        output.write_text(out.getvalue(), encoding="utf-8")
        typer.echo(f"wrote {output}")


def register(app: typer.Typer) -> None:
    app.command("select")(select)
