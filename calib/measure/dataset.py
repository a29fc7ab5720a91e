"""Measurement datasets: what the fitter consumes, and its CSV format.

One row per measurement of one marker by one sensor in one robot configuration:

``config``   configuration id (text); rows of one configuration share their joint angles
``pose``     pose group (configurations that target the same Cartesian pose); may be empty
``q1``…``qN`` joint angles as the controller measured them, **degrees** (a file whose angles look
             like radians is refused: ``calib.measure.units``)
``x,y,z``    marker position in the sensor frame, **mm** (the mean of the samples)
``marker``   optional, marker name on the tool (default: the model's first marker)
``sensor``   optional, sensor name (default ``sensor``)
``std_mm``   optional, spread of the samples (per-axis standard deviation), mm
``n``        optional, number of samples averaged
``split``    optional, ``cal`` or ``val`` (calibration or validation part)
``qw,qx,qy,qz`` optional, all four together: the measured **orientation** of the target's frame
             (a 6-DoF target: a Motive rigid body, a T-Mac, a probe) as a unit quaternion,
             **scalar first**, Hamilton convention, rotating target-frame vectors into the sensor
             frame (``R_sensor←target``; ``x,y,z`` is then that frame's origin). A row may leave
             all four empty (a position-only row); a norm off 1 by more than 1e-3 is refused
             (normalised otherwise).
``std_deg``  optional, attitude spread of the samples (standard deviation per axis of the
             rotation vector), **degrees**

Lines starting with ``#`` are comments. Everything in memory is mm and radians.

Spreadsheet exports are read as they are meant (``calib.io.csvdialect``): ``;`` or tab between
fields, decimal commas (``12,5``), a UTF-8 byte-order mark. What cannot be read unambiguously
(mixed separators or decimal marks, decimal commas in a comma-separated file without quotes,
another encoding) is refused with a message that names it.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calib.io import csvdialect
from calib.robot.model import RobotModel
from calib.measure.units import radians_row
from calib.robot.transforms import matrix_to_quat, quat_to_matrix


class DatasetError(ValueError):
    """A dataset that cannot be fitted; the message names the file, row and column."""


@dataclass(frozen=True)
class Dataset:
    """Measured marker positions with the joint angles the robot reported.

    q_rad: (k, n) controller convention; xyz_mm: (k, 3) sensor frame; std_mm: (k,) (NaN when
    unknown); count: (k,) samples per row (0 when unknown); the rest are (k,) string arrays.

    Orientation (6-DoF rows), None when no row has one: rot: (k, 3, 3) ``R_sensor←target`` of
    the measured target frame (NaN for rows without orientation); att_std_rad: (k,) attitude
    spread per axis, rad (NaN when unknown).
    """

    config: np.ndarray
    pose: np.ndarray
    q_rad: np.ndarray
    xyz_mm: np.ndarray
    marker: np.ndarray
    sensor: np.ndarray
    std_mm: np.ndarray
    count: np.ndarray
    split: np.ndarray
    source: str = ""
    rot: np.ndarray | None = None
    att_std_rad: np.ndarray | None = None
    #: True when ``std_mm`` / ``att_std_rad`` were estimated from the data's residuals
    #: (``calib.fit.noise``), not stated by the sensor: no guard may judge a model against them.
    spreads_estimated: bool = False

    def __len__(self) -> int:
        return int(self.q_rad.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.q_rad.shape[1])

    @property
    def sensors(self) -> list[str]:
        return sorted(set(self.sensor.tolist()))

    @property
    def oriented(self) -> np.ndarray:
        """(k,) bool: rows that carry a measured orientation."""
        if self.rot is None:
            return np.zeros(len(self), bool)
        return np.isfinite(self.rot).all(axis=(1, 2))

    @property
    def has_orientation(self) -> bool:
        return bool(self.oriented.any())

    def without_orientation(self) -> "Dataset":
        """The same rows as position-only measurements."""
        return replace(self, rot=None, att_std_rad=None)

    def subset(self, mask: np.ndarray) -> "Dataset":
        mask = np.asarray(mask)
        fields = _FIELDS + (("rot", "att_std_rad") if self.rot is not None else ())
        return replace(self, **{f: getattr(self, f)[mask] for f in fields})

    def calibration(self) -> "Dataset":
        return self.subset(self.split != "val")

    def validation(self) -> "Dataset":
        return self.subset(self.split == "val")

    def with_split(self, split: str) -> "Dataset":
        return replace(self, split=np.full(len(self), split))

    def concat(self, other: "Dataset") -> "Dataset":
        if other.n_joints != self.n_joints:
            raise DatasetError(f"cannot join datasets with {self.n_joints} and {other.n_joints} joints")
        out = {f: np.concatenate([getattr(self, f), getattr(other, f)]) for f in _FIELDS}
        if self.rot is not None or other.rot is not None:
            out["rot"] = np.concatenate([_rot_or_nan(self), _rot_or_nan(other)])
            out["att_std_rad"] = np.concatenate([_att_or_nan(self), _att_or_nan(other)])
        return replace(self, **out, source=f"{self.source}+{other.source}")


_FIELDS = ("config", "pose", "q_rad", "xyz_mm", "marker", "sensor", "std_mm", "count", "split")


def _rot_or_nan(ds: Dataset) -> np.ndarray:
    return ds.rot if ds.rot is not None else np.full((len(ds), 3, 3), np.nan)


def _att_or_nan(ds: Dataset) -> np.ndarray:
    return ds.att_std_rad if ds.att_std_rad is not None else np.full(len(ds), np.nan)


def from_arrays(
    q_rad: np.ndarray,
    xyz_mm: np.ndarray,
    *,
    marker: str | np.ndarray = "",
    sensor: str | np.ndarray = "sensor",
    pose: np.ndarray | None = None,
    config: np.ndarray | None = None,
    std_mm: np.ndarray | None = None,
    count: np.ndarray | None = None,
    split: str | np.ndarray = "cal",
    rot: np.ndarray | None = None,
    att_std_rad: np.ndarray | float | None = None,
) -> Dataset:
    """Build a dataset in memory (simulations, MCAP logs). rot: (k, 3, 3) measured target
    orientations ``R_sensor←target`` (NaN rows: not measured); att_std_rad: their spread per axis."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    k = q.shape[0]
    xyz = np.asarray(xyz_mm, dtype=float).reshape(k, 3)

    def col(v, default):
        if v is None:
            v = default
        arr = np.asarray(v)
        return np.broadcast_to(arr, (k,)).copy() if arr.ndim == 0 else arr

    return Dataset(
        config=col(config, np.arange(k).astype(str)).astype(str),
        pose=col(pose, "").astype(str),
        q_rad=q,
        xyz_mm=xyz,
        marker=col(marker, "").astype(str),
        sensor=col(sensor, "sensor").astype(str),
        std_mm=col(std_mm, np.nan).astype(float),
        count=col(count, 0).astype(int),
        split=col(split, "cal").astype(str),
        rot=None if rot is None else np.asarray(rot, dtype=float).reshape(k, 3, 3),
        att_std_rad=None if rot is None else col(att_std_rad, np.nan).astype(float),
    )


