"""The KR C4's RSI Ethernet configuration file (``<ROOT><CONFIG/><SEND/><RECEIVE/></ROOT>``):
which elements the controller sends each cycle, which it reads from the answer and on which
channel, and the ``SENTYPE`` it expects. The file we ship is
``drivers/kuka_rsi/controller/remaster_rsi_ethernet.xml``; the fake KR C4 is driven by it."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

SHIPPED = Path(__file__).resolve().parent / "controller" / "remaster_rsi_ethernet.xml"

#: ``DEF_*`` send tags and the ``<Rob>`` element each one puts on the wire.
SEND_ELEMENTS = {"DEF_RIst": "RIst", "DEF_RSol": "RSol", "DEF_AIPos": "AIPos", "DEF_ASPos": "ASPos",
                 "DEF_EIPos": "EIPos", "DEF_ESPos": "ESPos", "DEF_MACur": "MACur", "DEF_MECur": "MECur",
                 "DEF_Delay": "Delay"}


@dataclass(frozen=True)
class RsiEthernetConfig:
    """One configuration. send: the ``<Rob>`` elements sent, in file order (``IPOC`` is always
    added by RSI). receive: answer tag (``AK.A1``, ``Stop``, ...) → Ethernet output channel."""

    path: Path
    ip_number: str
    port: int
    sen_type: str
    only_send: bool
    send: tuple[str, ...]
    receive: dict[str, int]

    @classmethod
    def load(cls, path: str | Path = SHIPPED) -> "RsiEthernetConfig":
        """Parse ``path``; ValueError naming the file and the element for anything malformed."""
        path = Path(path)
        try:
            root = ET.parse(path).getroot()
        except (OSError, ET.ParseError) as exc:
            raise ValueError(f"{path}: not a readable RSI Ethernet configuration: {exc}") from exc
        if root.tag != "ROOT":
            raise ValueError(f"{path}: root element is <{root.tag}>, expected <ROOT>")

        def text(tag: str) -> str:
            node = root.find(f"CONFIG/{tag}")
            if node is None or not (node.text or "").strip():
                raise ValueError(f"{path}: <CONFIG><{tag}> is missing")
            return node.text.strip()

        try:
            port = int(text("PORT"))
        except ValueError as exc:
            raise ValueError(f"{path}: <PORT> must be an integer: {exc}") from None
        send = []
        for el in root.findall("SEND/ELEMENTS/ELEMENT"):
            tag = el.get("TAG", "")
            if tag not in SEND_ELEMENTS:
                raise ValueError(f"{path}: SEND element TAG={tag!r} is not one we know ({', '.join(SEND_ELEMENTS)})")
            if el.get("INDX") != "INTERNAL":
                raise ValueError(f"{path}: SEND element {tag} must have INDX=\"INTERNAL\"")
            send.append(SEND_ELEMENTS[tag])
        receive: dict[str, int] = {}
        for el in root.findall("RECEIVE/ELEMENTS/ELEMENT"):
            tag, indx = el.get("TAG", ""), el.get("INDX", "")
            if not tag or not indx.isdigit() or not 1 <= int(indx) <= 64:
                raise ValueError(f"{path}: RECEIVE element TAG={tag!r} needs INDX 1..64, got {indx!r}")
            if int(indx) in receive.values():
                raise ValueError(f"{path}: RECEIVE channel {indx} is used twice")
            receive[tag] = int(indx)
        return cls(path, text("IP_NUMBER"), port, text("SENTYPE"), text("ONLYSEND").upper() == "TRUE",
                   tuple(send), receive)

    def axes_read(self, letter: str = "A") -> int:
        """How many consecutive ``AK.A1..`` (or ``EK.E1..``) corrections the controller reads."""
        prefix = "AK.A" if letter == "A" else "EK.E"
        n = 0
        while f"{prefix}{n + 1}" in self.receive:
            n += 1
        return n

    @property
    def reads_stop(self) -> bool:
        """Whether our ``<Stop>`` flag reaches the controller (ROS-I's KR C4 setup has none)."""
        return "Stop" in self.receive
