"""Alerts reach a webhook (a real HTTP server on loopback) and a command; a failing hook is logged,
never raised."""

import json
import sys
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer

from acquire.station.alerts import Alerter


def test_an_event_is_posted_to_the_webhook_and_piped_to_the_command(tmp_path):
    received: list[dict] = []

    class Hook(BaseHTTPRequestHandler):
        def do_POST(self):  # noqa: N802 - the http.server API
            received.append(json.loads(self.rfile.read(int(self.headers["Content-Length"]))))
            self.send_response(204)
            self.end_headers()

        def log_message(self, *args):
            pass

    server = HTTPServer(("127.0.0.1", 0), Hook)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    out = tmp_path / "events.txt"
    cmd = [sys.executable, "-c", f"import os, sys; open({str(out)!r}, 'w').write(os.environ['REMASTER_EVENT'] + "
                                 "' ' + sys.stdin.read())"]
    try:
        body = Alerter(cmd, f"http://127.0.0.1:{server.server_port}/remaster", 10).send(
            "state", "robot R1: calibrated → drifted", robot_serial="R1", to="drifted")
    finally:
        server.shutdown()
        server.server_close()
    assert received == [body] and body["event"] == "state" and body["robot_serial"] == "R1"
    event, payload = out.read_text().split(" ", 1)
    assert event == "state" and json.loads(payload) == body


def test_a_failing_hook_is_logged_and_the_station_goes_on(tmp_path, caplog):
    alerter = Alerter([sys.executable, "-c", "import sys; sys.exit('pager down')"], "http://127.0.0.1:9/none", 2)
    body = alerter.send("damaged", "archive: x: result.json missing")
    assert body["event"] == "damaged"
    assert "exited 1: pager down" in caplog.text and "alert webhook http://127.0.0.1:9/none failed" in caplog.text
