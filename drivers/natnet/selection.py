"""What each plan marker is on the NatNet stream: the selector syntax (``MarkerSelector``) and
its resolution to stream ids against Motive's model definitions (``resolve_markers``).

A resolved marker is one of ("rb", rigid body id), ("lm", labeled-marker id = model id << 16 |
marker id) or ("bone", (skeleton or asset id, bone id)); ``drivers.natnet.samples`` finds them
in a frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from drivers.natnet import codec

#: A selector resolved to stream ids: (kind, id) as listed in the module docstring.
Resolved = tuple[str, object]


def _id_or_name(text: str, limit: int = 0x7FFFFFFF) -> int | str:
    """``"7"`` → 7 (a NatNet id), anything else stays a name."""
    return int(text) if text.isdigit() and int(text) <= limit else text


@dataclass(frozen=True, slots=True)
class MarkerSelector:
    """What one plan marker is on the NatNet stream.

    kind "rb": a rigid body (``body`` = id or name) reported by its pivot position;
    kind "lm": a labeled marker (``model`` id, ``marker`` id);
    kind "ms": an asset's marker by name (``body`` = the rigid body, skeleton or trained
    markerset the marker belongs to, ``name`` = marker name), resolved to a labeled marker
    once the model definitions arrive;
    kind "sk": a skeleton bone (``body`` = skeleton id or name, ``name`` = bone id or name)
    reported by its position; bones of a trained markerset (NatNet 4.1 asset) the same way.
    """

    kind: str
    body: str | int | None = None
    model: int | None = None
    marker: int | None = None
    name: str | int | None = None

    SYNTAX = (
        "'rb:<rigid body id or name>', 'lm:<model id>:<marker id>', "
        "'ms:<asset name>:<marker name>' or 'sk:<skeleton id or name>:<bone id or name>'"
    )

    @classmethod
    def parse(cls, text: str) -> "MarkerSelector":
        if not isinstance(text, str):
            raise TypeError(f"marker selector must be a string ({cls.SYNTAX}), got {text!r}")
        kind, _, rest = text.partition(":")
        if kind == "rb" and rest:
            return cls("rb", body=int(rest) if rest.lstrip("-").isdigit() else rest)
        a, _, b = rest.partition(":")
        if kind == "lm":
            if a.isdigit() and b.isdigit() and int(a) <= 0xFFFF and int(b) <= 0xFFFF:
                return cls("lm", model=int(a), marker=int(b))
        if kind == "ms":
            if a and b:
                return cls("ms", body=a, name=b)
        if kind == "sk":
            if a and b and not (a.isdigit() and int(a) > 0xFFFF) and not (b.isdigit() and int(b) > 0xFFFF):
                return cls("sk", body=_id_or_name(a), name=_id_or_name(b))
        raise ValueError(f"marker selector {text!r} is not one of {cls.SYNTAX}")

    @property
    def needs_names(self) -> bool:
        """True when the selector names something, so Motive's model definitions are needed."""
        return self.kind == "ms" or isinstance(self.body, str) or (self.kind == "sk" and isinstance(self.name, str))



def resolve_by_name(md: codec.ModelDef, sel: MarkerSelector, who: str) -> tuple[str, object]:
    """A named selector against Motive's model definitions: ("rb", body id), ("lm", model id
    << 16 | marker id) or ("bone", (skeleton or asset id, bone id)); ``who`` starts the
    ValueError raised for a name Motive does not define (it lists what Motive does define)."""
    bodies = {d.name: d.id for d in md.rigid_bodies}
    skeletons = {d.name: d for d in md.skeletons}
    assets = {d.name: d for d in md.assets}
    if sel.kind == "rb":
        if sel.body not in bodies:
            raise ValueError(f"{who}: no rigid body named {sel.body!r}; Motive defines {sorted(bodies)}")
        return ("rb", bodies[sel.body])
    if sel.kind == "sk":
        owners = {**{d.name: d for d in md.assets}, **skeletons}
        if isinstance(sel.body, str):
            owner = owners.get(sel.body)
        else:
            owner = next((d for d in (*md.skeletons, *md.assets) if d.id == sel.body), None)
        if owner is None:
            raise ValueError(
                f"{who}: no skeleton or asset {sel.body!r}; Motive defines skeletons "
                f"{sorted(skeletons)} and assets {sorted(assets)}"
            )
        bones = {b.name: b.id for b in owner.rigid_bodies}
        bone = sel.name if isinstance(sel.name, int) else bones.get(sel.name)
        if bone is None:
            raise ValueError(f"{who}: {owner.name!r} has no bone {sel.name!r}; its bones are {sorted(bones)}")
        return ("bone", (owner.id, bone))
    # "ms": a marker of an asset by name
    sets = {d.name: d.marker_names for d in md.marker_sets}
    if sel.body in assets:
        asset = assets[sel.body]
        for m in asset.markers:
            if m.name == sel.name:
                return ("lm", m.id if m.id > 0xFFFF else (asset.id << 16) | m.id)
        raise ValueError(
            f"{who}: asset {sel.body!r} has no marker {sel.name!r}; its markers are "
            f"{[m.name for m in asset.markers]}"
        )
    names = sets.get(sel.body)
    if names is None or sel.name not in names:
        raise ValueError(
            f"{who}: no marker {sel.name!r} in marker set {sel.body!r}; Motive defines "
            + ("; ".join(f"{k}: {', '.join(v)}" for k, v in sets.items()) or "no marker sets")
        )
    if sel.body in bodies:
        model = bodies[sel.body]
    elif sel.body in skeletons:
        model = skeletons[sel.body].id
    else:
        raise ValueError(
            f"{who}: marker set {sel.body!r} belongs to no rigid body, skeleton or asset of the "
            "same name, so its labeled-marker ids are unknown; select the marker as "
            "'lm:<model id>:<marker id>'"
        )
    return ("lm", (model << 16) | (names.index(sel.name) + 1))


def resolve_markers(
    selectors: Mapping[str, MarkerSelector], md: codec.ModelDef | None, who: str
) -> dict[str, Resolved]:
    """Plan marker name → resolved marker (see the module docstring). Selectors by name need
    ``md`` (skipped while it is None); a name Motive does not define raises ValueError
    (starting ``"<who>: marker '<plan name>'"``) listing what it does define."""
    out: dict[str, Resolved] = {}
    for plan_name, sel in selectors.items():
        if sel.kind == "lm":
            out[plan_name] = ("lm", (sel.model << 16) | sel.marker)
        elif not sel.needs_names:
            out[plan_name] = ("rb", sel.body) if sel.kind == "rb" else ("bone", (sel.body, sel.name))
        elif md is not None:
            out[plan_name] = resolve_by_name(md, sel, f"{who}: marker {plan_name!r}")
    return out
