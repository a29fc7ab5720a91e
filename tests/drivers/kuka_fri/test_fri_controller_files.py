"""The Sunrise application shipped with the FRI commander states its FRI parameters once, and
they agree with the commander's defaults."""

from __future__ import annotations

import re
from pathlib import Path

from drivers.kuka_fri.commander import DEFAULT_PORT, FriCommander

APP = Path(__file__).resolve().parents[3] / "drivers" / "kuka_fri" / "controller" / "RemasterFriApp.java"


def _constant(text: str, name: str) -> str:
    m = re.search(rf"static final \w+ {name} = \"?([\w.]+)\"?;", text)
    assert m, f"{APP.name} states no {name}"
    return m.group(1)


def test_the_application_uses_the_commanders_port_and_a_joint_position_overlay(limits):
    text = APP.read_text()
    assert int(_constant(text, "CLIENT_PORT")) == DEFAULT_PORT == FriCommander.from_url("fri://", limits=limits).bind[1]
    assert 1 <= int(_constant(text, "SEND_PERIOD_MS")) <= 100
    assert int(_constant(text, "RECEIVE_MULT")) == 1
    assert "FRIJointOverlay(session, ClientCommandMode.POSITION)" in text  # absolute joint positions
    assert "new PositionControlMode()" in text
    assert "setSendPeriodMilliSec(SEND_PERIOD_MS)" in text and "setPortOnRemote(CLIENT_PORT)" in text
    notes = APP.with_name("README.md").read_text()
    for value in ("30200", "5 ms", "| 1 |"):
        assert value in notes
