"""YAML files validated by pydantic, with errors that name file, line, column and field.

Used for robot models here and for plans in ``acquire``. A bad file raises ``ConfigError``
(a ``ValueError``) whose message lists every problem as
``path:line:column: field: message (given: …)``.

Every YAML the project reads (plans, inline ``plan_text``, daemon config, simulated cells, robot
models) goes through ``parse_yaml_text``/``load_yaml_with_marks``: a safe loader that refuses
anchors and aliases, duplicate keys (naming both lines), nesting deeper than ``MAX_DEPTH`` and
input larger than ``MAX_BYTES`` — all as ``ConfigError`` with file, line and column.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError, ValidationInfo, model_validator

M = TypeVar("M", bound=BaseModel)

Marks = dict[tuple, tuple[int, int]]


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message says where and why."""


class CrossFieldChecked(BaseModel):
    """A model with checks across fields that point at the offending field.

    Subclasses return ``(field path, message)`` pairs from ``deferred_errors()``. Validated in
    memory they raise at once; loaded through ``load_validated`` they are reported with the
    line and column of that field.
    """

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        return []

    @model_validator(mode="after")
    def _cross_field_checks(self, info: ValidationInfo):
        if info.context and info.context.get("defer_cross_field_checks"):
            return self
        errors = self.deferred_errors()
        if errors:
            raise ValueError("; ".join(f"{'.'.join(map(str, loc)) or '(top level)'}: {msg}" for loc, msg in errors))
        return self


MAX_BYTES = 1 << 20
"""Largest YAML file or inline text accepted (1 MiB; the biggest shipped file is ~5 kB)."""
MAX_DEPTH = 64
"""Deepest nesting of mappings/sequences accepted (shipped files nest at most 8 deep)."""


def _where(source: str | Path, mark: yaml.Mark | None) -> str:
    return f"{source}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(source)


class _Loader(yaml.SafeLoader):
    """A SafeLoader that refuses anchors/aliases and over-deep nesting while composing.

    Aliases are refused outright rather than expanded within a bound: no file of ours needs them,
    and a few hundred bytes of nested aliases expand to gigabytes ("billion laughs").
    """

    def __init__(self, text: str, source: str | Path) -> None:
        super().__init__(text)
        self.source = source
        self.depth = 0

    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise ConfigError(f"{_where(self.source, event.start_mark)}: YAML aliases are not allowed "
                              f"(given *{event.anchor}); write the value out in full")
        if getattr(event, "anchor", None) is not None:
            raise ConfigError(f"{_where(self.source, event.start_mark)}: YAML anchors are not allowed "
                              f"(given &{event.anchor}); write the value out in full where it is used")
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            if self.depth >= MAX_DEPTH:
                raise ConfigError(f"{_where(self.source, event.start_mark)}: nested too deep (more than "
                                  f"{MAX_DEPTH} levels of mappings/lists; allowed: at most {MAX_DEPTH})")
            self.depth += 1
            try:
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1
        return super().compose_node(parent, index)


def _construct(node: yaml.Node, path: tuple, marks: Marks, loader: _Loader) -> Any:
    marks[path] = (node.start_mark.line + 1, node.start_mark.column + 1)
    plain = {yaml.MappingNode: "tag:yaml.org,2002:map", yaml.SequenceNode: "tag:yaml.org,2002:seq"}.get(type(node))
    if plain is not None and node.tag != plain:
        raise ConfigError(f"{_where(loader.source, node.start_mark)}: {'.'.join(map(str, path)) or '(top level)'}: "
                          f"YAML tags are not allowed on mappings and lists (given {node.tag!r})")
    if isinstance(node, yaml.MappingNode):
        out: dict = {}
        first_line: dict = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise ConfigError(f"{_where(loader.source, key_node.start_mark)}: "
                                  f"{'.'.join(map(str, path)) or '(top level)'}: a key must be a plain value "
                                  "(given a mapping or list as a key)")
            key = loader.construct_object(key_node)
            line = key_node.start_mark.line + 1
            if key in first_line:
                field = ".".join(map(str, path + (key,)))
                raise ConfigError(f"{_where(loader.source, key_node.start_mark)}: {field}: duplicate key {key!r} "
                                  f"(first given on line {first_line[key]}, again on line {line}); each key may "
                                  "appear once — remove one of them")
            first_line[key] = line
            out[key] = _construct(value_node, path + (key,), marks, loader)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_construct(v, path + (i,), marks, loader) for i, v in enumerate(node.value)]
    return loader.construct_object(node, deep=True)