def read_csv(path: str | Path, model: RobotModel) -> Dataset:
    """Read a measurement CSV (format in the module docstring) and check it against ``model``.

    Raises DatasetError naming the file, line and column for: missing columns, wrong column
    counts, non-numbers and NaNs, a joint count that does not match the model, unknown markers,
    joint angles outside ±720°, and positions that look like metres rather than mm.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    return parse_csv(csvdialect.decode(raw, str(path), DatasetError), model, source=str(path))


def parse_csv(text: str, model: RobotModel, *, source: str = "<csv>") -> Dataset:
    """Parse CSV text; see ``read_csv`` (separator and decimal mark: ``calib.io.csvdialect``)."""
    lines = csvdialect.content_lines(text)
    if not lines:
        raise DatasetError(f"{source}: no header and no data")
    header_line, header_text = lines[0]
    sep = csvdialect.sniff_separator(header_text, source, header_line, DatasetError)
    rows: list[tuple[int, list[str]]] = [(no, csvdialect.split(line, sep)) for no, line in lines]
    header = rows[0][1]
    csvdialect.check_unique(header, source, header_line, DatasetError)
    qcols = sorted((h for h in header if h[:1] == "q" and h[1:].isdigit()), key=lambda h: int(h[1:]))
    n = model.n_joints
    if [int(h[1:]) for h in qcols] != list(range(1, len(qcols) + 1)):
        raise DatasetError(f"{source}:{header_line}: joint columns must be q1…qN without gaps, got {qcols}")
    if len(header) == 1:
        raise DatasetError(f"{source}:{header_line}: the header is one column (given {header_text.strip()!r}); "
                           f"allowed: config, q1…q{n}, x, y, z, … separated by commas, semicolons or tabs")
    if len(qcols) != n:
        raise DatasetError(
            f"{source}:{header_line}: {len(qcols)} joint columns (q1…q{len(qcols)}) but the robot model "
            f"'{model.name}' has {n} joints"
        )
    required = ["config", "x", "y", "z"]
    missing = [c for c in required if c not in header]
    if missing:
        raise DatasetError(f"{source}:{header_line}: missing column(s) {missing}; required: config, q1…q{n}, x, y, z")
    known = set(required) | set(qcols) | {"pose", "marker", "sensor", "std_mm", "n", "split", *QUAT, "std_deg"}
    unknown = [h for h in header if h not in known]
    if unknown:
        raise DatasetError(f"{source}:{header_line}: unknown column(s) {unknown}; allowed: {sorted(known)}")
    idx = {h: i for i, h in enumerate(header)}
    partial = [c for c in QUAT if c in idx]
    if partial and len(partial) != 4:
        raise DatasetError(f"{source}:{header_line}: orientation columns {partial} without {[c for c in QUAT if c not in idx]}; "
                           "an orientation needs all four of qw, qx, qy, qz (unit quaternion, scalar first)")
    if "std_deg" in idx and not partial:
        raise DatasetError(f"{source}:{header_line}: column 'std_deg' (attitude spread) without orientation columns qw, qx, qy, qz")
    data = rows[1:]
    if not data:
        raise DatasetError(f"{source}: header only, no measurements")
    numeric = [idx[h] for h in [*qcols, "x", "y", "z", "std_mm", "n", *QUAT, "std_deg"] if h in idx]
    dialect = csvdialect.Dialect(sep, csvdialect.sniff_decimal(data, numeric, source, DatasetError))

    def number(lineno: int, row: list[str], name: str, allow_empty: bool = False) -> float:
        raw = row[idx[name]].strip()
        if raw == "" and allow_empty:
            return math.nan
        try:
            v = csvdialect.number(raw, dialect.decimal)
        except ValueError:
            raise DatasetError(f"{source}:{lineno}: column '{name}': {raw!r} is not a number "
                               f"(this file is {dialect.describe()})") from None
        if not math.isfinite(v):
            raise DatasetError(f"{source}:{lineno}: column '{name}': {raw!r} is not a finite number")
        return v

    cols: dict[str, list] = {k: [] for k in ("config", "pose", "q", "xyz", "marker", "sensor", "std", "n", "split", "quat", "att")}
    default_marker = model.marker_names[0]
    for lineno, row in data:
        if len(row) != len(header):
            raise DatasetError(csvdialect.width_error(source, lineno, row, len(header), dialect))
        cols["config"].append(row[idx["config"]].strip())
        cols["pose"].append(row[idx["pose"]].strip() if "pose" in idx else "")
        q = [number(lineno, row, h) for h in qcols]
        for h, v in zip(qcols, q):
            if abs(v) > 720:
                raise DatasetError(f"{source}:{lineno}: column '{h}': {v} is outside ±720; joint angles are in degrees")
        cols["q"].append(q)
        cols["xyz"].append([number(lineno, row, c) for c in "xyz"])
        mk = row[idx["marker"]].strip() if "marker" in idx else ""
        mk = mk or default_marker
        if mk not in model.marker_names:
            raise DatasetError(f"{source}:{lineno}: column 'marker': {mk!r} is not on the tool; markers: {model.marker_names}")
        cols["marker"].append(mk)
        cols["sensor"].append((row[idx["sensor"]].strip() if "sensor" in idx else "") or "sensor")
        std = number(lineno, row, "std_mm", allow_empty=True) if "std_mm" in idx else math.nan
        if std < 0:
            raise DatasetError(f"{source}:{lineno}: column 'std_mm': {std} is negative")
        cols["std"].append(std)
        cnt = number(lineno, row, "n", allow_empty=True) if "n" in idx else math.nan
        cols["n"].append(0 if math.isnan(cnt) else int(cnt))
        sp = (row[idx["split"]].strip() if "split" in idx else "") or "cal"
        if sp not in ("cal", "val"):
            raise DatasetError(f"{source}:{lineno}: column 'split': {sp!r} is not 'cal' or 'val'")
        cols["split"].append(sp)
        if partial:
            cols["quat"].append(_quaternion(lineno, row, idx, number, source))
            att = number(lineno, row, "std_deg", allow_empty=True) if "std_deg" in idx else math.nan
            if att < 0 or att > 90:
                raise DatasetError(f"{source}:{lineno}: column 'std_deg': {att} is outside 0…90 (attitude spread in degrees)")
            cols["att"].append(math.radians(att))
    radians = radians_row(cols["q"], model)
    if radians is not None:  # before the fit: radians barely move the model, so check_units passes them
        row, why = radians
        raise DatasetError(f"{source}:{data[row][0]}: columns 'q1'…'q{n}': {why}; this file needs degrees")
    ds = Dataset(
        config=np.array(cols["config"], dtype=str),
        pose=np.array(cols["pose"], dtype=str),
        q_rad=np.radians(np.array(cols["q"], dtype=float)),
        xyz_mm=np.array(cols["xyz"], dtype=float),
        marker=np.array(cols["marker"], dtype=str),
        sensor=np.array(cols["sensor"], dtype=str),
        std_mm=np.array(cols["std"], dtype=float),
        count=np.array(cols["n"], dtype=int),
        split=np.array(cols["split"], dtype=str),
        source=source,
        rot=quat_to_matrix(np.array(cols["quat"], dtype=float)) if partial else None,
        att_std_rad=np.array(cols["att"], dtype=float) if partial else None,
    )
    check_units(ds, model)
    return ds


#: The orientation columns: a unit quaternion, scalar first (module docstring).
QUAT = ("qw", "qx", "qy", "qz")
#: How far a quaternion's norm may be from 1 (rounding in a file) before it is refused.
QUAT_NORM_TOLERANCE = 1e-3


def _quaternion(lineno: int, row: list[str], idx: dict[str, int], number, source: str) -> list[float]:
    """The row's quaternion (4,) scalar first, or four NaNs when all four cells are empty."""
    cells = [row[idx[c]].strip() for c in QUAT]
    if all(c == "" for c in cells):
        return [math.nan] * 4
    if any(c == "" for c in cells):
        raise DatasetError(f"{source}:{lineno}: orientation {dict(zip(QUAT, cells))} is partly empty; give all four of "
                           "qw, qx, qy, qz or leave all four empty (a position-only row)")
    q = [number(lineno, row, c) for c in QUAT]
    norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        raise DatasetError(f"{source}:{lineno}: columns 'qw'…'qz': the quaternion has norm {norm:.6g}; allowed: a unit "
                           "quaternion (norm 1 within 1e-3), scalar first (w, x, y, z) — Euler angles or a scalar-last "
                           "quaternion are not accepted")
    return q


