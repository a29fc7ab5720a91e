"""Canonical answers: one parameter set for one robot, written on the nominal model's branch.

A DH chain describes the same arm with more than one parameter set. Turning link i's end frame
by 180° about its z axis (flipping its x axis) gives the same motion with

    (θ_i, a_i, α_i, β_i) → (θ_i + 180°, −a_i, −α_i, −β_i)   and   θ_{i+1} → θ_{i+1} − 180°

("X" below). With the Hayati torsion (``mdh``) the same turned frame can also be written
(θ_i, a_i, α_i + 180°, 180° − β_i) ("Y"), so (θ_i + 180°, −a_i, −α_i − 180°, β_i − 180°) is the
same link as (θ_i, a_i, α_i, β_i) ("E", no turned frame). A least-squares solve may end on any of
these mirrors; the user reads a joint offset of +177.98° that is really −2.02° and a link length
of −70 mm. ``canonical_params`` picks, among the mirrors, the set nearest the nominal model
(link lengths, twists, torsions and marker positions; then the smallest joint offsets), writes
every offset in (−180°, 180°] and every twist and torsion within 180° of its nominal value, and
checks that the forward kinematics of every measured marker is unchanged.

With link masses (the compliance model) a mirror must carry them too: the model's centres of mass
belong to the nominal model's frames, so a turned frame carries its link's centre turned with it;
``carries_masses_alike`` checks that the fitted set, its masses so carried, has the canonical
set's gravity torques, and ``mirrored_links`` names the links an answer left mirrored has turned.

Where the 180° turn cannot go into the next joint's offset (the last axis, or an axis whose
offset is not fitted), it goes into the marker positions when all measured markers are fitted;
otherwise that mirror is not offered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.robot.gravity import gravity_torques, moved_coms
from calib.robot.kinematics import Chain

#: Weights of the distance to nominal: mm of a link length or marker coordinate per unit, and
#: the weight of a joint offset (rad) — small, so offsets only break ties between mirrors.
LENGTH_SCALE_MM = 100.0
OFFSET_WEIGHT = 0.01
#: Largest change of a measured marker's position (mm) that the mapping may make and still
#: count as the same forward kinematics (rounding of a few products of rotations).
FK_TOLERANCE_MM = 1e-6


def wrap_angle(a):
    """Angles (rad) wrapped to (−π, π]; array or float."""
    out = np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2 * math.pi)
    return float(out) if np.ndim(out) == 0 else out


def wrap_deg(a: float) -> float:
    """An angle in degrees wrapped to (−180, 180]."""
    return math.degrees(wrap_angle(math.radians(a)))


def wrapped_only(chain: Chain, params: np.ndarray) -> np.ndarray:
    """``params`` (P,) with the offsets in (−π, π] and every twist and torsion within π of its
    nominal value: the same kinematics, no mirror mapped."""
    n, nom = chain.n, chain.nominal
    p = np.asarray(params, dtype=float).copy()
    p[:n] = wrap_angle(p[:n])
    for kind in ("alpha", "beta"):
        i = chain.index(kind)
        p[i] = nom[i] + wrap_angle(p[i] - nom[i])
    return p


@dataclass(frozen=True)
class Mapping:
    """The canonical parameter vector (P,), what was changed (one line per link), and the largest
    change of a measured marker's predicted position the mapping made (mm)."""

    params: np.ndarray
    changes: list[str]
    fk_change_mm: float


