"""A NatNet frame as ``MarkerSample`` objects: finding the resolved markers (``drivers.natnet.selection``)
in a ``codec.FrameOfData`` and converting their positions (Motive's unit → mm) and orientations
(Motive's quaternion → rotation matrix)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from drivers.natnet import codec
from drivers.natnet.selection import Resolved
from drivers.protocols import MarkerSample

_NAN3 = np.full(3, np.nan)
_NAN3.flags.writeable = False


def body_rotation(quat_xyzw) -> np.ndarray | None:
    """A rigid body's (or bone's) orientation (3, 3) from its NatNet quaternion.

    Motive sends (qx, qy, qz, qw) — scalar **last** — as float32; the quaternion rotates the
    body's local frame (the one its markers were defined in at creation, origin at the pivot)
    into Motive's streamed world frame, the same frame its position is in (y up by default;
    the streaming "Up Axis" setting turns positions and orientations alike). So the matrix is
    ``R_sensor←body`` as ``calib.measure.dataset`` expects. None for a non-finite or zero
    quaternion."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or n < 0.5:
        return None
    from calib.robot.transforms import quat_to_matrix

    return quat_to_matrix(np.array([q[3], q[0], q[1], q[2]]) / n)


def find_body(rows: np.ndarray, ident: int):
    """The row of ``rows`` (a frame's rigid bodies, labeled or asset markers) with id ``ident``,
    else None."""
    hit = np.flatnonzero(rows["id"] == ident)
    return rows[hit[0]] if hit.size else None


def find_marker(frame: codec.FrameOfData, ident: int):
    """A labeled marker by its composite id, else the same id among 4.1 asset markers."""
    row = find_body(frame.labeled_markers, ident)
    if row is None:
        for asset in frame.assets:
            row = find_body(asset.markers, ident)
            if row is not None:
                break
    return row


def find_bone(frame: codec.FrameOfData, owner: int, bone: int):
    """Bone ``bone`` of skeleton (else 4.1 asset) ``owner``; frame bone ids are matched on
    their low 16 bits (frame data packs owner id << 16 | bone id)."""
    for group in (frame.skeletons, frame.assets):
        for item in group:
            if item.id == owner:
                hit = np.flatnonzero((item.rigid_bodies["id"] & 0xFFFF) == bone)
                if hit.size:
                    return item.rigid_bodies[hit[0]]
    return None


def frame_samples(
    frame: codec.FrameOfData,
    host_time: float,
    resolved: Mapping[str, Resolved],
    plan_names: Iterable[str],
    scale_mm: float,
) -> list[MarkerSample]:
    """One sample per plan marker from ``frame``: resolved markers first (in ``resolved``'s
    order), then every name of ``plan_names`` not yet resolved (invisible, NaN position).

    Positions (3,) are Motive's (its unit × ``scale_mm`` = mm); residuals in mm; ``device_time``
    is the frame's timestamp (s), ``host_time`` the host clock when it arrived (s). A labeled
    marker is visible unless occluded (its predicted position is kept); a rigid body or bone
    while its tracking-valid bit is set, with its rotation (3, 3); a marker missing from the
    frame is invisible at NaN."""
    out = []
    for plan_name, (kind, ident) in resolved.items():
        pos, visible, residual, rotation = _NAN3, False, None, None
        if kind == "lm":
            row = find_marker(frame, ident)
            if row is not None:
                pos = row["pos"].astype(np.float64) * scale_mm
                visible = not (row["params"] & codec.MARKER_OCCLUDED)
                residual = float(row["residual"]) * scale_mm
        else:
            row = (find_body(frame.rigid_bodies, ident) if kind == "rb"
                   else find_bone(frame, *ident))
            if row is not None:
                pos = row["pos"].astype(np.float64) * scale_mm
                visible = bool(row["params"] & codec.RIGID_BODY_TRACKED)
                residual = float(row["mean_error"]) * scale_mm
                rotation = body_rotation(row["quat"]) if visible else None
        if visible and not np.all(np.isfinite(pos)):
            visible = False
        out.append(MarkerSample(plan_name, pos, frame.timestamp, host_time, visible, None, residual,
                                rotation if visible else None))
    for plan_name in plan_names:
        if plan_name not in resolved:
            out.append(MarkerSample(plan_name, _NAN3, frame.timestamp, host_time, False))
    return out