def parse_yaml_text(text: str, source: str | Path = "<text>") -> tuple[Any, Marks]:
    """Parse YAML ``text`` safely; return the data and a map from field path to (line, column), 1-based.

    ``source`` names the text in errors (a file path, or e.g. ``"plan_text"``). Refused with a
    ``ConfigError`` naming ``source:line:column``: more than ``MAX_BYTES`` bytes (UTF-8), anchors and
    aliases, nesting deeper than ``MAX_DEPTH``, duplicate keys (both lines named), non-scalar keys,
    tags the safe loader does not know, and an empty document.
    """
    size = len(text.encode("utf-8"))
    if size > MAX_BYTES:
        raise ConfigError(f"{source}: too large ({size} bytes; allowed: at most {MAX_BYTES} bytes)")
    # A loader per text: a loader keeps every object it constructed (a shared one grew without
    # bound in a long-running daemon) and is not thread-safe.
    loader = _Loader(text, source)
    try:
        node = loader.get_single_node()
        if node is None:
            raise ConfigError(f"{source}: the file is empty")
        marks: Marks = {}
        return _construct(node, (), marks, loader), marks
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise ConfigError(f"{_where(source, mark)}: not valid YAML: {getattr(exc, 'problem', None) or exc}") from None
    finally:
        loader.dispose()


def read_yaml_text(path: str | Path) -> str:
    """The text of a YAML file, refused as ``ConfigError`` if unreadable or over ``MAX_BYTES``."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if len(raw) > MAX_BYTES:
        raise ConfigError(f"{path}: too large (more than {MAX_BYTES} bytes; allowed: at most {MAX_BYTES} bytes)")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}:{line}: not UTF-8 text (byte {exc.start}); save the file as UTF-8") from None


def load_yaml_with_marks(path: str | Path) -> tuple[Any, Marks]:
    """Parse a YAML file safely (see ``parse_yaml_text``); return the data and its field marks."""
    return parse_yaml_text(read_yaml_text(path), Path(path))


def locate(loc: tuple, marks: Marks) -> tuple[int, int] | None:
    """(line, column) of field path ``loc`` in the file, or of its nearest parent that has one."""
    for n in range(len(loc), -1, -1):
        if loc[:n] in marks:
            return marks[loc[:n]]
    return None


def error_line(path: str | Path, marks: Marks, loc: tuple, message: str) -> str:
    """One problem as ``path:line:col: field: message`` (the line of ``loc`` or its parent)."""
    where = locate(tuple(loc), marks)
    prefix = f"{path}:{where[0]}:{where[1]}" if where else str(path)
    return f"{prefix}: {'.'.join(str(p) for p in loc) or '(top level)'}: {message}"


def format_validation_error(path: str | Path, exc: ValidationError, marks: Marks, data: Any) -> str:
    """Every pydantic error as ``path:line:col: field: message (given: value)``."""
    lines = []
    for err in exc.errors(include_url=False):
        loc = tuple(err["loc"])
        # Drop pydantic's discriminator/function tags that are not keys in the file.
        file_loc = tuple(p for p in loc if not (isinstance(p, str) and ("[" in p or "function-" in p)))
        given = err.get("input")
        given_txt = "" if isinstance(given, (dict, list)) else f" (given: {given!r})"
        lines.append(error_line(path, marks, file_loc, f"{err['msg']}{given_txt}"))
    return "\n".join(lines)


def load_validated(path: str | Path, model: type[M]) -> M:
    """Load ``path`` and validate it as ``model``; raise ConfigError naming line and field.

    A model may check relations between fields in ``deferred_errors()`` (returning
    ``(field path, message)`` pairs) and skip them in its validators when the validation
    context has ``defer_cross_field_checks``; they are then reported at the right line here.
    """
    data, marks = load_yaml_with_marks(path)
    try:
        obj = model.model_validate(data, context={"defer_cross_field_checks": True})
    except ValidationError as exc:
        raise ConfigError(format_validation_error(path, exc, marks, data)) from None
    deferred = getattr(obj, "deferred_errors", None)
    problems = deferred() if deferred else []
    if problems:
        raise ConfigError("\n".join(error_line(path, marks, loc, msg) for loc, msg in problems))
    return obj
