"""``acquire examples``: the example plans, robot models, simulated cells and the Foxglove layout
shipped in the package.

Examples::

    acquire examples                       # list them, with their paths
    acquire run example --fake             # run a packaged plan by name (results in ./runs)
    acquire examples --copy example        # copy a plan into the current folder to adapt it

A copied plan has its ``robot`` and ``fake.sim_config`` pointing at the packaged files
(absolute paths) and writes its runs to ``runs`` beside it, so it works from any folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def listing() -> str:
    """Every packaged file by kind: name, path, and its first comment line."""
    from calib.io.resources import KINDS, foxglove_layout_hint, packaged, summary

    how = {"plans": "acquire run NAME --fake", "robots": "--robot NAME", "sim": "acquire sim --config NAME"}
    lines = []
    for kind, title in KINDS.items():
        files = packaged(kind)
        lines.append(f"{title} ({how[kind]}):")
        for f in files:
            lines.append(f"  {f.stem:<20} {f}")
            text = summary(f)
            if text:
                lines.append(f"  {'':<20} {text}")
        lines.append("")
    lines.append(f"Foxglove layout (Foxglove: Layouts → Import; for a run log or acquire run --live):\n  {foxglove_layout_hint()}")
    return "\n".join(lines).rstrip()


def copy_plan(name: str, dest: Path) -> Path:
    """Write packaged plan ``name`` to ``dest`` (a folder or a file name) with its robot model and
    simulated cell as absolute packaged paths and its output folder ``runs`` beside the copy.
    Comments are kept (the paths are edited in place). Raises FileExistsError rather than
    overwrite, ValueError for an unknown name."""
    import re

    from calib.io.resources import find, packaged

    src = find("plans", name)
    if src is None:
        raise ValueError(f"no packaged plan {name!r}; allowed: {', '.join(p.stem for p in packaged('plans'))}")
    target = dest / src.name if dest.is_dir() else dest
    if target.exists():
        raise FileExistsError(f"{target} exists; choose another name or remove it first")
    folder = src.resolve().parent

    def absolute(m: re.Match) -> str:
        rel = m.group(2)
        return f"{m.group(1)}{(folder / rel).resolve()}{m.group(3)}"

    text = src.read_text(encoding="utf-8")
    text = re.sub(r"(?m)^(robot:\s*)(\S+)(.*)$", absolute, text)
    text = re.sub(r"(?m)^(\s+sim_config:\s*)(\S+)(.*)$", lambda m: absolute(m) if m.group(2) != "null" else m.group(0), text)
    text = re.sub(r"(?m)^(\s+folder:\s*)(\S+)(.*)$", lambda m: f"{m.group(1)}runs{' ' * 25}# logs and results, beside this plan",
                  text)
    target.write_text(text, encoding="utf-8")
    return target


def examples(
    copy: Optional[str] = typer.Option(None, "--copy", help="Copy this packaged plan (by name) to adapt it."),
    to: Path = typer.Option(Path("."), "--to", help="Folder or file name for --copy."),
) -> None:
    """List the packaged example plans, robot models, simulated cells and Foxglove layout (or copy a plan)."""
    if copy is None:
        typer.echo(listing())
        return
    try:
        target = copy_plan(copy, to)
    except (ValueError, FileExistsError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(f"wrote {target}; run it with: acquire run {target} --fake")


def register(app: typer.Typer) -> None:
    """Add the ``examples`` sub-command to ``app``."""
    app.command("examples")(examples)
