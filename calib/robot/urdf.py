"""URDF in and out: a robot model from a URDF's serial chain, and a robot model as a URDF.

Reading and writing go through ``yourdfpy`` (imported on use: it pulls trimesh). URDF is metres
and radians; our models are mm and degrees (``calib.robot.model``).

**Import** (``import_urdf``): the chain from the base link to the tip link; fixed joints before
the first revolute joint fold into the model's base frame, fixed joints after the last one into
its flange frame, fixed joints in between into the link geometry. Each revolute joint becomes
one DH/M-DH link (``calib.robot.dh_convert``). The joint value in the URDF is the controller's angle
(the ROS-Industrial convention: vendor URDFs flip axes so that it is): a joint whose axis has its
largest component negative (e.g. ``0 0 -1``) gets ``sign: -1`` and the DH z along the flipped
axis, so the DH table keeps the usual directions. Limits and speeds are the URDF's ``<limit>``
(radians → degrees); ``max_accel`` (no URDF field) is written as the planning value
``ACCEL_PER_SPEED`` × speed per second. Link masses and centres of mass come from ``<inertial>``
when every moving body has a mass. Tool markers come from fixed child links of the tip named
``marker_<name>`` (as ``export_urdf`` writes them) or, failing that, one marker ``flange`` at the
flange origin, to be replaced by the real tool.

**Export** (``export_urdf``): links base_link, link_1 … link_n, flange, marker_<name>; joints named
by the model's axes, then ``link_n-flange`` and ``flange-marker_<name>`` (fixed). Each revolute joint
turns about its z with ``axis 0 0 sign``, so that the URDF's joint values are the controller's
angles; link_i's frame is DH frame i − 1 turned by θ_i.

``urdf_fk`` evaluates a URDF's own kinematics (yourdfpy) for the FK equality checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.robot.dh_convert import AxisLine, DHTable, dh_from_axes, frame_to_yaml, link_matrix, Link
from calib.robot.model import RobotModel, robot_model_from_dict
from calib.robot.transforms import homogeneous, invert

#: ``max_accel`` written on import, per unit of top speed (deg/s² per deg/s): a planning value,
#: as in the shipped models (URDF has no acceleration limit).
ACCEL_PER_SPEED = 3.0
#: Prefix of the fixed links under the flange that carry tool markers.
MARKER_PREFIX = "marker_"
MOVABLE = ("revolute", "continuous", "prismatic", "floating", "planar")


class UrdfError(ValueError):
    """A URDF that cannot become a robot model (or be read); the message names the file, the
    joint or link, and what would be accepted."""


@dataclass
class UrdfImport:
    """``model`` the imported robot model; ``base``/``tip`` the chain's end links; ``joints`` the
    URDF names of its revolute joints in order; ``table`` the DH conversion; ``notes`` what was
    chosen or assumed, for the user."""

    model: RobotModel
    base: str
    tip: str
    joints: list[str]
    table: DHTable
    notes: list[str] = field(default_factory=list)


def _yourdfpy():
    import yourdfpy  # noqa: PLC0415  (trimesh behind it: only when URDFs are used)

    return yourdfpy


def check_well_formed(path: Path) -> None:
    """Parse ``path`` strictly as XML; ``UrdfError`` naming ``file:line:column`` and the parser's
    message if it is not well-formed, or if it has a DOCTYPE (entities could read local files or
    expand without bound; URDF needs none).

    yourdfpy, given a malformed file, logs the error and re-parses with ``recover=True``: an
    unclosed tag then silently drops the rest of the robot (a 2-joint file imported as 1 joint).
    """
    from lxml import etree  # noqa: PLC0415

    parser = etree.XMLParser(recover=False, resolve_entities=False, load_dtd=False, no_network=True,
                             huge_tree=False)
    try:
        tree = etree.parse(str(path), parser=parser)
    except etree.XMLSyntaxError as exc:
        line, col = exc.position if exc.position else (exc.lineno, 0)
        raise UrdfError(f"{path}:{line}:{col}: not well-formed XML: {exc.msg}; nothing was read from this file "
                        "— fix the XML (an unclosed or mismatched tag, a stray '&' or '<')") from None
    except OSError as exc:
        raise UrdfError(f"{path}: cannot read: {exc}") from None
    if tree.docinfo.doctype:
        raise UrdfError(f"{path}:1:1: a DOCTYPE is not allowed in a URDF (given {tree.docinfo.doctype[:80]!r}); "
                        "remove it (run xacro first for macros)")


def load_urdf(path: str | Path, fk: bool = True):
    """A ``yourdfpy.URDF`` without meshes, with its scene graph when ``fk`` (needed by
    ``urdf_fk``; it evaluates every joint, so leave it off for a file not yet checked);
    ``UrdfError`` if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise UrdfError(f"{path}: no such URDF file")
    check_well_formed(path)
    ydf = _yourdfpy()
    from lxml import etree  # noqa: PLC0415  (yourdfpy's XML library)

    try:
        urdf = ydf.URDF.load(str(path), build_scene_graph=fk, load_meshes=False,
                             build_collision_scene_graph=False, load_collision_meshes=False)
    except (etree.XMLSyntaxError, KeyError, AttributeError, ValueError, TypeError, IndexError) as exc:
        raise UrdfError(f"{path}: not a readable URDF ({type(exc).__name__}: {exc}); "
                        "expected <robot name=...> with <link name=...> and <joint name=... type=...> "
                        "elements, each joint with <parent link=...> and <child link=...>") from exc
    if urdf.robot is None or not urdf.robot.links:
        raise UrdfError(f"{path}: no <link> elements: not a URDF robot")
    return urdf


