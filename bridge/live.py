"""Live view: the session's log channels streamed to Foxglove over a WebSocket.

A :class:`LiveServer` wraps the Foxglove SDK's WebSocket server (``foxglove-sdk``). The session
log mirrors every record it writes with :meth:`LiveServer.publish`:
the same topic, schema name, JSON schema and JSON bytes as the MCAP file, so Foxglove shows the
same panels live as it does on the file afterwards. One channel per topic, created on first use.

Safety of the session comes first: the live view is a convenience and must never block or end a
session. :meth:`LiveServer.publish` does not raise; a failure is logged once per kind and counted
in :attr:`LiveServer.stats`. A server that cannot start (port taken) logs why and publishes
nothing. Each server has its own ``foxglove.Context``, so two servers (tests) never share channels.

Slow clients: ``Channel.log`` only hands the bytes to the SDK, which queues them per client
(``message_backlog_size`` messages; when full the *oldest* data message is dropped, and a client
whose control queue fills is disconnected); the front below passes that on (it stops reading
from the SDK while a client does not read). tests/bridge/test_live.py measures publishing to a
client that never reads.

Both subprotocol names connect. The SDK accepts only ``foxglove.sdk.v1`` and answers HTTP 400
to a client that offers only the older ``foxglove.websocket.v1`` (older Foxglove app versions,
Lichtblick); for now the two are the same protocol under two names, and the SDK has no option
for a second name. So the SDK listens on an ephemeral port of 127.0.0.1 and a small TCP front
(:class:`bridge.live_front.SubprotocolFront`, its own thread, ended at :meth:`LiveServer.stop`)
listens on the configured host and port, rewrites only the handshake's
``Sec-WebSocket-Protocol`` header (``foxglove.websocket.v1`` → ``foxglove.sdk.v1``, and the
answer back to the name the client offered) and then passes the bytes both ways. A client
offering neither name is refused by the SDK as before (HTTP 400).

The SDK's own log lines (a client refused at the handshake; a dropped slow client) go through
Python logging (``foxglove.set_log_level``), and the front's (a connection that failed) straight,
to :attr:`LiveServer.on_sdk_log` — the session log's events in ``hilbo run`` — and never to the
terminal, where they were printed over the operator view.

Binds 127.0.0.1 by default: the stream carries the session's data, and nothing here
authenticates a client. Open it in Foxglove with "Open connection" → "Foxglove WebSocket" →
``ws://127.0.0.1:8765``.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from bridge.errors import BridgeError
from bridge.live_front import SubprotocolFront

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "LiveError",
    "LiveServer",
    "LiveSink",
    "LiveStats",
]

logger = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
"""Loopback only unless configured otherwise (the stream is not authenticated)."""
DEFAULT_PORT = 8765
"""Foxglove's default WebSocket port (what its "Open connection" dialog proposes)."""
_DEFAULT_BACKLOG = 1024  # messages queued per client before the oldest is dropped (SDK default)
_SDK_HOST = "127.0.0.1"  # the SDK itself is reached only through the front (module docstring)


class LiveError(BridgeError, ValueError):
    """A bad live-view option (raised by the constructor only; publishing never raises)."""


class LiveSink(Protocol):
    """What the session log needs of a live view (:class:`LiveServer` is one)."""

    def publish(self, topic: str, schema_name: str, json_schema: Mapping[str, Any],
                message_json: bytes | str, log_time_ns: int) -> None:
        """Mirror one record already written to the log; never raises."""
        ...


@dataclass
class LiveStats:
    """What a :class:`LiveServer` did.

    Attributes:
        published: Messages handed to the SDK.
        channels: Channels created (one per topic).
        errors: Failed publishes (or channel creations), by kind.
    """

    published: int = 0
    channels: int = 0
    errors: Counter[str] = field(default_factory=Counter)


