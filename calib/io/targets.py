"""Cartesian robot targets in and out of the files robot programs keep them in.

Three formats, each read into ``Target`` records and written back with only the pose changed:

``csv``   our table: a header line with ``name,x,y,z,a,b,c`` (mm; A, B, C the ZYX Euler angles
          in degrees, KUKA's convention: R = Rz(A)·Ry(B)·Rx(C)), optionally ``q1…qn`` (degrees,
          controller angles: the configuration to reach the target in); ``#`` lines are comments.
``kuka``  a KRL data list (``.dat``): every ``DECL [GLOBAL] E6POS|POS NAME={X …, Y …, Z …, A …,
          B …, C …, S …, T …, E1 …}`` declaration. X, Y, Z (mm), A, B, C (degrees, as above);
          S (Status) and T (Turn) kept as they are: T bit i set means axis i+1 is negative.
          Everything else in the file — other declarations, E6AXIS and FDAT/PDAT lines, comments,
          the S/T/E values, spacing, line ends — is written back byte for byte.
``rapid`` an ABB RAPID module (``.mod``, ``.modx``, ``.prg``): every ``CONST|PERS|VAR robtarget
          name:=[[x,y,z],[q1,q2,q3,q4],[cf1,cf4,cf6,cfx],[eax_a,…,eax_f]];`` (mm; the quaternion
          w first; cf1, cf4, cf6 the quadrants of axes 1, 4, 6: ⌊angle / 90°⌋). Only the position
          and the quaternion change; the configuration, external axes and the rest of the file
          stay byte for byte.

Numbers only: turning them into frames is ``calib.ik.compensation``'s business. Errors name file,
line, field and what is allowed (``TargetFileError``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

FORMATS = ("csv", "kuka", "rapid")
SUFFIXES = {".csv": "csv", ".dat": "kuka", ".mod": "rapid", ".modx": "rapid", ".prg": "rapid", ".sys": "rapid"}
_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"


class TargetFileError(ValueError):
    """A targets file that cannot be read or written; the message names file, line and field."""


@dataclass
class Target:
    """One Cartesian target. ``values``: (x, y, z, a, b, c) mm/deg (csv, kuka) or
    (x, y, z, qw, qx, qy, qz) mm (rapid); ``line`` 1-based; ``config``: what the file says about
    the configuration (csv: ``joints_deg``; kuka: ``S``, ``T``; rapid: ``cf`` [cf1, cf4, cf6, cfx]);
    ``spans``: where each value's text sits in the file (start, end), for writing back."""

    name: str
    line: int
    values: tuple[float, ...]
    config: dict = field(default_factory=dict)
    spans: list[tuple[int, int]] = field(default_factory=list)


@dataclass
class TargetFile:
    """A read targets file: its ``text`` (csv: None), ``format`` and ``targets``."""

    path: Path
    format: str
    targets: list[Target]
    text: str | None = None
    n_joints_columns: int = 0


def target_format(path: Path, given: str = "auto") -> str:
    """The format of ``path``: ``given`` unless auto, else by suffix (``SUFFIXES``)."""
    if given != "auto":
        if given not in FORMATS:
            raise TargetFileError(f"unknown targets format {given!r}; allowed: auto, {', '.join(FORMATS)}")
        return given
    fmt = SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        raise TargetFileError(f"{path}: cannot tell the format from the suffix {path.suffix!r} (known: "
                              f"{', '.join(f'{k} → {v}' for k, v in SUFFIXES.items())}); give --format")
    return fmt


def read_targets(path: str | Path, fmt: str = "auto") -> TargetFile:
    path = Path(path)
    fmt = target_format(path, fmt)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise TargetFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # KRL and RAPID files are often Windows-1252; bytes kept as they are
    reader = {"csv": _read_csv, "kuka": _read_kuka, "rapid": _read_rapid}[fmt]
    out = reader(path, text)
    if not out.targets:
        what = {"csv": "data rows", "kuka": "DECL E6POS/POS declarations", "rapid": "robtarget declarations"}[fmt]
        raise TargetFileError(f"{path}: no {what} found: nothing to compensate")
    return out


def _line_of(text: str, pos: int) -> int:
    return text.count("\n", 0, pos) + 1


