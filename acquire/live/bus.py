"""The Zenoh bus: one session per process, loopback-only unless configured otherwise.

Key expressions (DESIGN.md)::

    remaster/<cell>/<device>/<stream>          driver data: joint_state, markers, tracker/point, …
    remaster/<cell>/run/<run-id>/event         sequencer events (moved, settled, suspended, …)
    remaster/<cell>/run/<run-id>/sample        one record per measured configuration
    remaster/<cell>/run/<run-id>/status        the run's progress (RunController.status()) on every change
    remaster/<cell>/control/<verb>             the daemon's queryables (status, start, pause, …)

A cell on a plant's router has a *site* (``DaemonConfig.site``, ``Bus(site=…)``): every key of
that cell then starts ``remaster/<site>/<cell>/…`` (``remaster/<site>/<cell>/daemon``, its
runs, its control queries), so many sites' cells share one router without clashing and a
station subscribes to ``remaster/<site>/**`` or ``remaster/**``. Without a site (one cell, no
router) the keys are unchanged.

Build them with :func:`key`, which validates every chunk.

Payload encoding: a ``dict`` is sent as compact UTF-8 JSON (:mod:`acquire.record.jsonpayload`: numpy
arrays as lists, NaN/inf as ``null``) with Zenoh encoding ``application/json``; ``bytes`` are sent
unchanged as ``application/octet-stream``. Query parameters travel in the selector
(``key?name=value;…``), a query's body as JSON, an optional opaque attachment (e.g. a credential)
as bytes. A reply is one JSON object; a handler that raises sends an error reply
``{"error": <class name>, "message": <text>}``, which :meth:`Bus.query` raises as
:class:`BusQueryError`.

Network: by default the session is a ``peer`` that listens on ``tcp/127.0.0.1:7447`` (falling
back to an ephemeral loopback port when 7447 is taken), connects only to the endpoints it is
given, with multicast and gossip scouting off, so nothing leaves the machine. With
``listen_loopback_only=True`` every listen and connect endpoint must be a loopback address
(127.0.0.0/8, ::1, localhost) or a unix socket; a remote-facing daemon passes
``listen_loopback_only=False`` together with its TLS / access-control settings.

Measurement data is published with ``CongestionControl.BLOCK``: a slow subscriber slows the
publisher rather than losing samples. Always close the bus (context manager): an unclosed Zenoh
session keeps the process alive.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from typing import Any, Callable

import zenoh

from acquire.record.jsonpayload import PayloadError, decode_json, encode_json

log = logging.getLogger(__name__)

#: Root of every key expression of the product.
ROOT = "remaster"
#: The default listen endpoint of a process that serves a cell (the Zenoh default port, loopback).
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
_MODES = ("peer", "router", "client")
_CELL_RE = re.compile(r"^[a-z0-9_-]+$")
_CHUNK_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
_LOOPBACK_HOST_RE = re.compile(r"^(127\.\d{1,3}\.\d{1,3}\.\d{1,3}|\[::1\]|localhost)$")
_CONFIG_KEYS = {"mode", "listen", "connect", "zenoh"}
#: Zenoh configuration paths that a loopback-only bus refuses in ``config["zenoh"]``: they would
#: open it to the network behind the listen/connect checks.
_GUARDED_PREFIXES = ("mode", "listen", "connect", "scouting")

Callback = Callable[[str, bytes], None]
QueryHandler = Callable[[str, dict, "bytes | None", "bytes | None"], dict]


class BusError(RuntimeError):
    """The Zenoh session cannot be opened or used (closed bus, endpoint in use, transport error)."""


class BusConfigError(BusError, ValueError):
    """A bad key, key expression, endpoint or bus configuration; the message says what is allowed."""


class BusTimeoutError(BusError, TimeoutError):
    """No reply to a query within its timeout (nobody serves the key, or the server is stuck)."""


class BusQueryError(BusError):
    """The queryable answered with an error reply; ``error`` and ``message`` are the server's."""

    def __init__(self, key: str, error: str, message: str):
        super().__init__(f"query {key!r} refused: {error}: {message}")
        self.key = key
        self.error = error
        self.message = message


