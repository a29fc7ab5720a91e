"""YAML files validated by pydantic, with errors that name file, line, column and field.

Used for robot models here and for plans in ``acquire``. A bad file raises ``ConfigError``
(a ``ValueError``) whose message lists every problem as
``path:line:column: field: message (given: …)``.
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


def _construct(node: yaml.Node, path: tuple, marks: Marks, loader: "yaml.SafeLoader") -> Any:
    marks[path] = (node.start_mark.line + 1, node.start_mark.column + 1)
    if isinstance(node, yaml.MappingNode):
        out: dict = {}
        for key_node, value_node in node.value:
            key = yaml.SafeLoader.construct_object(loader, key_node)
            out[key] = _construct(value_node, path + (key,), marks, loader)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_construct(v, path + (i,), marks, loader) for i, v in enumerate(node.value)]
    return loader.construct_object(node, deep=True)


class _Loader(yaml.SafeLoader):
    pass


def load_yaml_with_marks(path: str | Path) -> tuple[Any, Marks]:
    """Parse a YAML file; return the data and a map from field path to (line, column), 1-based."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark else str(path)
        raise ConfigError(f"{where}: not valid YAML: {getattr(exc, 'problem', exc)}") from exc
    if node is None:
        raise ConfigError(f"{path}: the file is empty")
    marks: Marks = {}
    # A loader per file: a loader keeps every object it constructed (a shared one grew without
    # bound in a long-running daemon) and is not thread-safe.
    return _construct(node, (), marks, _Loader("")), marks


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