# --- the tree ------------------------------------------------------------------------------
class _Tree:
    """Parent/child structure of a URDF with the checks a serial-chain import needs."""

    def __init__(self, urdf, where: str) -> None:
        self.where = where
        self.links = [lk.name for lk in urdf.robot.links]
        self.joints = {j.name: j for j in urdf.robot.joints}
        self.parent_joint: dict[str, object] = {}
        self.children: dict[str, list] = {name: [] for name in self.links}
        for j in urdf.robot.joints:
            for role, link in (("parent", j.parent), ("child", j.child)):
                if link not in self.children:
                    raise UrdfError(f"{where}: joint {j.name!r} names {role} link {link!r}, which is not a <link> of the file")
            if j.child in self.parent_joint:
                other = self.parent_joint[j.child].name
                raise UrdfError(f"{where}: link {j.child!r} is the child of joints {other!r} and {j.name!r}: "
                                "not a tree (a URDF link has one parent joint)")
            self.parent_joint[j.child] = j
            self.children[j.parent].append(j)
        self.roots = [name for name in self.links if name not in self.parent_joint]
        if not self.roots:
            raise UrdfError(f"{where}: every link has a parent joint (a loop): no base link")

    def path(self, base: str, tip: str) -> list:
        """Joints from ``base`` down to ``tip``."""
        for name, role in ((base, "--base"), (tip, "--tip")):
            if name not in self.children:
                raise UrdfError(f"{self.where}: no link {name!r} ({role}); links: {', '.join(self.links)}")
        out = []
        link = tip
        while link != base:
            j = self.parent_joint.get(link)
            if j is None:
                raise UrdfError(f"{self.where}: link {tip!r} (--tip) is not below link {base!r} (--base)")
            out.append(j)
            link = j.parent
        return out[::-1]

    def at_zero(self, base: str, link: str) -> np.ndarray:
        """(4, 4) pose of ``link`` in ``base`` at the zero configuration, metres."""
        t = np.eye(4)
        for j in self.path(base, link):
            t = t @ (np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=float))
        return t

    def subtree(self, link: str) -> list[str]:
        out, todo = [], [link]
        while todo:
            name = todo.pop()
            out.append(name)
            todo.extend(j.child for j in self.children[name])
        return out

    def _is_marker(self, link: str) -> bool:
        j = self.parent_joint.get(link)
        return j is not None and j.type == "fixed" and link.startswith(MARKER_PREFIX)

    def default_base(self) -> str:
        if len(self.roots) > 1:
            raise UrdfError(f"{self.where}: {len(self.roots)} links have no parent ({', '.join(self.roots)}): "
                            "the file holds unconnected parts; choose the robot's base with --base")
        return self.roots[0]

    def default_tip(self, base: str) -> str:
        """The end link reached through the most movable joints; marker_* links under it do not
        count as ends. Several such ends → ``UrdfError`` asking for ``--tip``."""
        leaves = []
        for name in self.subtree(base):
            if self._is_marker(name):
                continue
            ends = [j for j in self.children[name] if not self._is_marker(j.child)]
            if not ends:
                leaves.append(name)
        count = {leaf: sum(j.type in MOVABLE for j in self.path(base, leaf)) for leaf in leaves}
        most = max(count.values())
        best = [leaf for leaf in leaves if count[leaf] == most]
        if len(best) > 1:
            raise UrdfError(f"{self.where}: {len(best)} end links are reached through {most} movable joints "
                            f"({', '.join(sorted(best))}): choose the flange with --tip")
        return best[0]