def key(cell: str, *parts: str, site: str | None = None) -> str:
    """``remaster/<cell>/<part>/…`` (``remaster/<site>/<cell>/<part>/…`` with a site), every chunk checked.

    ``cell`` and ``site`` match ``[a-z0-9_-]+``; each part is one or more ``/``-separated chunks of
    ``[A-Za-z0-9_.-]`` (no wildcards, no empty chunks). Raises BusConfigError otherwise.
    """
    if not isinstance(cell, str) or not _CELL_RE.match(cell):
        raise BusConfigError(f"cell id must match [a-z0-9_-]+, given {cell!r}")
    if not parts:
        raise BusConfigError("a key needs at least one part after the cell, e.g. key(cell, 'run', run_id, 'event')")
    chunks: list[str] = []
    for part in parts:
        if not isinstance(part, str):
            raise BusConfigError(f"key parts must be strings, given {part!r} ({type(part).__name__})")
        for chunk in part.split("/"):
            if not _CHUNK_RE.match(chunk):
                raise BusConfigError(
                    f"key part {part!r}: chunk {chunk!r} is not allowed; chunks are non-empty and use only "
                    "letters, digits, '_', '.', '-' (no wildcards)"
                )
            chunks.append(chunk)
    if site is not None:
        if not isinstance(site, str) or not _CELL_RE.match(site):
            raise BusConfigError(f"site id must match [a-z0-9_-]+, given {site!r}")
        return "/".join((ROOT, site, cell, *chunks))
    return "/".join((ROOT, cell, *chunks))


def run_key(cell: str, run_id: str, kind: str) -> str:
    """``remaster/<cell>/run/<run-id>/<kind>``; kind is ``event`` or ``sample``."""
    if kind not in ("event", "sample"):
        raise BusConfigError(f"run stream must be 'event' or 'sample', given {kind!r}")
    return key(cell, "run", run_id, kind)


def control_key(cell: str, verb: str, site: str | None = None) -> str:
    """``remaster/[<site>/]<cell>/control/<verb>`` (status, start, pause, resume, abort, runs, …)."""
    return key(cell, "control", verb, site=site)


def check_key_expr(expr: str, *, concrete: bool = False) -> str:
    """Validate a Zenoh key expression (``concrete``: no ``*``/``**``/``$*``); return it canonical."""
    if not isinstance(expr, str) or not expr:
        raise BusConfigError(f"key expression must be a non-empty string, given {expr!r}")
    try:
        ke = zenoh.KeyExpr(expr)
    except zenoh.ZError as exc:
        raise BusConfigError(f"invalid key expression {expr!r}: {exc}") from exc
    if concrete and ("*" in expr or "$" in expr):
        raise BusConfigError(f"a publisher/queryable/token key must be concrete (no wildcards), given {expr!r}")
    return str(ke)


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for Zenoh endpoints that stay on this machine (loopback IP or a unix socket)."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    proto, _, address = locator.partition("/")
    if proto.startswith("unixsock"):
        return True
    if proto not in ("tcp", "udp", "tls", "quic", "ws") or not address:
        return False
    host, _, port = address.rpartition(":")
    return bool(_LOOPBACK_HOST_RE.match(host)) and port.isdigit()


class Publisher:
    """A declared publisher on one concrete key. ``put`` accepts a dict (JSON) or bytes."""

    def __init__(self, pub: zenoh.Publisher, key_expr: str):
        self._pub = pub
        self.key = key_expr

    def put(self, payload: dict | bytes) -> None:
        data, encoding = _encode(payload)
        try:
            self._pub.put(data, encoding=encoding)
        except zenoh.ZError as exc:
            raise BusError(f"publishing on {self.key!r} failed: {exc}") from exc

    @property
    def matched(self) -> bool:
        """Whether any subscriber currently matches this publisher's key."""
        return bool(self._pub.matching_status.matching)

    def wait_matched(self, timeout: float) -> bool:
        """Block (at most ``timeout`` seconds) until a subscriber matches; return whether one did."""
        deadline = time.monotonic() + timeout
        while not self.matched:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except zenoh.ZError as exc:  # already undeclared with its session
            log.debug("undeclaring publisher %s: %s", self.key, exc)


