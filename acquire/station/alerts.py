"""Alerts a plant uses: a command and/or a webhook told of every event the station raises.

Events (JSON objects, ``"event"`` naming the kind, ``"time"`` ISO 8601 UTC, ``"text"`` one line):

``state``        a robot's state changed (``robot_serial``, ``site``, ``cell``, ``from``, ``to``,
                 ``reasons``; states in ``acquire.station.states``)
``damaged``      the scrub found a stored file missing or altered (``run``, ``file``, ``problem``)
``refused``      a cell's run was refused (``site``, ``cell``, ``problem``: wrong serial, a run that
                 would replace another, over a size limit or the free-space reserve)

``alert.command`` (argv) runs once per event with the event on stdin and ``REMASTER_EVENT`` /
``REMASTER_TEXT`` in its environment; ``alert.webhook`` receives it as an HTTP POST with a JSON
body. Each has ``alert.timeout_s``; a failed alert is logged and never stops the station. Every
event is also logged (journald).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import urllib.error
import urllib.request
from datetime import datetime, timezone

log = logging.getLogger(__name__)


class Alerter:
    """Sends events to the configured command and webhook (``AlertSection``; either may be None)."""

    def __init__(self, command: list[str] | None = None, webhook: str | None = None, timeout_s: float = 10.0) -> None:
        self.command = command
        self.webhook = webhook
        self.timeout_s = timeout_s

    def send(self, event: str, text: str, **fields) -> dict:
        """Log and deliver one event; returns it."""
        body = {"event": event, "time": datetime.now(timezone.utc).isoformat(timespec="seconds"), "text": text,
                **fields}
        log.warning("alert %s: %s", event, text)
        data = json.dumps(body).encode()
        if self.command:
            env = dict(os.environ, REMASTER_EVENT=event, REMASTER_TEXT=text)
            try:
                done = subprocess.run(self.command, input=data, env=env, timeout=self.timeout_s,
                                      capture_output=True, check=False)
                if done.returncode != 0:
                    log.error("alert command %s exited %d: %s", self.command[0], done.returncode,
                              done.stderr.decode(errors="replace").strip()[:300])
            except (OSError, subprocess.TimeoutExpired) as exc:
                log.error("alert command %s failed: %s", self.command[0], exc)
        if self.webhook:
            req = urllib.request.Request(self.webhook, data=data, method="POST",
                                         headers={"Content-Type": "application/json"})
            try:
                with urllib.request.urlopen(req, timeout=self.timeout_s) as resp:
                    resp.read()
            except (OSError, urllib.error.URLError, ValueError) as exc:
                log.error("alert webhook %s failed: %s", self.webhook, exc)
        return body