def canonical_params(chain: Chain, params: np.ndarray, free: set[str], q_rad: np.ndarray,
                     measured_markers: list[str]) -> Mapping:
    """Map ``params`` (P,) onto the nominal model's branch without changing the kinematics.

    free: names of the fitted parameters (a mirror may change only those, or values it leaves
    numerically equal, e.g. a = 0); q_rad (k, n): configurations on which the forward kinematics
    of ``measured_markers`` must stay the same (the data's). Raises nothing: when no mirror is
    nearer nominal, or the check fails, the parameters come back wrapped only.
    """
    n = chain.n
    nom = chain.nominal
    p0 = np.asarray(params, dtype=float).copy()
    mdh = chain.model.convention == "mdh"
    names = chain.param_names
    ms = chain.marker_slice()
    midx = [chain.marker_names.index(m) for m in measured_markers]
    markers_free = all(f"{chain.marker_names[k]}.{c}" in free for k in midx for c in "xyz")

    def link(i, v, pre):
        """Link i's (δ, a, α, β) under variant v with ``pre`` turn from the previous link, or None."""
        d, a, al, be = p0[i], p0[2 * n + i], p0[3 * n + i], p0[4 * n + i]
        if v == "X":
            d, a, al, be = d + math.pi, -a, -al, -be
        elif v == "Y":
            al, be = al + math.pi, math.pi - be
        elif v == "E":
            d, a, al, be = d + math.pi, -a, -al - math.pi, be - math.pi
        if pre and f"{chain.model.axis_names[i]}.offset" in free:
            d -= math.pi
        elif pre and not (i == n - 1 and markers_free):  # the last link's turn goes into the markers
            return None
        new = {"offset": wrap_angle(d), "a": a, "alpha": nom[3 * n + i] + wrap_angle(al - nom[3 * n + i]),
               "beta": nom[4 * n + i] + wrap_angle(be - nom[4 * n + i])}
        old = {"offset": p0[i], "a": p0[2 * n + i], "alpha": p0[3 * n + i], "beta": p0[4 * n + i]}
        for kind, val in new.items():
            name = names[chain.index(kind, i)]
            same = abs(wrap_angle(val - old[kind])) < 1e-12 if kind != "a" else abs(val - old[kind]) < 1e-12
            if not same and name not in free:
                return None
        return new

    def cost(i, new):
        return (abs(new["a"] - nom[2 * n + i]) / LENGTH_SCALE_MM + abs(wrap_angle(new["alpha"] - nom[3 * n + i]))
                + abs(wrap_angle(new["beta"] - nom[4 * n + i])) + OFFSET_WEIGHT * abs(new["offset"]))

    variants = ("id", "X", "Y", "E") if mdh else ("id", "X")
    post = {"id": 0, "X": 1, "Y": 1, "E": 0}
    # Dynamic programme over the links; state: the previous link's end frame turned (1) or not.
    best = {0: (0.0, [])}
    for i in range(n):
        nxt: dict[int, tuple[float, list]] = {}
        for s, (c0, path) in best.items():
            for v in variants:
                new = link(i, v, bool(s))
                if new is None:
                    continue
                s2 = post[v]
                if i == n - 1 and (s2 or (s and f"{chain.model.axis_names[i]}.offset" not in free)) and not markers_free:
                    continue
                c = c0 + cost(i, new)
                if s2 not in nxt or c < nxt[s2][0]:
                    nxt[s2] = (c, path + [(v, bool(s), new)])
        best = nxt
    candidates = sorted(best.values(), key=lambda t: t[0])
    wrapped = wrapped_only(chain, p0)
    base_cost = sum(cost(i, link(i, "id", False)) for i in range(n))
    q = np.asarray(q_rad, dtype=float)
    for c, path in candidates:
        if c >= base_cost - 1e-9:
            break
        cand = _assemble(chain, p0, path)
        if any(v != "id" or pre for v, pre, _ in path):
            cand = _move_markers(chain, p0, cand, q[0], midx)
        change = _fk_change(chain, p0, cand, q, midx)
        marker_cost = np.abs(cand[ms] - nom[ms]).sum() - np.abs(wrapped[ms] - nom[ms]).sum()
        if change > FK_TOLERANCE_MM or c + marker_cost / LENGTH_SCALE_MM >= base_cost - 1e-9:
            continue
        changes = [f"{chain.model.axis_names[i]}: {_describe(v, pre)}" for i, (v, pre, _) in enumerate(path) if v != "id" or pre]
        if not np.allclose(cand[ms], p0[ms]):
            changes.append("marker positions turned with the flange frame")
        return Mapping(cand, changes, change)
    return Mapping(wrapped, [], _fk_change(chain, p0, wrapped, q, midx))


def _describe(v: str, pre: bool) -> str:
    text = {"id": "", "X": "frame turned 180° about z (θ + 180°, −a, −α, −β)",
            "Y": "frame turned 180° about z (α + 180°, 180° − β)", "E": "mirrored link (θ + 180°, −a, −α − 180°, β − 180°)"}[v]
    if pre:
        text = (text + "; " if text else "") + "θ − 180° for the previous frame's turn"
    return text


