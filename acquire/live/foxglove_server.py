"""The live view: the run log's channels served to the Foxglove app over WebSocket.

:class:`LiveServer` wraps the Foxglove SDK's WebSocket server (PyPI ``foxglove-sdk``; the Foxglove
WebSocket protocol, subprotocol ``foxglove.sdk.v1`` — the successor of ``foxglove.websocket.v1``
with the same messages, which the Foxglove app speaks; viewers that only know
``foxglove.websocket.v1``, such as older Lichtblick releases, are refused by the SDK). A :class:`acquire.record.recorder.RunLog` given ``live=`` hands it every
message it writes — the same topic, schema name, JSON schema and JSON bytes as in the MCAP file —
so what Foxglove shows live is exactly what the log holds (``/tf``, ``/markers``,
``/joint_state``, ``/log``, ``/run/sample``, ``/run/event``, ``/<sensor>/markers``; see
:mod:`acquire.record.foxglove_view`). Open it in Foxglove with *Open connection → Foxglove WebSocket →
ws://HOST:PORT* and load the layout ``calib/data/foxglove/remaster-layout.json`` (``acquire examples`` prints its installed path).

The server binds to loopback unless told otherwise: anyone who can connect sees the run.
Channels outlive a run (the daemon keeps one server for all its runs); a topic whose schema
changes is re-advertised.
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765


class LiveServerError(RuntimeError):
    """The live view cannot start (port taken, SDK missing); the message says what to do."""


class LiveServer:
    """A Foxglove WebSocket server for the run's channels. Thread-safe. Close it with ``close``.

    host: interface to bind ("127.0.0.1" by default; "0.0.0.0" exposes the run to the network).
    port: TCP port (0 picks a free one; see ``port``). name: shown by Foxglove as the server name.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, name: str = "remaster") -> None:
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"live view port must be an integer in 0..65535, given {port!r}")
        try:
            import foxglove
        except ImportError as exc:
            raise LiveServerError("the live view needs the Foxglove SDK: pip install foxglove-sdk") from exc
        self._fg = foxglove
        self._ctx = foxglove.Context()
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._ctx)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types from Rust
            raise LiveServerError(f"cannot start the live view on {host}:{port}: {exc} (is the port in use? "
                                  "choose another with --live-port)") from exc
        self.host = host
        self._lock = threading.Lock()
        self._channels: dict[str, tuple[object, tuple[str, bytes]]] = {}
        self._closed = False
        log.info("live view: Foxglove WebSocket server on ws://%s:%d", host, self.port)

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return int(self._server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def advertise(self, topic: str, schema_name: str, json_schema: bytes):
        """Make ``topic`` known to clients (schema encoding ``jsonschema``, message encoding
        ``json``); returns the SDK channel, or None once closed. A changed schema re-advertises."""
        with self._lock:
            if self._closed:
                return None
            known = self._channels.get(topic)
            if known is None or known[1] != (schema_name, bytes(json_schema)):
                if known is not None:
                    known[0].close()
                schema = self._fg.Schema(name=schema_name, encoding="jsonschema", data=bytes(json_schema))
                channel = self._fg.Channel(topic, schema=schema, message_encoding="json", context=self._ctx)
                known = (channel, (schema_name, bytes(json_schema)))
                self._channels[topic] = known
            return known[0]

    def publish(self, topic: str, schema_name: str, json_schema: bytes, data: bytes, log_time_ns: int) -> None:
        """Send one JSON message (``data``, UTF-8 JSON bytes) on ``topic`` to subscribed clients
        (advertising the channel first if needed)."""
        channel = self.advertise(topic, schema_name, json_schema)
        if channel is not None:
            channel.log(bytes(data), log_time=int(log_time_ns))

    def close(self) -> None:
        """Stop the server (clients are disconnected). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            channels = [c for c, _ in self._channels.values()]
            self._channels.clear()
        for c in channels:
            c.close()
        self._server.stop()
        log.info("live view stopped")

    def __enter__(self) -> "LiveServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