# --- import -------------------------------------------------------------------------------
def _sign_of(axis: np.ndarray) -> int:
    """-1 when the axis's largest component is negative (a flipped axis, e.g. ``0 0 -1``)."""
    return -1 if axis[int(np.argmax(np.abs(axis)))] < 0 else 1


def _check_joint(j, where: str) -> None:
    what = f"{where}: joint {j.name!r}"
    if j.type == "prismatic":
        raise UrdfError(f"{what} is prismatic: remaster models revolute arms only (a linear track before the arm: "
                        "choose --base after it; a gripper after the flange: choose the flange with --tip)")
    if j.type in ("floating", "planar"):
        raise UrdfError(f"{what} is {j.type}: only revolute and fixed joints may lie on the chain "
                        "(choose --base after it, or --tip before it)")
    if j.type == "continuous":
        raise UrdfError(f"{what} is continuous (no position limits): a robot model needs limits; make it "
                        "type=\"revolute\" with <limit lower=... upper=... velocity=...> in radians")
    if j.type not in ("revolute", "fixed"):
        raise UrdfError(f"{what} has type {j.type!r}; allowed: revolute, continuous, prismatic, fixed, floating, planar")
    if j.mimic is not None:
        raise UrdfError(f"{what} mimics {j.mimic.joint!r}: a coupled joint is not a controller axis; "
                        "remaster needs independent revolute joints on the chain")
    if j.type == "fixed":
        return
    axis = np.asarray(j.axis, dtype=float)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-9:
        raise UrdfError(f"{what} has axis {axis.tolist()}: give a non-zero <axis xyz=\"x y z\"/>")
    lim = j.limit
    if lim is None:
        raise UrdfError(f"{what} has no <limit>: give <limit lower=... upper=... velocity=... effort=...> "
                        "(radians, rad/s)")
    for attr in ("lower", "upper", "velocity"):
        v = getattr(lim, attr)
        if v is None or not math.isfinite(v):
            raise UrdfError(f"{what}: <limit> lacks {attr}= (radians, rad/s): the model needs position limits and a top speed")
    if not lim.lower < lim.upper:
        raise UrdfError(f"{what}: <limit lower={lim.lower} upper={lim.upper}>: lower must be below upper (radians)")
    if max(abs(lim.lower), abs(lim.upper)) > 4 * math.pi:
        raise UrdfError(f"{what}: <limit lower={lim.lower} upper={lim.upper}> beyond ±4π: URDF limits are radians")
    if lim.velocity <= 0:
        raise UrdfError(f"{what}: <limit velocity={lim.velocity}> must be positive (rad/s)")


