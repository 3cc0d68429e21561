"""The live view's TCP front: lets clients of both Foxglove subprotocol names connect.

foxglove-sdk's WebSocket server accepts only the subprotocol ``foxglove.sdk.v1`` and answers
HTTP 400 to a client that offers only ``foxglove.websocket.v1`` (older Foxglove app versions,
Lichtblick, roslibjs-foxglove). The SDK has no option for further names, and its maintainers say
the two are, for now, the same protocol under two names. So :class:`SubprotocolFront` listens
on the address the operator configured, and for each client:

1. reads the HTTP upgrade request (at most :data:`MAX_HEAD_BYTES`, within
   ``handshake_timeout_s``);
2. when the client offers ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1``, rewrites the
   ``Sec-WebSocket-Protocol`` request header to ``foxglove.sdk.v1`` (nothing else: the key, the
   extensions and the rest pass unchanged, and ``Sec-WebSocket-Accept`` depends on the key
   only) and, in the SDK's ``101`` answer, names the protocol back as the client offered it;
   any other request is forwarded untouched, so the SDK itself refuses an unknown subprotocol;
3. then splices bytes both ways until either side closes.

Bounded: at most ``max_clients`` connections at once (the next one gets HTTP 503), a head of at
most :data:`MAX_HEAD_BYTES`, a handshake within ``handshake_timeout_s``, and a slow client is
back-pressured (the front stops reading from the SDK, whose own per-client queue then drops the
oldest messages, as without the front). The SDK listens on an ephemeral port of 127.0.0.1 only;
the front binds the configured host (127.0.0.1 by default). Its asyncio loop runs in one thread
of its own, started by :meth:`SubprotocolFront.start` and joined by :meth:`SubprotocolFront.stop`;
every connection's task is kept and cancelled at stop. Nothing here raises into the session:
a failed connection is counted and logged through ``on_error``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from collections.abc import Callable

__all__ = [
    "LEGACY_SUBPROTOCOL",
    "MAX_HEAD_BYTES",
    "SDK_SUBPROTOCOL",
    "SubprotocolFront",
    "rewrite_request",
    "rewrite_response",
]

logger = logging.getLogger(__name__)

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
"""The subprotocol foxglove-sdk's server accepts."""
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
"""The older name of the same protocol, all that older clients offer."""
MAX_HEAD_BYTES = 16384
"""Largest HTTP head (request or answer) the front reads; a browser's is well under 4 KiB."""
_HEADER = b"sec-websocket-protocol"
_CHUNK = 65536
_CLOSE_GRACE_S = 2.0  # after one side closed, how long the other may still finish its close
_JOIN_TIMEOUT_S = 5.0


def _split_head(head: bytes) -> tuple[bytes, list[bytes]]:
    lines = head.split(b"\r\n")
    return lines[0], [line for line in lines[1:] if line]


def _offered(lines: list[bytes]) -> list[str]:
    out: list[str] = []
    for line in lines:
        name, _, value = line.partition(b":")
        if name.strip().lower() == _HEADER:
            out += [p.strip() for p in value.decode("latin-1").split(",") if p.strip()]
    return out


def rewrite_request(head: bytes) -> tuple[bytes, str | None]:
    """The upgrade request as the SDK must see it, and the name to answer with.

    Args:
        head: The request head without its final blank line (``b"GET / HTTP/1.1\\r\\n..."``).

    Returns:
        ``(head, answer_as)``: when the client offers the legacy name and not the SDK's, the
        head with its ``Sec-WebSocket-Protocol`` header(s) replaced by one naming
        ``foxglove.sdk.v1``, and ``answer_as = "foxglove.websocket.v1"``; otherwise ``head``
        unchanged and None.
    """
    first, lines = _split_head(head)
    offered = _offered(lines)
    if SDK_SUBPROTOCOL in offered or LEGACY_SUBPROTOCOL not in offered:
        return head, None
    kept = [line for line in lines if line.partition(b":")[0].strip().lower() != _HEADER]
    kept.append(b"Sec-WebSocket-Protocol: " + SDK_SUBPROTOCOL.encode())
    return b"\r\n".join([first, *kept]), LEGACY_SUBPROTOCOL


def rewrite_response(head: bytes, answer_as: str | None) -> bytes:
    """The SDK's answer with the chosen subprotocol named as the client offered it.

    Args:
        head: The answer's head without its final blank line.
        answer_as: From :func:`rewrite_request`; None leaves the answer as it is.
    """
    if answer_as is None:
        return head
    first, lines = _split_head(head)
    out = []
    for line in lines:
        name, _, value = line.partition(b":")
        if name.strip().lower() == _HEADER and value.strip() == SDK_SUBPROTOCOL.encode():
            line = name + b": " + answer_as.encode()
        out.append(line)
    return b"\r\n".join([first, *out])