class Subscription:
    """A live subscription; ``close()`` stops the callbacks."""

    def __init__(self, sub: zenoh.Subscriber, key_expr: str):
        self._sub = sub
        self.key_expr = key_expr

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError as exc:
            log.debug("undeclaring subscriber %s: %s", self.key_expr, exc)


class Queryable:
    """A declared queryable; ``close()`` stops serving."""

    def __init__(self, q: zenoh.Queryable, key_expr: str):
        self._q = q
        self.key = key_expr

    def close(self) -> None:
        try:
            self._q.undeclare()
        except zenoh.ZError as exc:
            log.debug("undeclaring queryable %s: %s", self.key, exc)


def _encode(payload: dict | bytes) -> tuple[bytes, zenoh.Encoding]:
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return bytes(payload), zenoh.Encoding.APPLICATION_OCTET_STREAM
    if isinstance(payload, dict):
        return encode_json(payload), zenoh.Encoding.APPLICATION_JSON
    raise PayloadError(f"payload must be a dict (sent as JSON) or bytes, given {type(payload).__name__}")


def build_config(config: dict | None, listen_loopback_only: bool) -> tuple[zenoh.Config, list[str], bool]:
    """The Zenoh configuration for ``Bus``; returns (config, listen endpoints, listen was defaulted).

    ``config`` keys (all optional): ``mode`` (peer | router | client, default peer), ``listen``
    (list of endpoints, default ``[DEFAULT_ENDPOINT]``; ``tcp/127.0.0.1:0`` picks a free port),
    ``connect`` (list of endpoints, default none), ``zenoh`` (``{config path: value}`` passed to
    ``Config.insert_json5``, e.g. TLS or access control; refused for listen/connect/scouting/mode
    paths while ``listen_loopback_only``).
    """
    config = dict(config or {})
    unknown = sorted(set(config) - _CONFIG_KEYS)
    if unknown:
        raise BusConfigError(f"unknown bus config key(s) {unknown}; allowed: {sorted(_CONFIG_KEYS)}")
    mode = config.get("mode", "peer")
    if mode not in _MODES:
        raise BusConfigError(f"bus mode must be one of {list(_MODES)}, given {mode!r}")
    defaulted = "listen" not in config
    listen = [DEFAULT_ENDPOINT] if defaulted else config["listen"]
    connect = config.get("connect", [])
    for name, eps in (("listen", listen), ("connect", connect)):
        if not isinstance(eps, (list, tuple)) or not all(isinstance(e, str) and "/" in e for e in eps):
            raise BusConfigError(f"bus {name} must be a list of endpoints like 'tcp/127.0.0.1:7447', given {eps!r}")
        if listen_loopback_only:
            bad = [e for e in eps if not is_loopback_endpoint(e)]
            if bad:
                raise BusConfigError(
                    f"bus {name} endpoint(s) {bad} are not loopback; a loopback-only bus allows tcp/udp/tls/quic/ws on "
                    "127.0.0.0/8, [::1] or localhost, or unixsock-stream; remote access needs listen_loopback_only=False "
                    "with authentication configured"
                )
    overrides = config.get("zenoh", {})
    if not isinstance(overrides, dict):
        raise BusConfigError(f"bus config 'zenoh' must be a mapping of config paths to values, given {overrides!r}")
    if mode == "client" and not connect:
        raise BusConfigError("a client-mode bus needs at least one 'connect' endpoint")
    cfg = zenoh.Config()
    try:
        cfg.insert_json5("mode", json.dumps(mode))
        cfg.insert_json5("listen/endpoints", json.dumps([] if mode == "client" else list(listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("scouting/gossip/enabled", "false")
        if any(e.endswith(":0") for e in listen):
            # Only to learn the port the OS picked (see Bus.locators); read-only.
            cfg.insert_json5("adminspace/enabled", "true")
            cfg.insert_json5("adminspace/permissions", '{"read": true, "write": false}')
        for path, value in overrides.items():
            if listen_loopback_only and path.strip("/").split("/")[0] in _GUARDED_PREFIXES:
                raise BusConfigError(
                    f"bus config 'zenoh' path {path!r} is refused on a loopback-only bus; use the 'listen'/'connect'/'mode' "
                    "keys, or listen_loopback_only=False"
                )
            cfg.insert_json5(path, json.dumps(value))
    except zenoh.ZError as exc:
        raise BusConfigError(f"invalid zenoh configuration: {exc}") from exc
    return cfg, list(listen) if mode != "client" else [], defaulted


class Bus:
    """One Zenoh session for this process, with the product's key and payload conventions.

    Thread-safe; a context manager; ``close()`` is idempotent and undeclares everything.
    See the module docstring for the network defaults and the payload encoding.
    """

    def __init__(self, cell: str, *, config: dict | None = None, listen_loopback_only: bool = True,
                 site: str | None = None):
        key(cell, "x", site=site)  # validates the cell and site ids
        self.cell = cell
        #: The plant site of this cell (keys ``remaster/<site>/<cell>/…``), or None.
        self.site = site
        self.listen_loopback_only = listen_loopback_only
        cfg, listen, defaulted = build_config(config, listen_loopback_only)
        self._lock = threading.Lock()
        self._closed = False
        self._publishers: dict[str, Publisher] = {}
        self._entities: list[Any] = []
        fell_back = False
        try:
            self._session = zenoh.open(cfg)
        except zenoh.ZError as exc:
            if not (defaulted and "in use" in str(exc)):
                raise BusError(f"cannot open the Zenoh session (listen {listen}): {exc}") from exc
            fallback = dict(config or {}, listen=["tcp/127.0.0.1:0"])
            cfg, listen, _ = build_config(fallback, listen_loopback_only)
            try:
                self._session = zenoh.open(cfg)
            except zenoh.ZError as exc2:
                raise BusError(f"cannot open the Zenoh session (listen {listen}): {exc2}") from exc2
            fell_back = True
        self._listen = listen
        if fell_back:
            log.warning("%s is in use; listening on %s instead", DEFAULT_ENDPOINT, ", ".join(self.locators))
        log.debug("bus for cell %s open: zid %s, listening on %s", cell, self._session.zid(), listen)

    # -- lifecycle ---------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        """The underlying Zenoh session (for what this class does not wrap)."""
        self._check_open()
        return self._session

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise BusError(f"the bus of cell {self.cell!r} is closed")

    def close(self) -> None:
        """Undeclare every publisher, subscriber, queryable and token, then close the session."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = list(self._publishers.values()) + self._entities
            self._publishers.clear()
            self._entities.clear()
        for ent in reversed(entities):
            closer = getattr(ent, "close", None) or getattr(ent, "undeclare")
            try:
                closer()
            except zenoh.ZError as exc:  # e.g. a token its owner undeclared already
                # (named by its type: an undeclared zenoh entity raises in its own repr)
                log.debug("undeclaring a %s: %s", type(ent).__name__, exc)
        self._session.close()
        log.debug("bus for cell %s closed", self.cell)

    def __enter__(self) -> "Bus":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def locators(self) -> list[str]:
        """The endpoints this session actually listens on (ports resolved when ``:0`` was asked)."""
        self._check_open()
        zid = str(self._session.zid())
        try:
            replies = self._session.get(f"@/{zid}/*", timeout=1.0)
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    info = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
                if isinstance(info, dict) and "locators" in info:
                    return list(info["locators"])
        except zenoh.ZError as exc:
            log.debug("admin space query failed: %s", exc)
        return list(self._listen)

    # -- publish / subscribe ----------------------------------------------------------------
    def key(self, *parts: str) -> str:
        """``remaster/[<site>/]<this cell>/<parts…>``."""
        return key(self.cell, *parts, site=self.site)

    def publisher(self, key: str, *, reliable: bool = True) -> Publisher:
        """Declare a publisher on a concrete key; ``reliable`` → CongestionControl.BLOCK (else DROP)."""
        self._check_open()
        k = check_key_expr(key, concrete=True)
        cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        try:
            pub = Publisher(self._session.declare_publisher(k, congestion_control=cc), k)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a publisher on {k!r}: {exc}") from exc
        with self._lock:
            self._entities.append(pub)
        return pub

    def publish(self, key: str, payload: dict | bytes) -> None:
        """Publish one payload (dict → JSON) on ``key`` with blocking congestion control."""
        with self._lock:
            pub = self._publishers.get(key)
        if pub is None:
            self._check_open()
            k = check_key_expr(key, concrete=True)
            try:
                zpub = self._session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            except zenoh.ZError as exc:
                raise BusError(f"cannot declare a publisher on {k!r}: {exc}") from exc
            with self._lock:
                pub = self._publishers.setdefault(key, Publisher(zpub, k))
            if pub._pub is not zpub:
                zpub.undeclare()
        pub.put(payload)

    def release(self, prefix: str) -> int:
        """Undeclare the cached ``publish`` publishers on ``prefix`` and below (e.g. a finished
        run's keys); returns how many. Publishing there again declares afresh."""
        p = prefix.rstrip("/")
        with self._lock:
            keys = [k for k in self._publishers if k == p or k.startswith(p + "/")]
            pubs = [self._publishers.pop(k) for k in keys]
        for pub in pubs:
            pub.close()
        return len(pubs)

    def subscribe(self, key_expr: str, callback: Callback) -> Subscription:
        """Call ``callback(key, payload_bytes)`` for every sample matching ``key_expr`` (wildcards ok).

        Callbacks run on a Zenoh thread; exceptions they raise are logged, never propagated.
        """
        self._check_open()
        k = check_key_expr(key_expr)

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # a subscriber's bug must not kill the Zenoh thread
                log.exception("subscriber callback for %s failed on %s", k, sample.key_expr)

        try:
            sub = Subscription(self._session.declare_subscriber(k, on_sample), k)
        except zenoh.ZError as exc:
            raise BusError(f"cannot subscribe to {k!r}: {exc}") from exc
        with self._lock:
            self._entities.append(sub)
        return sub

    # -- liveliness -------------------------------------------------------------------------
    def liveliness_token(self, key: str) -> zenoh.LivelinessToken:
        """Announce ``key`` as alive for as long as the token (or the bus) lives."""
        self._check_open()
        k = check_key_expr(key, concrete=True)
        try:
            token = self._session.liveliness().declare_token(k)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a liveliness token on {k!r}: {exc}") from exc
        with self._lock:
            self._entities.append(token)
        return token

    def alive(self, key_expr: str, timeout: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens currently matching ``key_expr`` (sorted)."""
        self._check_open()
        k = check_key_expr(key_expr)
        try:
            replies = self._session.liveliness().get(k, timeout=timeout)
            # A token can answer over more than one route; a key is alive once.
            return sorted({str(r.ok.key_expr) for r in replies if r.ok is not None})
        except zenoh.ZError as exc:
            raise BusError(f"liveliness query {k!r} failed: {exc}") from exc

    def watch_liveliness(self, key_expr: str, callback: Callable[[str, bool], None], *, history: bool = True) -> Subscription:
        """Call ``callback(key, alive)`` when a matching token appears (True) or goes away (False)."""
        self._check_open()
        k = check_key_expr(key_expr)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("liveliness callback for %s failed", k)

        try:
            sub = Subscription(self._session.liveliness().declare_subscriber(k, on_sample, history=history), k)
        except zenoh.ZError as exc:
            raise BusError(f"cannot watch liveliness of {k!r}: {exc}") from exc
        with self._lock:
            self._entities.append(sub)
        return sub

    # -- queries ----------------------------------------------------------------------------
    def queryable(self, key: str, handler: QueryHandler) -> Queryable:
        """Serve queries on ``key``: ``handler(key, params, payload, attachment) -> dict`` (the JSON reply).

        ``params`` are the selector parameters (``key?a=1;b=2`` → ``{"a": "1", "b": "2"}``). If the
        handler raises, the querier gets an error reply naming the exception class and message.
        """
        self._check_open()
        k = check_key_expr(key)

        def on_query(query: zenoh.Query) -> None:
            with query:
                qkey = str(query.key_expr)
                try:
                    params = {name: value for name, value in query.parameters}
                    payload = query.payload.to_bytes() if query.payload is not None else None
                    attachment = query.attachment.to_bytes() if query.attachment is not None else None
                    reply = handler(qkey, params, payload, attachment)
                    data = encode_json(reply)
                except Exception as exc:  # every failure becomes an error reply, never a hang
                    log.warning("query %s refused: %s: %s", qkey, type(exc).__name__, exc)
                    err = encode_json({"error": type(exc).__name__, "message": str(exc)})
                    query.reply_err(err, encoding=zenoh.Encoding.APPLICATION_JSON)
                    return
                query.reply(query.key_expr, data, encoding=zenoh.Encoding.APPLICATION_JSON)

        try:
            q = Queryable(self._session.declare_queryable(k, on_query), k)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a queryable on {k!r}: {exc}") from exc
        with self._lock:
            self._entities.append(q)
        return q

    def wait_queryable(self, key: str, timeout: float) -> bool:
        """Block (at most ``timeout`` s) until a queryable serving ``key`` is known; return whether one is.

        Declarations travel asynchronously: a client that has just connected may query before the
        server's queryable reached it, and get no reply. Call this first when that matters.
        """
        self._check_open()
        k = check_key_expr(key)
        try:
            querier = self._session.declare_querier(k)
        except zenoh.ZError as exc:
            raise BusError(f"cannot declare a querier on {k!r}: {exc}") from exc
        try:
            deadline = time.monotonic() + timeout
            while not querier.matching_status.matching:
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.01)
            return True
        finally:
            querier.undeclare()

    def query(
        self,
        key: str,
        payload: dict | None = None,
        timeout: float = 5.0,
        *,
        params: dict[str, str] | None = None,
        attachment: bytes | None = None,
    ) -> dict:
        """Ask the queryable serving ``key``; return its JSON reply.

        Raises BusTimeoutError when nothing answers within ``timeout`` seconds and BusQueryError
        when the server replies with an error.
        """
        self._check_open()
        k = check_key_expr(key)
        if timeout <= 0:
            raise BusConfigError(f"query timeout must be > 0 s, given {timeout}")
        selector = k
        if params:
            for name, value in params.items():
                if not re.match(r"^[A-Za-z0-9_.\-]+$", str(name)) or any(c in str(value) for c in ";=&#"):
                    raise BusConfigError(f"query parameter {name!r}={value!r}: names use [A-Za-z0-9_.-], values no ';=&#'")
            selector = k + "?" + ";".join(f"{n}={v}" for n, v in params.items())
        kwargs: dict[str, Any] = {"timeout": timeout}
        if payload is not None:
            kwargs["payload"] = encode_json(payload)
            kwargs["encoding"] = zenoh.Encoding.APPLICATION_JSON
        if attachment is not None:
            kwargs["attachment"] = bytes(attachment)
        error: BusQueryError | None = None
        try:
            for reply in self._session.get(selector, **kwargs):
                if reply.ok is not None:
                    try:
                        return decode_json(reply.ok.payload.to_bytes())
                    except PayloadError as exc:
                        raise BusError(f"reply to {k!r} is not a JSON object: {exc}") from exc
                if error is None:
                    raw = reply.err.payload.to_bytes()
                    try:
                        body = decode_json(raw)
                        error = BusQueryError(k, str(body.get("error", "error")), str(body.get("message", "")))
                    except PayloadError:
                        text = raw.decode("utf-8", "replace")
                        if text.strip().lower() == "timeout":  # Zenoh's own error reply on expiry
                            raise BusTimeoutError(
                                f"the queryable serving {k!r} did not answer within {timeout} s"
                            ) from None
                        error = BusQueryError(k, "error", text)
        except zenoh.ZError as exc:
            raise BusError(f"query {k!r} failed: {exc}") from exc
        if error is not None:
            raise error
        raise BusTimeoutError(f"no reply to query {k!r} within {timeout} s (is the daemon running and connected?)")
