"""MkDocs hook: the reference pages generated from the code at build time.

Every CLI command and option comes from the typer application, every plan / simulated-cell /
daemon / station / robot-model field from its pydantic model (types, defaults, limits and the
``description`` each field carries), so the reference cannot drift from what the program
accepts. Repository notes that live beside their code (``systemd/README.md``, the drivers'
``PROTOCOL.md``) are brought in as pages too; their links to repository files become paths.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import typer
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]

SCHEMAS = {
    # page: (module, class, title, what it is)
    "reference/plan.md": ("acquire.plan.schema", "Plan", "Plan file (`acquire run PLAN`)",
                          "The measurement plan: robot, commander, sensors, poses, sequencing, fit, output."),
    "reference/cell-file.md": ("drivers.sim.config", "SimConfig", "Simulated cell file (`acquire sim --config`)",
                               "The simulated cell's hidden truth, its devices and scripted faults."),
    "reference/daemon-config.md": ("acquire.daemon.config", "DaemonConfig", "Daemon configuration (`acquire daemon --config`)",
                                   "The cell PC's service: cell id, devices, Zenoh, authentication, live view."),
    "reference/station-config.md": ("acquire.station.config", "StationConfig", "Station configuration (`acquire station --config`)",
                                    "The plant's archive station: cells, credentials, drift policy."),
    "reference/robot-model.md": ("calib.robot.model", "RobotModel", "Robot model file",
                                 "A robot's kinematics (DH or modified DH), limits, masses and tool markers."),
}

INCLUDED = {
    # page: (repository file, title)
    "how-to/systemd.md": ("systemd/README.md", None),
    "reference/protocols/kuka-fri.md": ("drivers/kuka_fri/PROTOCOL.md", None),
    "reference/protocols/tracker-line.md": ("drivers/tracker/PROTOCOL.md", None),
    "how-to/kuka-rsi-controller.md": ("drivers/kuka_rsi/controller/README.md", None),
    "how-to/kuka-sunrise-controller.md": ("drivers/kuka_fri/controller/README.md", None),
}


# ----------------------------------------------------------------------------------- the CLI
def _param_row(p) -> str:
    """One table row of a typer parameter: name(s), type, default, required, help."""
    if p.param_type_name == "argument":
        name = f"`{(p.metavar or p.name).upper()}`"
    else:
        name = ", ".join(f"`{o}`" for o in [*p.opts, *p.secondary_opts])
    if getattr(p, "is_flag", False) or getattr(p, "count", False):
        kind = "flag"
    else:
        ann = getattr(getattr(p, "type_descriptor", None), "annotation", None)
        kind = getattr(ann, "__name__", str(ann or "")).lower().replace("path", "path").replace("str", "text")
    default = p.default
    if callable(default) or default in (None, (), False) or getattr(p, "count", False) and default == 0:
        default = ""
    else:
        default = f"`{default}`"
    required = "yes" if p.required else ""
    help_text = _clean_help(getattr(p, "help", None) or "").replace("|", "\\|").replace("\n", " ")
    return f"| {name} | {kind} | {default} | {required} | {help_text} |"


def _command_md(cmd, path: list[str], out: list[str]) -> None:
    if getattr(cmd, "hidden", False):
        return
    full = " ".join(path)
    depth = min(len(path), 4)
    out.append(f"{'#' * (depth + 1)} `{full}`")
    out.append("")
    ctx = cmd.context_class(cmd, info_name=full)
    args = [(p.metavar or p.name).upper() for p in cmd.params if p.param_type_name == "argument"]
    sub = " COMMAND" if hasattr(cmd, "list_commands") else ""
    out.append(f"```text\nUsage: {full} [OPTIONS]{sub} {' '.join(args)}\n```")
    if cmd.help:
        out.append("")
        out.append(_clean_help(cmd.help))
    params = [p for p in cmd.params if not getattr(p, "hidden", False) and p.name not in ("help",)]
    if params:
        out += ["", "| argument / option | type | default | required | what it does |", "|---|---|---|---|---|"]
        out += [_param_row(p) for p in params]
    out.append("")
    if hasattr(cmd, "list_commands"):  # a group: its commands, each with its own section
        for name in cmd.list_commands(ctx):
            _command_md(cmd.get_command(ctx, name), [*path, name], out)


def _clean_help(text: str) -> str:
    """typer/rich help as Markdown: drop rich markup tags and ``\\b`` paragraph markers."""
    text = re.sub(r"\[/?(bold|b|i|italic|dim|red|green|yellow|cyan|magenta|blue)\]", "", text)
    text = text.replace("\b\n", "").replace("\b", "")
    return text.strip()


def cli_markdown() -> str:
    from acquire.cli import COMMANDS, app, load_command

    group = typer.main.get_command(app)
    out = ["# Command line (`acquire`)", "",
           "Generated from the program itself at documentation build time; `acquire COMMAND --help` prints the same.", ""]
    ctx = group.context_class(group, info_name="acquire")
    for name in COMMANDS:  # each sub-command's module loaded, as its own --help loads it
        _command_md(load_command(name, ctx), ["acquire", name], out)
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------------- schemas
def _type_of(s: dict, defs: dict) -> str:
    if "$ref" in s:
        name = s["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    if "const" in s:
        return f"`{json.dumps(s['const'])}`"
    if "enum" in s:
        return " \\| ".join(f"`{json.dumps(v)}`" for v in s["enum"])
    if "anyOf" in s:
        return " or ".join(_type_of(x, defs) for x in s["anyOf"])
    if "allOf" in s and len(s["allOf"]) == 1:
        return _type_of(s["allOf"][0], defs)
    t = s.get("type")
    if t == "array":
        inner = s.get("items") or (s.get("prefixItems") and {"type": "tuple"}) or {}
        return f"list of {_type_of(inner, defs) if inner else 'values'}"
    if t == "object":
        extra = s.get("additionalProperties")
        return f"mapping to {_type_of(extra, defs)}" if isinstance(extra, dict) and extra else "mapping"
    return t or "any"


_LIMITS = (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("exclusiveMaximum", "<"),
           ("minLength", "length ≥"), ("maxLength", "length ≤"), ("minItems", "items ≥"), ("maxItems", "items ≤"),
           ("pattern", "matches"))


def _limits(s: dict) -> str:
    parts = []
    for src in [s, *s.get("anyOf", [])]:
        for key, word in _LIMITS:
            if key in src:
                val = src[key]
                parts.append(f"{word} `{val}`")
    return ", ".join(parts)


def _model_table(name: str, s: dict, defs: dict) -> list[str]:
    out = [f"### {name}", "", f'<a id="{name.lower()}"></a>', ""]
    if s.get("description"):
        out += [s["description"].strip(), ""]
    props = s.get("properties", {})
    if not props:
        return out + ["(no fields)", ""]
    required = set(s.get("required", []))
    out += ["| field | type | default | limits | what it is |", "|---|---|---|---|---|"]
    for field, fs in props.items():
        default = "required" if field in required else (f"`{json.dumps(fs['default'])}`" if "default" in fs else "")
        desc = (fs.get("description") or "").replace("|", "\\|").replace("\n", " ")
        out.append(f"| `{field}` | {_type_of(fs, defs)} | {default} | {_limits(fs)} | {desc} |")
    return out + [""]


def schema_markdown(module: str, cls: str, title: str, what: str) -> str:
    import importlib

    model = getattr(importlib.import_module(module), cls)
    schema = model.model_json_schema(mode="validation")
    defs = schema.get("$defs", {})
    out = [f"# {title}", "", what, "",
           f"Generated from `{module}.{cls}` (pydantic) at documentation build time: every field the "
           "program accepts, nothing else (unknown fields are refused with file, line and column).", ""]
    out += _model_table(cls, schema, defs)
    for name in sorted(defs):
        out += _model_table(name, defs[name], defs)
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------------- included notes
_LINK = re.compile(r"\[([^\]]+)\]\((?!https?://|#)([^)]+)\)")


def included_markdown(rel: str, title: str | None) -> str:
    text = (ROOT / rel).read_text()
    base = Path(rel).parent

    def to_path(m: re.Match) -> str:  # a link to a repository file becomes its path
        target = (base / m.group(2)).as_posix()
        label = m.group(1)
        return f"{label} (`{target}`)" if label.strip("`") != target else f"`{target}`"

    text = _LINK.sub(to_path, text)
    note = f"\n\n*This page is `{rel}` of the repository.*\n"
    return (f"# {title}\n\n" if title else "") + text + note


# ----------------------------------------------------------------------------------- the hook
def on_files(files, config):
    pages = {"reference/cli.md": cli_markdown()}
    for page, (module, cls, title, what) in SCHEMAS.items():
        pages[page] = schema_markdown(module, cls, title, what)
    for page, (rel, title) in INCLUDED.items():
        pages[page] = included_markdown(rel, title)
    for page, content in pages.items():
        files.append(File.generated(config, page, content=content))
    return files