class SubprotocolFront:
    """A TCP front on ``host:port`` for the SDK's server on ``127.0.0.1:target_port``.

    Args:
        host: Address to bind.
        port: Port to bind (0: a free one; :attr:`port` tells which).
        target_port: The SDK server's port on 127.0.0.1.
        max_clients: Connections at once (the next gets HTTP 503).
        handshake_timeout_s: Time a client and the SDK each have for their HTTP head.
        on_error: Called with ``(kind, text)`` for each failed connection (from the front's
            thread); it must not raise.
    """

    def __init__(self, host: str, port: int, target_port: int, *, max_clients: int = 16,
                 handshake_timeout_s: float = 5.0,
                 on_error: Callable[[str, str], None] | None = None) -> None:
        self.host = host
        self.requested_port = port
        self.target_port = target_port
        self.max_clients = max_clients
        self.handshake_timeout_s = handshake_timeout_s
        self.on_error = on_error
        #: Connections served, and of those the ones whose subprotocol name was translated.
        self.connections = 0
        self.translated = 0
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stopping: asyncio.Event | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    @property
    def open_connections(self) -> int:
        """Client connections being served now."""
        return len(self._tasks)

    @property
    def port(self) -> int | None:
        """The port the front listens on, or None when it does not."""
        return None if self._sock is None else int(self._sock.getsockname()[1])

    def start(self) -> None:
        """Bind and listen (in the caller's thread, so a taken port raises here), then serve
        from the front's own thread.

        Raises:
            OSError: The address cannot be bound (in use, not this machine's).
        """
        family, _, _, _, address = socket.getaddrinfo(self.host, self.requested_port,
                                                      type=socket.SOCK_STREAM,
                                                      flags=socket.AI_PASSIVE)[0]
        sock = socket.create_server(address[:2], family=family, backlog=self.max_clients)
        sock.setblocking(False)
        self._sock = sock
        self._loop = asyncio.new_event_loop()
        self._stopping = asyncio.Event()
        self._thread = threading.Thread(target=self._run, name="hilbo-live-front", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Close every connection and the listener, end the thread. Idempotent."""
        loop, thread, stopping = self._loop, self._thread, self._stopping
        self._thread = None
        if loop is not None and thread is not None and stopping is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended (its thread failed)
                loop.call_soon_threadsafe(stopping.set)
            thread.join(timeout=_JOIN_TIMEOUT_S)
            if thread.is_alive():
                logger.error("live view: the front's thread did not end within %g s", _JOIN_TIMEOUT_S)
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    # ------------------------------------------------------------------ the front's thread
    def _run(self) -> None:
        loop = self._loop
        if loop is None:  # start() sets it before the thread starts
            return
        try:
            loop.run_until_complete(self._serve())
        except Exception as err:  # the live view never ends a session: logged, the front is off
            self._failed("front", f"the live view's front stopped: {type(err).__name__}: {err}")
        finally:
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _serve(self) -> None:
        if self._sock is None or self._stopping is None:  # start() sets both first
            return
        server = await asyncio.start_server(self._accepted, sock=self._sock, limit=MAX_HEAD_BYTES)
        try:
            await self._stopping.wait()
        finally:
            server.close()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)
            await server.wait_closed()

    async def _accepted(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is None or len(self._tasks) >= self.max_clients:
            self._failed("too_many_clients", f"live view: a client refused, {self.max_clients} "
                                              "are connected already")
            writer.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n"
                         b"Connection: close\r\n\r\n")
            with contextlib.suppress(OSError):
                await writer.drain()
            writer.close()
            return
        self._tasks.add(task)
        try:
            await self._relay(reader, writer)
        except asyncio.CancelledError:
            # Only stop() cancels a connection, and the connection ends here. Not re-raised:
            # asyncio's stream server (3.11) logs a cancelled callback task as an error.
            return
        except Exception as err:  # whatever one connection does, the others and the session go on
            self._failed(type(err).__name__, f"live view: a client connection failed: {err!r}")
        finally:
            self._tasks.discard(task)
            writer.close()

    async def _relay(self, client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        async with asyncio.timeout(self.handshake_timeout_s):
            request = await client_r.readuntil(b"\r\n\r\n")
            head, answer_as = rewrite_request(request[:-4])
            sdk_r, sdk_w = await asyncio.open_connection("127.0.0.1", self.target_port,
                                                         limit=MAX_HEAD_BYTES)
        try:
            # Bytes after either head (a first frame sent without waiting) stay in the readers'
            # buffers, and the pipes below pass them on first.
            sdk_w.write(head + b"\r\n\r\n")
            async with asyncio.timeout(self.handshake_timeout_s):
                answer = await sdk_r.readuntil(b"\r\n\r\n")
            client_w.write(rewrite_response(answer[:-4], answer_as) + b"\r\n\r\n")
            self.connections += 1
            if answer_as is not None and answer.startswith(b"HTTP/1.1 101"):
                self.translated += 1
            up = asyncio.ensure_future(_pipe(client_r, sdk_w))
            down = asyncio.ensure_future(_pipe(sdk_r, client_w))
            try:
                _, pending = await asyncio.wait({up, down}, return_when=asyncio.FIRST_COMPLETED)
                if pending:  # the other side's close handshake may still be on its way
                    await asyncio.wait(pending, timeout=_CLOSE_GRACE_S)
            finally:
                for task in (up, down):
                    task.cancel()
                ended = await asyncio.gather(up, down, return_exceptions=True)
            for err in ended:  # a pipe's own failure (OSError is its peer's end, not one)
                if isinstance(err, Exception):
                    self._failed(type(err).__name__, f"live view: relaying a connection failed: {err!r}")
        finally:
            sdk_w.close()

    def _failed(self, kind: str, text: str) -> None:
        callback = self.on_error
        if callback is None:
            logger.debug("%s", text)
            return
        try:
            callback(kind, text)
        except Exception:  # the callback's own failure must not end the front
            logger.debug("live view: reporting a front error failed", exc_info=True)


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Copy until end of stream, waiting for the writer to drain (back-pressure), then pass
    the end on (a half-close: the peer's close handshake can still come back)."""
    with contextlib.suppress(OSError):
        while data := await reader.read(_CHUNK):
            writer.write(data)
            await writer.drain()
        if writer.can_write_eof():
            writer.write_eof()