def write_csv(ds: Dataset, path: str | Path, *, comment: str = "") -> None:
    """Write ``ds`` in the CSV format of this module (degrees, mm)."""
    n = ds.n_joints
    with open(path, "w", newline="", encoding="utf-8") as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        w = csv.writer(fh)
        oriented = ds.has_orientation
        w.writerow(["config", "pose", *[f"q{i + 1}" for i in range(n)], "x", "y", "z", "marker", "sensor", "std_mm", "n", "split",
                    *((*QUAT, "std_deg") if oriented else ())])
        qd = np.degrees(ds.q_rad)
        quat = matrix_to_quat(np.nan_to_num(ds.rot)) if oriented else None
        for i in range(len(ds)):
            std = "" if np.isnan(ds.std_mm[i]) else f"{ds.std_mm[i]:.6g}"
            extra = []
            if oriented:
                ok = bool(ds.oriented[i])
                extra = [f"{v:.12f}" if ok else "" for v in quat[i]]
                extra.append("" if not ok or np.isnan(ds.att_std_rad[i]) else f"{np.degrees(ds.att_std_rad[i]):.6g}")
            w.writerow(
                [ds.config[i], ds.pose[i], *[f"{v:.9g}" for v in qd[i]], *[f"{v:.6f}" for v in ds.xyz_mm[i]],
                 ds.marker[i], ds.sensor[i], std, int(ds.count[i]), ds.split[i], *extra]
            )


