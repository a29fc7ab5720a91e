"""Read the public IPA robot-accuracy series (a UR10 measured by a Leica tracker with a T-Mac)
as they are, into pose datasets (``calib.measure.dataset.Dataset`` with orientation).

Files (``../shared/fixtures/ur10-ipa-tracker-6dof/``, MIT; Landgraf et al., IEEE CASE 2021):
``;`` between fields, decimal commas, the first line names the columns. Used columns:

``shoulder_pan_joint`` … ``wrist_3_joint``  joint angles, **radians** (ROS UR naming, θ = q)
``measurement_x/y/z``                       the T-Mac's origin in the tracker frame, mm
``measurement_rx/ry/rz``                    its orientation, **degrees**, intrinsic X-Y-Z Euler
                                            angles: R_tracker←T-Mac = Rx(rx)·Ry(ry)·Rz(rz)
``measurement_std_*``                       per-axis standard deviations of the samples (mm, °);
                                            optional: without them the rows carry no spread (NaN),
                                            and ``acquire fit`` estimates the noise from the data
                                            (``calib.fit.noise``)

The attitude spread of a row is the RMS of its three angle deviations (for these small, near
orthogonal angles a fair per-axis figure for the rotation vector). ``Timestamp`` lost its
precision in a spreadsheet and is not used.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from calib.io import csvdialect
from calib.measure.dataset import Dataset, DatasetError, from_arrays
from calib.robot.transforms import rot_x, rot_y, rot_z

JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
POSITION = tuple(f"measurement_{c}" for c in "xyz")
ANGLES = tuple(f"measurement_r{c}" for c in "xyz")


def euler_xyz_intrinsic(rx: np.ndarray, ry: np.ndarray, rz: np.ndarray) -> np.ndarray:
    """R = Rx(rx)·Ry(ry)·Rz(rz) (intrinsic X-Y-Z), angles in rad; (..., 3, 3)."""
    return rot_x(rx) @ rot_y(ry) @ rot_z(rz)


def is_ipa_series(path: str | Path) -> bool:
    """Whether the first line of ``path`` is an IPA series header (';'-separated, the UR joint and
    ``measurement_*`` columns): ``acquire fit`` then reads it with ``read_ipa_series``."""
    try:
        with open(path, "rb") as f:
            head = f.readline(4096).decode("utf-8-sig", errors="replace")
    except OSError:
        return False
    cells = [c.strip() for c in head.strip().split(";")]
    return all(c in cells for c in (*JOINTS, *POSITION))


def read_ipa_series(path: str | Path, *, marker: str = "tmac", sensor: str = "tracker", prefix: str = "") -> Dataset:
    """Every row of one IPA series as a pose dataset (configuration ids ``{prefix}c{row}``).

    Raises DatasetError naming the file, line and column for a missing column, a cell that is
    not a number, or a row with the wrong number of fields."""
    path = Path(path)
    try:
        text = csvdialect.decode(path.read_bytes(), str(path), DatasetError)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    lines = csvdialect.content_lines(text)
    if len(lines) < 2:
        raise DatasetError(f"{path}: no header and data")
    head_no, head = lines[0]
    header = csvdialect.split(head, ";")
    spreads = [f"measurement_std_{c}" for c in ("x", "y", "z", "rx", "ry", "rz")]
    has_spread = all(c in header for c in spreads)
    need = [*JOINTS, *POSITION, *ANGLES, *(spreads if has_spread else ())]
    missing = [c for c in need if c not in header]
    if missing:
        raise DatasetError(f"{path}:{head_no}: missing column(s) {missing}; this reader expects the IPA series format "
                           "(';'-separated, decimal comma; the measurement_std_* columns all or none)")
    col = {h: i for i, h in enumerate(header)}
    rows = []
    for no, line in lines[1:]:
        cells = csvdialect.split(line, ";")
        if len(cells) != len(header):
            raise DatasetError(csvdialect.width_error(str(path), no, cells, len(header), csvdialect.Dialect(";", ",")))
        vals = []
        for c in need:
            try:
                v = csvdialect.number(cells[col[c]], ",")
            except ValueError:
                raise DatasetError(f"{path}:{no}: column '{c}': {cells[col[c]]!r} is not a number (decimal comma)") from None
            if not math.isfinite(v):
                raise DatasetError(f"{path}:{no}: column '{c}': {cells[col[c]]!r} is not a finite number")
            vals.append(v)
        rows.append(vals)
    a = np.array(rows)
    q = a[:, :6]
    if np.abs(q).max() > 2 * math.pi + 0.1:
        raise DatasetError(f"{path}: joint angles up to {np.abs(q).max():.1f}: the series gives radians (±2π)")
    xyz = a[:, 6:9]
    rot = euler_xyz_intrinsic(*np.radians(a[:, 9:12]).T)
    if has_spread:
        std_mm = np.sqrt(np.mean(a[:, 12:15] ** 2, axis=1))
        att = np.radians(np.sqrt(np.mean(a[:, 15:18] ** 2, axis=1)))
    else:
        std_mm = att = np.full(len(a), np.nan)
    ds = from_arrays(q, xyz, marker=marker, sensor=sensor, config=np.array([f"{prefix}c{i}" for i in range(len(a))]),
                     std_mm=std_mm, count=np.full(len(a), 1 if has_spread else 0), rot=rot, att_std_rad=att)
    return replace(ds, source=str(path))
