"""CSV as spreadsheets export it: the separator and the decimal mark, found or refused by name.

A spreadsheet in a German, French or Italian locale saves "CSV" with ``;`` between fields and
a decimal comma (``12,5``); Excel adds a UTF-8 byte-order mark; some tools write tabs. The
readers of ``calib.measure.dataset`` and ``calib.fit.socket`` use this module so that such a file is read
as it is meant, or refused with a message that names the separator and the decimal mark:

- separator: the one of ``,`` ``;`` tab that the header line (first line not starting with
  ``#``) uses; a header that mixes two is refused, naming both;
- decimal mark: ``.`` unless the numeric cells use commas (``12,5``, also ``1.234,5`` with
  thousands points); cells of both kinds in one file are refused, naming a line of each;
  decimal commas in a comma-separated file without quotes cannot be told from separators —
  a row with more fields than the header says so and how to export instead.

Errors are raised as the caller's error class (a ``ValueError``) with ``source:line``.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

SEPARATORS = {",": "comma ','", ";": "semicolon ';'", "\t": "tab"}
_COMMA_DECIMAL = re.compile(r"^[+-]?(\d{1,3}(\.\d{3})+|\d*),\d+([eE][+-]?\d+)?$")
_POINT_DECIMAL = re.compile(r"^[+-]?(\d{1,3}(,\d{3})+|\d*)\.\d+([eE][+-]?\d+)?$|^[+-]?\d+\.?([eE][+-]?\d+)?$")
_HAS_POINT = re.compile(r"\d\.\d|^[+-]?\.\d|\d\.$")


@dataclass(frozen=True)
class Dialect:
    """separator: ``,`` ``;`` or a tab; decimal: ``.`` or ``,``."""

    separator: str = ","
    decimal: str = "."

    def describe(self) -> str:
        return f"{SEPARATORS[self.separator]}-separated, decimal {'comma' if self.decimal == ',' else 'point'}"


def decode(raw: bytes, source: str, error: type[Exception] = ValueError) -> str:
    """UTF-8 text (a leading byte-order mark removed); other encodings are refused by name."""
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{source}: not UTF-8 text (byte {exc.start}: {raw[exc.start:exc.start + 1]!r}); save it as "
                    "'CSV UTF-8' (Excel) or 'Text CSV' with UTF-8 (LibreOffice)") from None


def content_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line that is neither blank nor a ``#`` comment."""
    text = text.lstrip("\ufeff")
    return [(no, line) for no, line in enumerate(text.splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith("#")]


def sniff_separator(header: str, source: str, lineno: int, error: type[Exception] = ValueError) -> str:
    """The separator the header line uses (``,`` when it has one column)."""
    used = [s for s in SEPARATORS if s in header]
    if len(used) > 1:
        raise error(f"{source}:{lineno}: the header mixes separators ({' and '.join(SEPARATORS[s] for s in used)}; "
                    f"given {header.strip()!r}); allowed: one of comma, semicolon or tab between all columns")
    return used[0] if used else ","


def split(line: str, separator: str) -> list[str]:
    """One line's cells (quotes honoured), stripped."""
    return [c.strip() for c in next(csv.reader([line], delimiter=separator))]


def check_unique(header: Sequence[str], source: str, lineno: int, error: type[Exception] = ValueError) -> None:
    """Refuse a header that names a column twice (a spreadsheet export with a pasted column):
    which value is meant cannot be known, so nothing is read."""
    seen: dict[str, list[int]] = {}
    for i, name in enumerate(header, start=1):
        seen.setdefault(name, []).append(i)
    twice = {name: cols for name, cols in seen.items() if len(cols) > 1}
    if twice:
        what = "; ".join(f"{name!r} in columns {', '.join(map(str, cols))}" for name, cols in twice.items())
        raise error(f"{source}:{lineno}: the header names a column more than once ({what}); "
                    "allowed: each column once — delete or rename the extra one")


def split_header(line: str) -> list[str]:
    """Header cells with the separator the header itself uses (for format detection)."""
    used = [s for s in SEPARATORS if s in line]
    return split(line.lstrip("\ufeff"), used[0] if len(used) == 1 else ",")


def sniff_decimal(rows: Iterable[tuple[int, Sequence[str]]], columns: Sequence[int], source: str,
                  error: type[Exception] = ValueError) -> str:
    """``,`` when the numeric cells (``columns`` of ``rows``) use decimal commas, else ``.``;
    refuses a file that uses both, naming a line of each."""
    comma = point = None
    for lineno, cells in rows:
        for c in columns:
            if c >= len(cells):
                continue
            v = cells[c]
            if comma is None and _COMMA_DECIMAL.match(v):
                comma = (lineno, v)
            elif point is None and _HAS_POINT.search(v) and "," not in v:
                point = (lineno, v)
        if comma and point:
            raise error(f"{source}: mixed decimal marks: line {comma[0]} has a decimal comma ({comma[1]!r}), "
                        f"line {point[0]} a decimal point ({point[1]!r}); allowed: one decimal mark in the whole file")
    return "," if comma else "."


def number(raw: str, decimal: str) -> float:
    """A cell as a float under the decimal mark; raises ValueError for anything else."""
    v = raw.strip()
    if decimal == ",":
        if not _COMMA_DECIMAL.match(v) and not re.match(r"^[+-]?\d+([eE][+-]?\d+)?$", v) \
                and v.lower().lstrip("+-") not in ("nan", "inf", "infinity"):
            raise ValueError(raw)
        v = v.replace(".", "").replace(",", ".")
    elif "," in v:
        if not _POINT_DECIMAL.match(v):
            raise ValueError(raw)
        v = v.replace(",", "")
    return float(v)


def width_error(source: str, lineno: int, cells: Sequence[str], n_header: int, dialect: Dialect) -> str:
    """The message for a row whose field count differs from the header's, with the likely cause."""
    msg = f"{source}:{lineno}: {len(cells)} columns, the header has {n_header}"
    if dialect.separator == "," and len(cells) > n_header and any(re.fullmatch(r"[+-]?\d+", c) for c in cells):
        msg += (" — decimal commas in a comma-separated file? (the header is comma-separated; a value like '12,5' "
                "splits in two); export with ';' as the separator or '.' as the decimal mark")
    return msg


def is_socket_csv(path: Path) -> bool:
    """True for a CSV whose header (first non-comment line) ends in ``placement,socket`` (the
    format of ``calib.fit.socket``; the rest is ``calib.measure.dataset``'s). Reads one line: deciding which
    fit runs costs nothing of the fit the file does not need."""
    if path.suffix.lower() != ".csv":
        return False
    try:
        with path.open(encoding="utf-8-sig") as fh:
            for line in fh:
                if line.strip() and not line.lstrip().startswith("#"):
                    return split_header(line)[-2:] == ["placement", "socket"]
    except (OSError, UnicodeDecodeError):
        return False
    return False