class LiveServer:
    """The Foxglove WebSocket server of one session; a context manager.

    Args:
        host: Address to bind (``127.0.0.1`` by default: this machine only).
        port: TCP port, 0-65535 (0: any free port; :attr:`port` tells which).
        name: Server name Foxglove shows.
        message_backlog_size: Messages queued per client before the oldest is dropped.

    Raises:
        LiveError: A bad option.

    Example:
        >>> with LiveServer(port=8765) as live, SessionLog(path, ..., live=live) as log:
        ...     ...  # every record the log writes is also streamed
    """

    def __init__(self, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, name: str = "hilbo",
                 message_backlog_size: int = _DEFAULT_BACKLOG) -> None:
        if not isinstance(host, str) or not host:
            raise LiveError(f"live host={host!r}; expected an address such as '127.0.0.1'")
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise LiveError(f"live port={port!r}; expected an integer in [0, 65535] (0: any free port)")
        if isinstance(message_backlog_size, bool) or not isinstance(message_backlog_size, int) \
                or message_backlog_size < 1:
            raise LiveError(f"message_backlog_size={message_backlog_size!r}; expected an integer >= 1")
        self.host = host
        self.name = name
        self.stats = LiveStats()
        self.start_error: str | None = None
        self._requested_port = port
        self._backlog = message_backlog_size
        self._server: Any = None
        self._front: SubprotocolFront | None = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._schemas: dict[str, str] = {}
        #: Called with each line the SDK logs (text, logging level), from the SDK's thread;
        #: None: counted in :attr:`stats` only.
        self.on_sdk_log: Callable[[str, int], None] | None = None
        self._sdk_handler: _SdkLogHandler | None = None

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> LiveServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> bool:
        """Start the server; on failure log why and stay off (the session goes on without it).

        Returns:
            True when the server listens.
        """
        if self._server is not None:
            return True
        try:
            import foxglove  # deferred: a session without the live view never loads the SDK

            self._route_sdk_logging(foxglove)
            self._context = foxglove.Context()
            self._server = foxglove.start_server(
                name=self.name, host=_SDK_HOST, port=0, context=self._context,
                message_backlog_size=self._backlog)
            # A taken or foreign address fails here; stop() below then ends the SDK's server.
            self._front = SubprotocolFront(self.host, self._requested_port, int(self._server.port),
                                           on_error=self._front_error)
            self._front.start()
        except (ImportError, OSError, RuntimeError, ValueError, TypeError) as err:
            self.start_error = f"{type(err).__name__}: {err}"
            logger.error("live view: cannot listen on %s:%s (%s); the session goes on without it",
                         self.host, self._requested_port, self.start_error)
            self.stop()
            return False
        logger.info("live view: %s", self.url)
        return True

    def stop(self) -> None:
        """Close the channels and the front's connections, stop the server. Idempotent."""
        front, self._front = self._front, None
        if front is not None:
            front.stop()  # first: its clients see the end of the stream, not a reset
        server, self._server = self._server, None
        channels, self._channels = self._channels, {}
        for topic, channel in channels.items():
            try:
                channel.close()
            except (RuntimeError, ValueError) as err:
                self._error("close", f"closing channel {topic}: {err}")
        if server is not None:
            server.stop()
        self._context = None
        handler, self._sdk_handler = self._sdk_handler, None
        if handler is not None:
            sdk = logging.getLogger(_SDK_LOGGER)
            sdk.removeHandler(handler)
            sdk.propagate = handler.propagated

    def _route_sdk_logging(self, foxglove: Any) -> None:
        """The SDK's log lines to :attr:`on_sdk_log` instead of the terminal."""
        # Without it the SDK writes its lines to stderr itself. The first call in a process
        # decides (a later one has no effect); WARNING: refusals and drops, not each client.
        foxglove.set_log_level(logging.WARNING)
        sdk = logging.getLogger(_SDK_LOGGER)
        self._sdk_handler = _SdkLogHandler(self, propagated=sdk.propagate)
        sdk.addHandler(self._sdk_handler)
        sdk.propagate = False

    def _sdk_line(self, text: str, level: int, *, kind: str | None = None) -> None:
        self.stats.errors[kind or "sdk_" + logging.getLevelName(level).lower()] += 1
        callback = self.on_sdk_log
        if callback is not None:
            try:
                callback(text, level)
            except Exception:  # the live view never ends a session (module docstring)
                logger.debug("live view: forwarding an SDK log line failed", exc_info=True)

    def _front_error(self, kind: str, text: str) -> None:
        # From the front's thread: counted, and forwarded like the SDK's own lines.
        self._sdk_line(text, logging.WARNING, kind="front_" + kind)

    @property
    def running(self) -> bool:
        """True while the server listens."""
        return self._server is not None

    @property
    def port(self) -> int | None:
        """The port clients connect to (the free port chosen for ``port=0``), or None when off."""
        if self._server is None or self._front is None:
            return None
        return self._front.port

    @property
    def translated(self) -> int:
        """Connections that offered only ``foxglove.websocket.v1`` and were let in."""
        return 0 if self._front is None else self._front.translated

    @property
    def url(self) -> str | None:
        """``ws://host:port`` to open in Foxglove, or None when off."""
        if self._server is None:
            return None
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    # ------------------------------------------------------------------ publishing
    def publish(self, topic: str, schema_name: str, json_schema: Mapping[str, Any],
                message_json: bytes | str, log_time_ns: int) -> None:
        """Stream one record on ``topic`` (its channel is created on first use). Never raises.

        Args:
            topic: The log's topic (``/breaths``...).
            schema_name: The log's schema name for the topic (``hilbo.Breath``...).
            json_schema: The topic's JSON schema (draft-07 object), as in the log.
            message_json: The record as written to the log (UTF-8 JSON).
            log_time_ns: Its log time, ns.
        """
        if self._server is None:
            return
        # Anything the SDK raises is caught: the live view must never end a session (logged
        # once per kind and counted, so a broken view is visible without flooding the log).
        try:
            channel = self._channels.get(topic)
            if channel is None:
                channel = self._open_channel(topic, schema_name, json_schema)
            elif self._schemas[topic] != schema_name:
                self._error("schema_changed", f"{topic}: schema {schema_name!r} after "
                                              f"{self._schemas[topic]!r}; streamed on the first")
            data = message_json.encode() if isinstance(message_json, str) else bytes(message_json)
            channel.log(data, log_time=_log_time(log_time_ns))
            self.stats.published += 1
        except Exception as err:  # see the comment above: counted and logged, never raised
            self._error(type(err).__name__, f"{topic}: {err}")

    def _open_channel(self, topic: str, schema_name: str, json_schema: Mapping[str, Any]) -> Any:
        import foxglove

        schema = foxglove.Schema(name=schema_name, encoding="jsonschema",
                                 data=json.dumps(dict(json_schema)).encode())
        channel = foxglove.Channel(topic, schema=schema, message_encoding="json",
                                   context=self._context)
        self._channels[topic] = channel
        self._schemas[topic] = schema_name
        self.stats.channels += 1
        return channel

    def _error(self, kind: str, text: str) -> None:
        self.stats.errors[kind] += 1
        if self.stats.errors[kind] == 1:
            logger.error("live view: %s (further %s errors are only counted)", text, kind)


_SDK_LOGGER = "foxglove"


class _SdkLogHandler(logging.Handler):
    """Hands the SDK's log records to their :class:`LiveServer` (from the SDK's thread)."""

    def __init__(self, server: LiveServer, *, propagated: bool) -> None:
        super().__init__(logging.WARNING)
        self.server = server
        self.propagated = propagated

    def emit(self, record: logging.LogRecord) -> None:
        self.server._sdk_line(record.getMessage(), record.levelno)


def _log_time(log_time_ns: int) -> int | None:
    # The protocol's timestamp is a uint64; out of range lets the SDK stamp it with its own clock.
    t = int(log_time_ns)
    return t if 0 <= t < 2**64 else None
