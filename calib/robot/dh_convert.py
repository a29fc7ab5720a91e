"""Joint axes in space → a DH or modified-DH (Hayati) table with the same forward kinematics.

Input: the joint axes of a serial arm at its zero configuration, as lines in the base frame
(a point, mm, and a unit direction each: the DH z axis, i.e. the axis direction times the
controller's sign), and the tip frame at the zero configuration. Output: the base frame, one
link per joint (``Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)``, ``calib.robot.model``) and the flange frame, such
that the chain reproduces every configuration exactly (not only the zero one): link ``i``'s z
axis is joint ``i + 1``'s axis line, so rotating joint ``i`` by ``sign·q`` about it is what the
source model does.

Per pair of consecutive axes:

* not parallel: the common normal (standard DH; β = 0), x along ``z_i × z_{i+1}`` with the sign
  that keeps |θ| ≤ 90°;
* parallel or near-parallel (within ``NEAR_PARALLEL_DEG``) in an ``mdh`` table: Hayati's link,
  d = 0 (the next frame's origin is where the next axis crosses the plane normal to this one
  through this frame's origin) and the misalignment in α and β — well conditioned where the
  common normal runs off to infinity;
* exactly parallel in a ``dh`` table: the same construction with β = 0 (the classic d = 0
  choice for parallel axes).

Nothing here reads files: ``calib.robot.urdf`` supplies the lines from a URDF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.robot.transforms import homogeneous, invert, matrix_to_euler_zyx, rot_x, rot_y, rot_z

#: Consecutive axes closer to parallel than this (degrees) make ``auto`` choose ``mdh`` and get a
#: Hayati link: a common normal at 5° already puts the DH frame about 11 link lengths away.
NEAR_PARALLEL_DEG = 5.0
#: Axes within this angle (rad) count as exactly parallel (a dh table then drops β).
PARALLEL_EPS = 1e-9


@dataclass(frozen=True)
class AxisLine:
    """One joint axis at the zero configuration, base frame: ``point`` (3,) mm on the axis,
    ``direction`` (3,) unit vector of the DH z axis (positive rotation = positive DH angle)."""

    point: np.ndarray
    direction: np.ndarray


@dataclass(frozen=True)
class Link:
    """One link's parameters: theta, alpha, beta in rad; d, a in mm."""

    theta: float
    d: float
    a: float
    alpha: float
    beta: float = 0.0


@dataclass
class DHTable:
    """``base2frame0`` (4, 4) mm; ``links`` one per joint; ``frames`` (n + 1) DH frames in the base
    frame at the zero configuration, (4, 4) mm each; ``lastframe2flange`` (4, 4) mm; ``notes``
    says which pairs were near-parallel and how they were treated."""

    convention: str
    base2frame0: np.ndarray
    links: list[Link]
    frames: list[np.ndarray]
    lastframe2flange: np.ndarray
    notes: list[str] = field(default_factory=list)


def link_matrix(link: Link) -> np.ndarray:
    """(4, 4) ``Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)``, mm."""
    t = homogeneous(rot_z(link.theta), np.array([0.0, 0.0, link.d]))
    t = t @ homogeneous(rot_x(link.alpha), np.array([link.a, 0.0, 0.0]))
    return t @ homogeneous(rot_y(link.beta), np.zeros(3))


def _angle_about(u: np.ndarray, v: np.ndarray, axis: np.ndarray) -> float:
    """Signed angle (rad) turning u into v about ``axis`` (u, v ⟂ axis)."""
    return math.atan2(float(np.cross(u, v) @ axis), float(u @ v))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def axis_angle_deg(z0: np.ndarray, z1: np.ndarray) -> float:
    """Angle between two axis lines ignoring direction, degrees in [0, 90]."""
    s = float(np.linalg.norm(np.cross(z0, z1)))
    return math.degrees(math.atan2(s, abs(float(z0 @ z1))))


def choose_convention(lines: list[AxisLine]) -> tuple[str, list[str]]:
    """``mdh`` if any consecutive axes are within ``NEAR_PARALLEL_DEG`` of parallel, else ``dh``;
    and the reasons (pairs by 1-based joint index)."""
    why = []
    for i in range(len(lines) - 1):
        ang = axis_angle_deg(lines[i].direction, lines[i + 1].direction)
        if ang < NEAR_PARALLEL_DEG:
            why.append(f"axes {i + 1} and {i + 2} are {'parallel' if ang < 1e-9 else f'{ang:.3g}° from parallel'}")
    return ("mdh" if why else "dh"), why


def _base_frame(first: AxisLine) -> np.ndarray:
    """Frame 0: z on joint 1's axis, origin where the base origin projects onto it, x the base x
    projected onto the plane normal to the axis (so an axis along base z through the origin gives
    the identity)."""
    z = first.direction
    origin = first.point - (first.point @ z) * z
    for guess in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        x = guess - (guess @ z) * z
        if np.linalg.norm(x) > 1e-6:
            x = _unit(x)
            break
    return homogeneous(np.column_stack([x, np.cross(z, x), z]), origin)


