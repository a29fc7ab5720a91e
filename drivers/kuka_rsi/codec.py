"""KUKA RSI Ethernet XML: robot → PC ``<Rob>`` state and PC → robot ``<Sen>`` corrections.

The real-time path parses and formats with precompiled regular expressions and ``%`` format
strings (a few microseconds per packet), never a DOM. The grammar accepted is the flat
document every RSI configuration sends: an optional ``<?xml …?>`` declaration, one root element,
children that are either empty elements with attributes (``<AIPos A1="0.0" …/>``) or elements
holding text (``<IPOC>123</IPOC>``). Anything else — truncated documents, nested children,
unknown roots, non-numeric values, missing IPOC or axes — raises ``ProtocolError`` and nothing
else.

Units on the wire: degrees (axes), millimetres/degrees (Cartesian); this module keeps the wire
units, the commander converts to radians.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from drivers.errors import ProtocolError

__all__ = [
    "RobState",
    "SenCommand",
    "parse_rob",
    "parse_sen",
    "SenFormatter",
    "RobFormatter",
    "MAX_AXES",
    "MAX_EXTERNAL_AXES",
]

MAX_AXES = 6
MAX_EXTERNAL_AXES = 6

_NAME = rb"[A-Za-z_][\w.\-]*"
_ATTR = rb"\s+" + _NAME + rb'\s*=\s*"[^"<]*"'


def _element(group: int) -> bytes:
    """One flat child; ``group`` is the number of its name group in the enclosing pattern."""
    back = b"\\" + str(group).encode()
    return rb"<(" + _NAME + rb")((?:" + _ATTR + rb")*)\s*(?:/>|>([^<]*)</" + back + rb"\s*>)"


_DOC = re.compile(
    rb"\A\s*(?:<\?xml[^>]*\?>\s*)?<(Rob|Sen)((?:" + _ATTR + rb")*)\s*>((?:\s*" + _element(4) + rb")*)\s*</\1\s*>\s*\Z"
)
_CHILD = re.compile(_element(1))
_ATTRS = re.compile(rb'(' + _NAME + rb')\s*=\s*"([^"<]*)"')


@dataclass(frozen=True, slots=True)
class RobState:
    """One controller packet.

    axis_actual_deg: AIPos A1..An (n ≤ 6), degrees. axis_setpoint_deg: ASPos (the set-point
    axis positions when RSI started, the reference of absolute corrections) or None.
    external_actual_deg / external_setpoint_deg: EIPos / ESPos E1..Em (m may be 0).
    cartesian_actual / cartesian_setpoint: RIst / RSol as (X, Y, Z, A, B, C) in mm and degrees,
    or None. delay: the controller's late-packet count (``Delay D``) or None. ipoc: the stamp
    to echo.
    """

    ipoc: int
    axis_actual_deg: tuple[float, ...]
    axis_setpoint_deg: tuple[float, ...] | None = None
    external_actual_deg: tuple[float, ...] = ()
    external_setpoint_deg: tuple[float, ...] | None = None
    cartesian_actual: tuple[float, ...] | None = None
    cartesian_setpoint: tuple[float, ...] | None = None
    delay: int | None = None
    type: str = ""


@dataclass(frozen=True, slots=True)
class SenCommand:
    """One answer: AK A1..An and EK E1..Em corrections (degrees), the Stop flag, the IPOC."""

    ipoc: int
    axis_correction_deg: tuple[float, ...]
    external_correction_deg: tuple[float, ...] = ()
    stop: bool = False
    type: str = ""


def _snippet(data: bytes) -> str:
    text = data[:80].decode("ascii", "replace")
    return repr(text + ("…" if len(data) > 80 else ""))


def _document(data: bytes, root: bytes) -> tuple[str, dict[bytes, tuple[bytes, bytes | None]]]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"RSI packet must be bytes, got {type(data).__name__}")
    m = _DOC.match(bytes(data))
    if m is None:
        raise ProtocolError(f"RSI packet is not a flat XML document: {_snippet(bytes(data))}")
    if m.group(1) != root:
        raise ProtocolError(
            f"RSI packet has root <{m.group(1).decode()}>, expected <{root.decode()}>: {_snippet(bytes(data))}"
        )
    typ = ""
    for k, v in _ATTRS.findall(m.group(2)):
        if k.lower() == b"type":
            typ = v.decode("ascii", "replace")
    children: dict[bytes, tuple[bytes, bytes | None]] = {}
    for c in _CHILD.finditer(m.group(3)):
        children[c.group(1)] = (c.group(2), c.group(3))
    return typ, children


def _axes(children, tag: bytes, letter: bytes, limit: int, required: bool) -> tuple[float, ...] | None:
    """Attributes ``<letter>1..<letter>k`` of ``tag`` as floats, contiguous from 1."""
    found = children.get(tag)
    if found is None:
        if required:
            raise ProtocolError(f"RSI packet has no <{tag.decode()}> element")
        return None
    values: dict[int, float] = {}
    for k, v in _ATTRS.findall(found[0]):
        if k[:1] == letter and k[1:].isdigit():
            try:
                x = float(v)
                if not math.isfinite(x):
                    raise ValueError(v)
                values[int(k[1:])] = x
            except ValueError:
                raise ProtocolError(
                    f"<{tag.decode()} {k.decode()}> is not a number: {v[:20].decode('ascii', 'replace')!r}"
                ) from None
    n = len(values)
    if n > limit or any(i not in values for i in range(1, n + 1)):
        raise ProtocolError(
            f"<{tag.decode()}> must carry {letter.decode()}1..{letter.decode()}k with k ≤ {limit}, "
            f"got {sorted(values)}"
        )
    if required and n == 0:
        raise ProtocolError(f"<{tag.decode()}> carries no axis values")
    return tuple(values[i] for i in range(1, n + 1))


def _cartesian(children, tag: bytes) -> tuple[float, ...] | None:
    found = children.get(tag)
    if found is None:
        return None
    attrs = dict(_ATTRS.findall(found[0]))
    try:
        xyzabc = tuple(float(attrs[k]) for k in (b"X", b"Y", b"Z", b"A", b"B", b"C"))
        if not all(map(math.isfinite, xyzabc)):
            raise ValueError(xyzabc)
        return xyzabc
    except (KeyError, ValueError):
        raise ProtocolError(f"<{tag.decode()}> must carry numeric X Y Z A B C, got {found[0][:80]!r}") from None


def _ipoc(children) -> int:
    found = children.get(b"IPOC")
    if found is None or found[1] is None:
        raise ProtocolError("RSI packet has no <IPOC> stamp")
    text = found[1].strip()
    if not text.isdigit():
        raise ProtocolError(f"<IPOC> must be a non-negative integer, got {text[:20]!r}")
    return int(text)


def parse_rob(data: bytes) -> RobState:
    """Decode a controller packet. Raises ProtocolError (only) on anything malformed."""
    typ, ch = _document(data, b"Rob")
    delay = None
    if b"Delay" in ch:
        d = dict(_ATTRS.findall(ch[b"Delay"][0])).get(b"D")
        if d is None or not d.strip().isdigit():
            raise ProtocolError(f"<Delay D> must be a non-negative integer, got {d!r}")
        delay = int(d)
    return RobState(
        ipoc=_ipoc(ch),
        axis_actual_deg=_axes(ch, b"AIPos", b"A", MAX_AXES, True),
        axis_setpoint_deg=_axes(ch, b"ASPos", b"A", MAX_AXES, False),
        external_actual_deg=_axes(ch, b"EIPos", b"E", MAX_EXTERNAL_AXES, False) or (),
        external_setpoint_deg=_axes(ch, b"ESPos", b"E", MAX_EXTERNAL_AXES, False),
        cartesian_actual=_cartesian(ch, b"RIst"),
        cartesian_setpoint=_cartesian(ch, b"RSol"),
        delay=delay,
        type=typ,
    )


def parse_sen(data: bytes) -> SenCommand:
    """Decode a PC answer (used by the fake controller and tests). ProtocolError on bad input."""
    typ, ch = _document(data, b"Sen")
    stop = False
    if b"Stop" in ch:
        text = (ch[b"Stop"][1] or b"").strip()
        if text not in (b"0", b"1"):
            raise ProtocolError(f"<Stop> must be 0 or 1, got {text[:20]!r}")
        stop = text == b"1"
    return SenCommand(
        ipoc=_ipoc(ch),
        axis_correction_deg=_axes(ch, b"AK", b"A", MAX_AXES, True),
        external_correction_deg=_axes(ch, b"EK", b"E", MAX_EXTERNAL_AXES, False) or (),
        stop=stop,
        type=typ,
    )


def _check_type(sen_type: str) -> str:
    if not re.fullmatch(r"[A-Za-z_][\w.\-]*", sen_type or ""):
        raise ValueError(f"RSI Type attribute must be an XML name such as 'ImFree', got {sen_type!r}")
    return sen_type


class SenFormatter:
    """Formats ``<Sen>`` answers for a fixed axis count with one precompiled ``%`` template.

    ``format(values_deg, stop, ipoc)``: values_deg is a sequence of ``n_axes + n_external``
    floats (AK A1..An, then EK E1..Em), degrees. Seven decimals (≈1.7e-9 rad resolution).
    """

    DECIMALS = 7

    def __init__(self, n_axes: int, n_external: int = 0, sen_type: str = "ImFree") -> None:
        if not 1 <= n_axes <= MAX_AXES or not 0 <= n_external <= MAX_EXTERNAL_AXES:
            raise ValueError(
                f"RSI carries 1..{MAX_AXES} robot axes and 0..{MAX_EXTERNAL_AXES} external axes, "
                f"got {n_axes} and {n_external}"
            )
        f = f"%.{self.DECIMALS}f"
        ak = " ".join(f'A{i}="{f}"' for i in range(1, n_axes + 1))
        ek = (" <EK " + " ".join(f'E{i}="{f}"' for i in range(1, n_external + 1)) + "/>") if n_external else ""
        self.n_values = n_axes + n_external
        self._template = (
            f'<Sen Type="{_check_type(sen_type)}"><AK {ak}/>{ek.strip()}<Stop>%d</Stop><IPOC>%d</IPOC></Sen>'
        )

    def format(self, values_deg, stop: bool, ipoc: int) -> bytes:
        return (self._template % (*values_deg, stop, ipoc)).encode("ascii")


class RobFormatter:
    """Formats ``<Rob>`` state packets (the fake controller's side), same technique.

    ``format(actual_deg, setpoint_deg, cart_actual, cart_setpoint, delay, ipoc)`` with
    actual/setpoint of length ``n_axes + n_external`` (A1..An then E1..Em), degrees.
    elements: the ``<Rob>`` elements in the order the controller's RSI Ethernet configuration
    sends them (``SEND``: RIst, RSol, AIPos, ASPos, EIPos, ESPos, MACur, MECur, Delay); motor
    currents are sent as zeros. ``IPOC`` always ends the packet.
    """

    DEFAULT_ELEMENTS = ("RIst", "RSol", "AIPos", "ASPos", "EIPos", "ESPos", "Delay")

    def __init__(self, n_axes: int, n_external: int = 0, rob_type: str = "KUKA",
                 elements: tuple[str, ...] = DEFAULT_ELEMENTS) -> None:
        if not 1 <= n_axes <= MAX_AXES or not 0 <= n_external <= MAX_EXTERNAL_AXES:
            raise ValueError(
                f"RSI carries 1..{MAX_AXES} robot axes and 0..{MAX_EXTERNAL_AXES} external axes, "
                f"got {n_axes} and {n_external}"
            )
        f = "%.6f"
        cart = " ".join(f'{k}="{f}"' for k in "XYZABC")
        a = " ".join(f'A{i}="{f}"' for i in range(1, n_axes + 1))
        e = " ".join(f'E{i}="{f}"' for i in range(1, n_external + 1))
        zeros_a = " ".join(f'A{i}="0.0"' for i in range(1, n_axes + 1))
        zeros_e = " ".join(f'E{i}="0.0"' for i in range(1, n_external + 1))
        parts = {"RIst": (f"<RIst {cart}/>", "cart_actual"), "RSol": (f"<RSol {cart}/>", "cart_setpoint"),
                 "AIPos": (f"<AIPos {a}/>", "actual"), "ASPos": (f"<ASPos {a}/>", "setpoint"),
                 "EIPos": (f"<EIPos {e}/>", "ext_actual"), "ESPos": (f"<ESPos {e}/>", "ext_setpoint"),
                 "MACur": (f"<MACur {zeros_a}/>", None), "MECur": (f"<MECur {zeros_e}/>", None),
                 "Delay": ('<Delay D="%d"/>', "delay")}
        unknown = [x for x in elements if x not in parts]
        if unknown:
            raise ValueError(f"unknown <Rob> element(s) {unknown}; known: {', '.join(parts)}")
        if "AIPos" not in elements:
            raise ValueError("a <Rob> packet without AIPos carries no axis positions")
        body, self._slots = "", []
        for name in elements:
            if name in ("EIPos", "ESPos", "MECur") and not n_external:
                continue
            text, slot = parts[name]
            body += text
            if slot is not None:
                self._slots.append(slot)
        self.n_axes, self.n_external = n_axes, n_external
        self.elements = tuple(elements)
        self._template = f'<Rob Type="{_check_type(rob_type)}">{body}<IPOC>%d</IPOC></Rob>'

    def format(self, actual_deg, setpoint_deg, cart_actual, cart_setpoint, delay: int, ipoc: int) -> bytes:
        n = self.n_axes
        fields = {"cart_actual": tuple(cart_actual), "cart_setpoint": tuple(cart_setpoint),
                  "actual": tuple(actual_deg[:n]), "setpoint": tuple(setpoint_deg[:n]),
                  "ext_actual": tuple(actual_deg[n:]), "ext_setpoint": tuple(setpoint_deg[n:]),
                  "delay": (delay,)}
        values = [v for slot in self._slots for v in fields[slot]]
        return (self._template % (*values, ipoc)).encode("ascii")