def check_units(ds: Dataset, model: RobotModel) -> None:
    """Catch metres-for-mm and radians-for-degrees by comparing distances between measured points
    with the same distances predicted by the nominal model (distances do not depend on the
    sensor registration). Raises DatasetError with the ratio it saw."""
    from calib.robot.kinematics import Chain  # local: keeps module import light

    if len(ds) < 3:
        return
    chain = Chain(model)
    pred = chain.marker_positions(ds.q_rad)
    idx = np.array([model.marker_index(m) for m in ds.marker])
    pred = pred[np.arange(len(ds)), idx]
    rng = np.random.default_rng(0)
    a = rng.integers(0, len(ds), size=min(2000, 4 * len(ds)))
    b = rng.integers(0, len(ds), size=a.size)
    keep = ds.sensor[a] == ds.sensor[b]
    d_meas = np.linalg.norm(ds.xyz_mm[a] - ds.xyz_mm[b], axis=1)[keep]
    d_pred = np.linalg.norm(pred[a] - pred[b], axis=1)[keep]
    ok = d_pred > 1.0
    if ok.sum() < 3:
        return
    ratio = float(np.median(d_meas[ok] / d_pred[ok]))
    where = ds.source or "dataset"
    if not ratio > 1e-6:
        raise DatasetError(
            f"{where}: the measured points do not move while the robot moved them by up to {d_pred.max():.0f} mm "
            "(the same position repeated?): check the sensor stream (frozen, or the wrong marker) before fitting"
        )
    if ratio < 0.05:
        raise DatasetError(
            f"{where}: measured points are {1 / ratio:.0f}× closer together than the robot moved them; "
            "positions look like metres — the format expects millimetres (multiply by 1000)"
        )
    if ratio > 20:
        raise DatasetError(
            f"{where}: measured points are {ratio:.0f}× farther apart than the robot moved them; "
            "joint angles may be radians written as degrees, or positions not in mm"
        )