def _assemble(chain: Chain, p0: np.ndarray, path: list) -> np.ndarray:
    n = chain.n
    p = p0.copy()
    for i, (_, _, new) in enumerate(path):
        p[i], p[2 * n + i], p[3 * n + i], p[4 * n + i] = new["offset"], new["a"], new["alpha"], new["beta"]
    return p


def _move_markers(chain: Chain, p0: np.ndarray, p: np.ndarray, q: np.ndarray, midx: list[int]) -> np.ndarray:
    """Measured markers moved by the rigid transform between the two parameter sets' flange frames
    (constant over configurations when the sets are mirrors; the FK check verifies it)."""
    t_old, t_new = chain.fk(q, p0), chain.fk(q, p)
    rel = np.linalg.solve(t_new, t_old)
    out = p.copy()
    ms = chain.marker_slice()
    mk = p0[ms].reshape(-1, 3).copy()
    mk[midx] = mk[midx] @ rel[:3, :3].T + rel[:3, 3]
    out[ms] = mk.ravel()
    return out


def _fk_change(chain: Chain, p0: np.ndarray, p: np.ndarray, q: np.ndarray, midx: list[int]) -> float:
    """Largest change (mm) of a measured marker's position over the configurations q."""
    if not midx or not len(q):
        return 0.0
    a = chain.marker_positions(q, p0)[:, midx]
    b = chain.marker_positions(q, p)[:, midx]
    return float(np.abs(a - b).max())


#: Largest difference of a gravity torque (N·m) between a fitted parameter set, its masses moved with
#: its frames, and the canonical set that still counts as the same sag (rounding; the sag of 1e-6
#: N·m is ~1e-11 rad).
TORQUE_TOLERANCE_NM = 1e-6


def carries_masses_alike(chain: Chain, q: np.ndarray, fitted: np.ndarray, mapped: np.ndarray) -> bool:
    """Whether the canonical set ``mapped`` (P,) predicts the same sag as the ``fitted`` one: the
    model's centres of mass belong to the nominal model's frames (``mapped``'s branch); carried into
    the fitted set's frames (``calib.robot.gravity.moved_coms``) they must give the same gravity
    torques at every configuration q (u, n) rad, to ``TORQUE_TOLERANCE_NM``. A mapping that keeps the
    measured markers' positions but moves an intermediate frame differently fails it and is refused."""
    coms = moved_coms(chain, fitted, mapped, q[0])
    gap = float(np.abs(gravity_torques(chain, q, fitted, coms) - gravity_torques(chain, q, mapped)).max())
    return gap <= TORQUE_TOLERANCE_NM


#: A link whose fitted twist or torsion lies more than this from its nominal value (rad), or whose
#: length has the opposite sign to a nominal length of at least ``MIRROR_MIN_LENGTH_MM``, has its
#: frame turned against the nominal model's: a mirrored parameter set.
MIRROR_ANGLE_RAD = math.pi / 2
MIRROR_MIN_LENGTH_MM = 1.0


def mirrored_links(chain: Chain, params: np.ndarray) -> list[str]:
    """Axes whose link in ``params`` (P,) is written mirrored against the nominal model (a frame
    turned by 180°: α or β more than 90° from nominal, or a turned against a nominal length),
    one line per axis saying which; [] on the nominal model's branch."""
    n, nom = chain.n, chain.nominal
    out = []
    for i, ax in enumerate(chain.model.axis_names):
        what = []
        for kind in ("alpha", "beta"):
            c = chain.index(kind, i)
            gap = abs(wrap_angle(params[c] - nom[c]))
            if gap > MIRROR_ANGLE_RAD:
                what.append(f"{kind} {math.degrees(gap):.0f}° from nominal")
        a, a_nom = params[2 * n + i], nom[2 * n + i]
        if abs(a_nom) >= MIRROR_MIN_LENGTH_MM and a * a_nom < 0:
            what.append(f"a {a:+.4g} mm against nominal {a_nom:+.4g} mm")
        if what:
            out.append(f"{ax} ({', '.join(what)})")
    return out