def _origin(j) -> np.ndarray:
    """Joint origin (4, 4) in mm."""
    t = np.eye(4) if j.origin is None else np.array(j.origin, dtype=float)
    t[:3, 3] *= 1000.0
    return t


def _bodies(tree: _Tree, urdf, base: str, chain: list) -> tuple[list[float], list[np.ndarray]] | None:
    """Mass (kg) and centre of mass (base frame at zero, mm) of what each revolute joint moves,
    or None when some body has no mass (then the model gets no gravity data)."""
    revolute = [j for j in chain if j.type == "revolute"]
    masses, coms = [], []
    for k, j in enumerate(revolute):
        moved = set(tree.subtree(j.child))
        if k + 1 < len(revolute):
            moved -= set(tree.subtree(revolute[k + 1].child))
        m, first = 0.0, np.zeros(3)
        for name in moved:
            inertial = urdf.link_map[name].inertial
            if inertial is None or not inertial.mass:
                continue
            origin = np.eye(4) if inertial.origin is None else np.asarray(inertial.origin, dtype=float)
            at = tree.at_zero(base, name) @ origin[:, 3]
            m += float(inertial.mass)
            first += float(inertial.mass) * at[:3] * 1000.0
        if m <= 0:
            return None
        masses.append(m)
        coms.append(first / m)
    return masses, coms


def _markers_below(tree: _Tree, tip: str) -> list[dict]:
    """Markers from fixed ``marker_<name>`` children of the tip (flange frame, mm)."""
    out = []
    for j in tree.children[tip]:
        if j.type == "fixed" and j.child.startswith(MARKER_PREFIX) and j.child != MARKER_PREFIX:
            out.append({"name": j.child[len(MARKER_PREFIX):], "xyz": [float(v) for v in _origin(j)[:3, 3]]})
    return out