def _number(path: Path, line: int, name: str, key: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise TargetFileError(f"{path}:{line}: {name}: field {key} is {text!r}, not a number") from None
    if not math.isfinite(v):
        raise TargetFileError(f"{path}:{line}: {name}: field {key} is {text!r}; allowed: a finite number")
    return v


# --- csv ----------------------------------------------------------------------------------------
_CSV_POSE = ("x", "y", "z", "a", "b", "c")


def _read_csv(path: Path, text: str) -> TargetFile:
    rows = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        return TargetFile(path, "csv", [])
    hline, header = rows[0]
    cols = [c.strip().lower() for c in header.split(",")]
    missing = [c for c in ("name",) + _CSV_POSE if c not in cols]
    if missing:
        raise TargetFileError(f"{path}:{hline}: header lacks {', '.join(missing)}; expected name,x,y,z,a,b,c[,q1,…,qn] "
                              "(mm; A, B, C ZYX Euler degrees; q joint angles in degrees)")
    qcols = [c for c in cols if re.fullmatch(r"q\d+", c)]
    if qcols and qcols != [f"q{i + 1}" for i in range(len(qcols))]:
        raise TargetFileError(f"{path}:{hline}: joint columns must be q1, q2, … in order; given {', '.join(qcols)}")
    targets = []
    for line, ln in rows[1:]:
        cells = [c.strip() for c in ln.split(",")]
        if len(cells) != len(cols):
            raise TargetFileError(f"{path}:{line}: {len(cells)} fields, the header has {len(cols)}")
        rec = dict(zip(cols, cells))
        name = rec["name"] or f"row{line}"
        values = tuple(_number(path, line, name, k, rec[k]) for k in _CSV_POSE)
        config = {}
        if qcols:
            config["joints_deg"] = [_number(path, line, name, k, rec[k]) for k in qcols]
        targets.append(Target(name, line, values, config))
    return TargetFile(path, "csv", targets, n_joints_columns=len(qcols))


def write_csv(path: Path, rows: list[tuple], joint_names: list[str]) -> None:
    """rows: (name, (x, y, z, a, b, c), joint targets deg or None, shift mm[, arm angle rad or None]);
    an ``arm_angle_deg`` column when a row has an arm angle (7-axis arms)."""
    with_psi = any(len(r) > 4 and r[4] is not None for r in rows)
    head = ["name", *_CSV_POSE, *[f"q{i + 1}" for i in range(len(joint_names))], "shift_mm"] + (["arm_angle_deg"] if with_psi else [])
    lines = [",".join(head)]
    for row in rows:
        name, pose, joints, shift = row[:4]
        cells = [name] + [f"{v:.6f}" for v in pose]
        cells += [f"{v:.6f}" for v in joints] if joints is not None else [""] * len(joint_names)
        cells.append(f"{shift:.6f}")
        if with_psi:
            cells.append("" if len(row) < 5 or row[4] is None else f"{math.degrees(row[4]):.6f}")
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


# --- KUKA KRL .dat ------------------------------------------------------------------------------
_KUKA_DECL = re.compile(r"^[ \t]*DECL[ \t]+(?:GLOBAL[ \t]+)?(E6POS|POS)[ \t]+(\w+)[ \t]*=[ \t]*\{([^}\n]*)\}",
                        re.IGNORECASE | re.MULTILINE)
_KUKA_ANY = re.compile(r"^[ \t]*DECL[ \t]+(?:GLOBAL[ \t]+)?(?:E6POS|POS)[ \t]+\w+[ \t]*=", re.IGNORECASE | re.MULTILINE)
_KUKA_FIELD = re.compile(r"([A-Za-z]\w*)[ \t]+(" + _NUM + r"|'[^']*')")
_KUKA_POSE = ("X", "Y", "Z", "A", "B", "C")


def _read_kuka(path: Path, text: str) -> TargetFile:
    targets = []
    for m in _KUKA_DECL.finditer(text):
        line = _line_of(text, m.start())
        name, body, at = m.group(2), m.group(3), m.start(3)
        fields: dict[str, tuple[str, int, int]] = {}
        for f in _KUKA_FIELD.finditer(body):
            key = f.group(1).upper()
            if key in fields:
                raise TargetFileError(f"{path}:{line}: {name}: field {key} appears twice")
            fields[key] = (f.group(2), at + f.start(2), at + f.end(2))
        missing = [k for k in _KUKA_POSE if k not in fields]
        if missing:
            raise TargetFileError(f"{path}:{line}: {name}: no {', '.join(missing)} (a partial {m.group(1).upper()} aggregate); "
                                  "allowed: a complete declaration {X …, Y …, Z …, A …, B …, C …, S …, T …}")
        values = tuple(_number(path, line, name, k, fields[k][0]) for k in _KUKA_POSE)
        config = {}
        for key in ("S", "T"):
            if key in fields:
                v = _number(path, line, name, key, fields[key][0])
                if v != int(v) or v < 0:
                    raise TargetFileError(f"{path}:{line}: {name}: field {key} is {fields[key][0]}; allowed: a whole number ≥ 0 (bits)")
                config[key] = int(v)
        targets.append(Target(name, line, values, config, [fields[k][1:] for k in _KUKA_POSE]))
    _all_understood(path, text, _KUKA_ANY, targets, "an E6POS/POS declaration", "DECL E6POS NAME={X …, Y …, Z …, A …, B …, C …, …} on one line")
    return TargetFile(path, "kuka", targets, text)


def _all_understood(path: Path, text: str, anywhere: re.Pattern, targets: list[Target], what: str, allowed: str) -> None:
    """Refuse a file with a declaration the reader did not take: it would stay uncompensated unseen."""
    read = {t.line for t in targets}
    for m in anywhere.finditer(text):
        line = _line_of(text, m.start())
        if line not in read:
            raise TargetFileError(f"{path}:{line}: {what} this reader does not understand (an array, or a layout other than "
                                  f"{allowed}): it would be left uncompensated — write it out as single targets")


# --- ABB RAPID ----------------------------------------------------------------------------------
_RAPID_DECL = re.compile(r"\b(?:CONST|PERS|VAR)\s+robtarget\s+(\w+)\s*:=\s*\[\s*\[([^\]]*)\]\s*,\s*"
                         r"\[([^\]]*)\]\s*,\s*\[([^\]]*)\]", re.IGNORECASE)
_RAPID_ANY = re.compile(r"\b(?:CONST|PERS|VAR)\s+robtarget\b", re.IGNORECASE)


def _rapid_numbers(path: Path, line: int, name: str, what: str, body: str, at: int, n: int) -> list[tuple[float, int, int]]:
    parts = []
    pos = 0
    for cell in body.split(","):
        stripped = cell.strip()
        start = at + pos + cell.index(stripped) if stripped else at + pos
        parts.append((stripped, start, start + len(stripped)))
        pos += len(cell) + 1
    if len(parts) != n:
        raise TargetFileError(f"{path}:{line}: {name}: {what} has {len(parts)} numbers; allowed: {n}")
    return [(_number(path, line, name, what, p), s, e) for p, s, e in parts]


def _read_rapid(path: Path, text: str) -> TargetFile:
    targets = []
    for m in _RAPID_DECL.finditer(text):
        line = _line_of(text, m.start())
        name = m.group(1)
        pos = _rapid_numbers(path, line, name, "trans [x,y,z]", m.group(2), m.start(2), 3)
        quat = _rapid_numbers(path, line, name, "rot [q1,q2,q3,q4]", m.group(3), m.start(3), 4)
        conf = _rapid_numbers(path, line, name, "robconf [cf1,cf4,cf6,cfx]", m.group(4), m.start(4), 4)
        norm = math.sqrt(sum(v * v for v, _, _ in quat))
        if abs(norm - 1.0) > 1e-3:
            raise TargetFileError(f"{path}:{line}: {name}: the quaternion's norm is {norm:.6f}; allowed: a unit quaternion "
                                  "(RAPID's tolerance ±0.001)")
        values = tuple(v for v, _, _ in pos) + tuple(v / norm for v, _, _ in quat)
        targets.append(Target(name, line, values, {"cf": [int(v) for v, _, _ in conf]},
                              [(s, e) for _, s, e in pos + quat]))
    _all_understood(path, text, _RAPID_ANY, targets, "a robtarget declaration", "name:=[[x,y,z],[q1,q2,q3,q4],[cf1,cf4,cf6,cfx],[eax…]]")
    return TargetFile(path, "rapid", targets, text)


def write_patched(tf: TargetFile, new_values: dict[str, tuple[float, ...]], path: Path) -> None:
    """Write ``tf``'s text to ``path`` with the values of the targets named in ``new_values``
    replaced (kuka: X…C; rapid: x, y, z, q1…q4) and every other byte as it was."""
    if tf.text is None:
        raise ValueError("write_patched applies to kuka and rapid files")
    edits = []
    for t in tf.targets:
        if t.name not in new_values:
            continue
        vals = new_values[t.name]
        if tf.format == "kuka":
            texts = [f"{v:.4f}" for v in vals[:3]] + [f"{v:.5f}" for v in vals[3:]]
        else:
            texts = [f"{v:.4f}" for v in vals[:3]] + [f"{v:.9f}" for v in vals[3:]]
        edits += [(s, e, txt) for (s, e), txt in zip(t.spans, texts)]
    out, last = [], 0
    for s, e, txt in sorted(edits):
        out += [tf.text[last:s], txt]
        last = e
    out.append(tf.text[last:])
    data = "".join(out)
    try:
        path.write_bytes(data.encode("utf-8") if _is_utf8(tf.path) else data.encode("latin-1"))
    except UnicodeEncodeError as exc:
        raise TargetFileError(f"{path}: cannot write: {exc}") from None


def _is_utf8(path: Path) -> bool:
    try:
        path.read_bytes().decode("utf-8")
        return True
    except (OSError, UnicodeDecodeError):
        return False