def _common_normal(frame: np.ndarray, nxt: AxisLine) -> Link:
    """Standard DH link from ``frame`` (z = this axis) to a non-parallel next axis."""
    o, x, z = frame[:3, 3], frame[:3, 0], frame[:3, 2]
    zn = nxt.direction
    c = float(z @ zn)
    w0 = o - nxt.point
    dz, dn = float(z @ w0), float(zn @ w0)
    t1 = (c * dn - dz) / (1.0 - c * c)
    t2 = (dn - c * dz) / (1.0 - c * c)
    foot, foot_next = o + t1 * z, nxt.point + t2 * zn
    xn = _unit(np.cross(z, zn))
    if xn @ x < -1e-12:  # keep |θ| ≤ 90°
        xn = -xn
    return Link(theta=_angle_about(x, xn, z), d=t1, a=float((foot_next - foot) @ xn), alpha=_angle_about(z, zn, xn))


def _hayati(frame: np.ndarray, nxt: AxisLine, with_beta: bool) -> Link:
    """Link with d = 0 to a (near-)parallel next axis; α, β take the misalignment (β only if
    ``with_beta``, else the axes must be parallel)."""
    o, x, z = frame[:3, 3], frame[:3, 0], frame[:3, 2]
    zn = nxt.direction
    t = float((o - nxt.point) @ z) / float(zn @ z)
    v = nxt.point + t * zn - o  # in the plane normal to z through o
    a = float(np.linalg.norm(v))
    xn = v / a if a > 1e-9 else x
    if xn @ x < -1e-12:
        xn, a = -xn, -a
    theta = _angle_about(x, xn, z)
    u, vv, w = np.column_stack([xn, np.cross(z, xn), z]).T @ zn
    beta = math.asin(max(-1.0, min(1.0, float(u)))) if with_beta else 0.0
    return Link(theta=theta, d=0.0, a=a, alpha=math.atan2(-float(vv), float(w)), beta=beta)


def _last_link(frame: np.ndarray, tip: np.ndarray) -> Link:
    """The last joint's link: d to the tip's foot on the axis, x towards the tip's x (projected),
    a the tip's offset along that x; the rest goes into the flange transform."""
    o, x, z = frame[:3, 3], frame[:3, 0], frame[:3, 2]
    xt = tip[:3, 0] - (tip[:3, 0] @ z) * z
    xn = _unit(xt) if np.linalg.norm(xt) > 1e-6 else x
    rel = tip[:3, 3] - o
    return Link(theta=_angle_about(x, xn, z), d=float(rel @ z), a=float(rel @ xn), alpha=0.0)


def dh_from_axes(lines: list[AxisLine], tip: np.ndarray, convention: str = "auto") -> DHTable:
    """A DH (``dh``) or Hayati (``mdh``) table whose kinematics equal the given axes.

    lines: per joint, its axis at the zero configuration (base frame, mm, unit DH z direction).
    tip: (4, 4) the tip (flange) frame in the base frame at the zero configuration, mm.
    convention: ``dh``, ``mdh`` or ``auto`` (``choose_convention``).
    """
    if convention not in ("dh", "mdh", "auto"):
        raise ValueError(f"convention must be dh, mdh or auto, given {convention!r}")
    if not lines:
        raise ValueError("no joint axes given")
    notes: list[str] = []
    if convention == "auto":
        convention, why = choose_convention(lines)
        notes.append(f"convention {convention}: " + ("; ".join(why) if why else "no consecutive axes are near-parallel"))
    near = math.sin(math.radians(NEAR_PARALLEL_DEG))
    frame0 = _base_frame(lines[0])
    frames = [frame0]
    links: list[Link] = []
    for i in range(len(lines) - 1):
        frame, nxt = frames[-1], lines[i + 1]
        s = float(np.linalg.norm(np.cross(frame[:3, 2], nxt.direction)))
        if s <= PARALLEL_EPS:
            link = _hayati(frame, nxt, with_beta=False)
        elif s < near and convention == "mdh":
            link = _hayati(frame, nxt, with_beta=True)
            notes.append(f"axes {i + 1} and {i + 2}: Hayati link (β = {math.degrees(link.beta):.4g}°)")
        else:
            link = _common_normal(frame, nxt)
            if s < near:
                notes.append(f"axes {i + 1} and {i + 2} are near-parallel in a dh table: common normal d = "
                             f"{link.d:.4g} mm (use --convention mdh for a well-conditioned table)")
        links.append(link)
        frames.append(frame @ link_matrix(link))
    last = _last_link(frames[-1], tip)
    links.append(last)
    frames.append(frames[-1] @ link_matrix(last))
    return DHTable(convention, frame0, links, frames, invert(frames[-1]) @ tip, notes)


def frame_to_yaml(t: np.ndarray) -> dict:
    """(4, 4) mm → ``calib.robot.model.Frame`` fields: xyz mm, zyx deg (yaw, pitch, roll)."""
    return {"xyz": [float(v) for v in t[:3, 3]], "zyx": [float(v) for v in np.degrees(matrix_to_euler_zyx(t[:3, :3]))]}