def import_urdf(path: str | Path, *, tip: str | None = None, base: str | None = None, convention: str = "auto",
                axes: list[str] | None = None, tool: dict | None = None) -> UrdfImport:
    """A robot model from the serial chain ``base`` → ``tip`` of a URDF (see the module text).

    tip/base: link names (default: the root link, and the end link reached through the most
    movable joints). convention: ``dh``, ``mdh`` or ``auto``. axes: controller names for the
    joints (default the URDF joint names). tool: a ``calib.robot.model.Tool`` layout to use instead of
    the markers found in the file.
    """
    where = str(path)
    urdf = load_urdf(path, fk=False)
    tree = _Tree(urdf, where)
    base = base or tree.default_base()
    tip = tip or tree.default_tip(base)
    chain = tree.path(base, tip)
    for j in chain:
        _check_joint(j, where)
    revolute = [j for j in chain if j.type == "revolute"]
    if not revolute:
        raise UrdfError(f"{where}: no revolute joint between {base!r} and {tip!r}: choose --base and --tip around the arm")
    if len(revolute) > 12:
        raise UrdfError(f"{where}: {len(revolute)} revolute joints between {base!r} and {tip!r}; a model has at most 12")
    if axes is not None and len(axes) != len(revolute):
        raise UrdfError(f"{len(axes)} axis names given for {len(revolute)} revolute joints "
                        f"({', '.join(j.name for j in revolute)})")
    # Walk the chain at the zero configuration: each revolute joint's axis line, then the tip.
    t = np.eye(4)
    lines, signs = [], []
    for j in chain:
        t = t @ _origin(j)
        if j.type == "revolute":
            axis = np.asarray(j.axis, dtype=float) / np.linalg.norm(j.axis)
            s = _sign_of(axis)
            lines.append(AxisLine(t[:3, 3].copy(), s * (t[:3, :3] @ axis)))
            signs.append(s)
    table = dh_from_axes(lines, t, convention)
    names = axes or [j.name for j in revolute]
    joints = []
    for k, (j, link, s) in enumerate(zip(revolute, table.links, signs)):
        joints.append({
            "axis": names[k], "theta": math.degrees(link.theta), "d": link.d, "a": link.a,
            "alpha": math.degrees(link.alpha), "beta": math.degrees(link.beta), "sign": s,
            # Rounded to 1e-9°: URDFs write 6.28318530718 for 2π, which is not a limit of 360.000000000024°.
            "limits": [round(math.degrees(j.limit.lower), 9), round(math.degrees(j.limit.upper), 9)],
            "max_speed": round(math.degrees(j.limit.velocity), 9),
            "max_accel": round(ACCEL_PER_SPEED * math.degrees(j.limit.velocity), 9),
        })
    notes = list(table.notes)
    notes.append(f"chain {base} → {tip}: {len(revolute)} revolute joints ({', '.join(j.name for j in revolute)}), "
                 f"{len(chain) - len(revolute)} fixed")
    if any(s < 0 for s in signs):
        notes.append("sign -1 (flipped URDF axis) on " + ", ".join(n for n, s in zip(names, signs) if s < 0))
    notes.append(f"max_accel = {ACCEL_PER_SPEED:g} × max_speed per second (a planning value; URDF has no acceleration limit)")
    bodies = _bodies(tree, urdf, base, chain)
    if bodies is None:
        notes.append("no gravity data: not every moving link has an <inertial> mass")
    else:
        for k, (m, com) in enumerate(zip(*bodies)):
            local = invert(table.frames[k + 1]) @ np.append(com, 1.0)
            joints[k]["mass_kg"] = m
            joints[k]["com_mm"] = [float(v) for v in local[:3]]
    if tool is None:
        markers = _markers_below(tree, tip)
        if markers:
            tool = {"name": "tool", "markers": markers}
            notes.append(f"tool markers from {MARKER_PREFIX}* links: {', '.join(m['name'] for m in markers)}")
        else:
            tool = {"name": "flange", "markers": [{"name": "flange", "xyz": [0.0, 0.0, 0.0]}]}
            notes.append("tool: one marker 'flange' at the flange origin — replace it with your tool's markers")
    data = {
        "name": urdf.robot.name or Path(path).stem,
        "convention": table.convention,
        "source": f"imported from URDF {Path(path).name} ({base} → {tip}) by remaster",
        "base": frame_to_yaml(table.base2frame0),
        "flange": frame_to_yaml(table.lastframe2flange),
        "joints": joints,
        "tool": tool,
    }
    try:
        model = robot_model_from_dict(_clean(data))
    except ValueError as exc:
        raise UrdfError(f"{where}: the imported model is not valid: {exc}") from exc
    return UrdfImport(model, base, tip, [j.name for j in revolute], table, notes)


def _clean(o):
    """Round away float noise (below 1e-12 mm or degrees) so files read 90 rather than 89.99999999999999."""
    if isinstance(o, float):
        r = round(o, 12)
        return 0.0 if r == 0 else r
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    return o


# --- FK of a URDF ----------------------------------------------------------------------------
def urdf_fk(urdf, joints: list[str], base: str, tip: str, q_rad: np.ndarray) -> np.ndarray:
    """The URDF's own kinematics (yourdfpy): ``tip`` in ``base`` for joint values ``q_rad``
    (N, n) radians of the named ``joints`` (others at 0) → (N, 4, 4) mm."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    out = np.empty((len(q), 4, 4))
    for i, row in enumerate(q):
        urdf.update_cfg({name: float(v) for name, v in zip(joints, row)})
        t = np.array(urdf.get_transform(tip, base), dtype=float)
        t[:3, 3] *= 1000.0
        out[i] = t
    return out


def fk_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Worst position (mm) and rotation (deg) difference between two stacks of (4, 4) poses."""
    from calib.robot.transforms import rotation_angle  # noqa: PLC0415

    pos = float(np.max(np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)))
    rel = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    return pos, float(np.degrees(np.max(rotation_angle(rel))))


def random_configurations(model: RobotModel, n: int, seed: int = 0) -> np.ndarray:
    """(n, n_joints) radians: the zero configuration and n − 1 uniform draws inside the limits."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(model.lower_limits_rad, model.upper_limits_rad, (n, model.n_joints))
    q[0] = 0.0
    return q


# --- export ---------------------------------------------------------------------------------
def _origin_m(t: np.ndarray) -> np.ndarray:
    out = np.array(t, dtype=float)
    out[:3, 3] = np.round(out[:3, 3] / 1000.0, 12) + 0.0  # metres; float noise below 1 nm dropped
    return out


def model_to_urdf(model: RobotModel):
    """A ``yourdfpy.URDF`` of the model (see the module text): base_link, link_1..n, flange,
    marker_<name>; joint values are the controller's angles."""
    ydf = _yourdfpy()
    n = model.n_joints
    links = [ydf.Link(name="base_link")]
    joints = []
    before = model.base.matrix()  # transform from the previous link frame to this joint's frame
    for i, j in enumerate(model.joints):
        lk = Link(math.radians(j.theta), j.d, j.a, math.radians(j.alpha), math.radians(j.beta))
        rest = link_matrix(Link(0.0, lk.d, lk.a, lk.alpha, lk.beta))  # Tz Tx Rx Ry after the joint rotation
        origin = before @ link_matrix(Link(lk.theta, 0.0, 0.0, 0.0))
        name = f"link_{i + 1}"
        inertial = None
        if j.mass_kg is not None and j.com_mm is not None:
            com = rest @ np.append(np.asarray(j.com_mm, dtype=float), 1.0)
            inertial = ydf.Inertial(origin=_origin_m(homogeneous(np.eye(3), com[:3])), mass=float(j.mass_kg),
                                    inertia=np.zeros((3, 3)))
        links.append(ydf.Link(name=name, inertial=inertial))
        joints.append(ydf.Joint(
            name=j.axis, type="revolute", parent="base_link" if i == 0 else f"link_{i}", child=name,
            origin=_origin_m(origin), axis=np.array([0.0, 0.0, float(j.sign)]),
            limit=ydf.Limit(effort=0.0, velocity=math.radians(j.max_speed),
                            lower=math.radians(j.limits[0]), upper=math.radians(j.limits[1])),
        ))
        before = rest
    links.append(ydf.Link(name="flange"))
    joints.append(ydf.Joint(name=f"link_{n}-flange", type="fixed", parent=f"link_{n}", child="flange",
                            origin=_origin_m(before @ model.flange.matrix())))
    for mk in model.tool.markers:
        links.append(ydf.Link(name=MARKER_PREFIX + mk.name))
        joints.append(ydf.Joint(name=f"flange-{MARKER_PREFIX}{mk.name}", type="fixed", parent="flange", child=MARKER_PREFIX + mk.name,
                                origin=_origin_m(homogeneous(np.eye(3), np.asarray(mk.xyz, dtype=float)))))
    robot = ydf.Robot(name=model.name, links=links, joints=joints)
    return ydf.URDF(robot=robot, build_scene_graph=True, load_meshes=False)


def export_urdf(model: RobotModel, path: str | Path, header: str = "") -> Path:
    """Write ``model`` as a URDF file (yourdfpy); ``header`` goes in a leading XML comment."""
    from lxml import etree  # noqa: PLC0415

    urdf = model_to_urdf(model)
    tree = urdf.write_xml()
    text = ("Written by remaster from a robot model (mm, degrees) — URDF in metres and radians.\n"
            "Joint values are the controller's angles; revolute joints turn about their z axis "
            "(axis 0 0 -1 where the controller's sense is the opposite).\n"
            "effort=\"0\": no torque limits are known; inertia tensors are not part of remaster models (zero).\n"
            + header)
    tree.getroot().insert(0, etree.Comment(" " + text.replace("--", "- -").strip() + " "))
    path = Path(path)
    tree.write(str(path), xml_declaration=True, pretty_print=True, encoding="utf-8")
    return path
