"""Network transports: TCP client (the cart or its gateway is the server) and UDP receiver.

TCP: :func:`asyncio.open_connection` with a connect timeout; the peer closing the connection
is a drop, and the base class reconnects with backoff. UDP: a datagram endpoint bound on the
configured address; each datagram holds one or more whole lines (a datagram's end also ends its
last line), queued up to ``queue_size`` — beyond that datagrams are dropped and counted as
``overflow`` rather than let memory grow.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from typing import Annotated

from msgspec import Meta

from drivers.cart._options import check_declared
from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES
from drivers.cart.reasons import RejectReason
from drivers.cart.transport import Backoff, CartTransport, TransportHooks
from drivers.config_model import FINITE
from drivers.errors import DriverConfigError

__all__ = ["TcpOptions", "TcpTransport", "UdpOptions", "UdpTransport"]

_log = logging.getLogger(__name__)
_READ_BYTES = 1 << 16


@dataclass(frozen=True, slots=True)
class TcpOptions:
    """Options of the ``"tcp"`` transport.

    Attributes:
        host: Cart or gateway address (name or IP).
        port: TCP port, 1–65535.
        connect_timeout_s: Longest wait for one connection attempt.
        idle_timeout_s: Reconnect after this long without a byte (a half-open connection
            otherwise never errors); None disables.
        max_line_bytes: Longest line kept.
        backoff: Reconnection policy.
    """

    host: Annotated[str, Meta(min_length=1)]
    port: Annotated[int, Meta(ge=1, le=65535)]
    connect_timeout_s: Annotated[float, Meta(gt=0.0, le=FINITE)] = 5.0
    idle_timeout_s: Annotated[float, Meta(gt=0.0, le=FINITE)] | None = None
    max_line_bytes: Annotated[int, Meta(ge=16)] = DEFAULT_MAX_LINE_BYTES
    backoff: Backoff = field(default_factory=Backoff)

    def __post_init__(self) -> None:
        check_declared(self)
        if not isinstance(self.backoff, Backoff):
            raise DriverConfigError(f"backoff = {self.backoff!r}: expected a Backoff table")
        _check_host(self.host, self.port)


def _check_host(host: str, port: int) -> None:
    """A host with its port glued on (``127.0.0.1:5050``) would only fail at connect time as an
    unknown name; the port has its own key. (IPv6 literals go in brackets or bare, e.g. ``::1``.)"""
    name, sep, tail = host.rpartition(":")
    if sep and tail.isdigit() and name and not (":" in name and not name.endswith("]")):
        raise DriverConfigError(f"host = {host!r}: expected a host name or address without a port "
                                f"(the port is its own key, port = {port} here)")


class TcpTransport(CartTransport):
    """Lines from a TCP connection to the cart; reconnects with backoff when it closes."""

    name = "tcp"

    def __init__(self, options: TcpOptions, hooks: TransportHooks | None = None) -> None:
        super().__init__(
            max_line_bytes=options.max_line_bytes,
            backoff=options.backoff,
            idle_timeout_s=options.idle_timeout_s,
            hooks=hooks,
        )
        self.options = options
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    def describe(self) -> str:
        return f"tcp {self.options.host}:{self.options.port}"

    async def _open_link(self) -> None:
        async with asyncio.timeout(self.options.connect_timeout_s):
            self._reader, self._writer = await asyncio.open_connection(self.options.host, self.options.port)

    async def _read_chunk(self) -> bytes | None:
        if self._reader is None:
            raise ConnectionResetError("not connected")
        data = await self._reader.read(_READ_BYTES)
        if not data:
            raise ConnectionResetError("connection closed by the cart")
        return data

    async def _close_link(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        if writer is None:
            return
        writer.close()
        try:
            await writer.wait_closed()
        except OSError as err:  # the peer may already have reset the connection
            _log.debug("tcp close: %s", err)


@dataclass(frozen=True, slots=True)
class UdpOptions:
    """Options of the ``"udp"`` transport.

    Attributes:
        port: Local UDP port to bind (0 picks a free one; see
            :attr:`UdpTransport.local_address`).
        host: Local address to bind; ``"0.0.0.0"`` (or the lab network's interface address)
            to receive from a cart on the network. Defaults to loopback so nothing is exposed
            by accident.
        queue_size: Datagrams buffered before new ones are dropped as ``overflow``.
        max_line_bytes: Longest line kept.
    """

    port: Annotated[int, Meta(ge=0, le=65535)]
    host: Annotated[str, Meta(min_length=1)] = "127.0.0.1"
    queue_size: Annotated[int, Meta(ge=1)] = 1024
    max_line_bytes: Annotated[int, Meta(ge=16)] = DEFAULT_MAX_LINE_BYTES

    def __post_init__(self) -> None:
        check_declared(self)


class _DatagramQueue(asyncio.DatagramProtocol):
    """Puts received datagrams on a bounded queue; counts what does not fit."""

    def __init__(self, queue: asyncio.Queue[bytes], counters: dict[str, int]) -> None:
        self._queue = queue
        self._counters = counters

    def datagram_received(self, data: bytes, addr: tuple[str | object, ...]) -> None:
        if not data:
            return
        try:
            self._queue.put_nowait(data)
        except asyncio.QueueFull:
            self._counters[RejectReason.OVERFLOW] = self._counters.get(RejectReason.OVERFLOW, 0) + 1

    def error_received(self, exc: Exception) -> None:
        # ICMP errors for datagrams we never sent (we only receive) are noise; log, don't stop.
        _log.warning("udp receive error: %s", exc)


class UdpTransport(CartTransport):
    """Lines from UDP datagrams arriving on a bound local address; no reconnection needed."""

    name = "udp"

    def __init__(self, options: UdpOptions, hooks: TransportHooks | None = None) -> None:
        super().__init__(max_line_bytes=options.max_line_bytes, backoff=None, hooks=hooks)
        self.options = options
        self._queue: asyncio.Queue[bytes] = asyncio.Queue(maxsize=options.queue_size)
        self._endpoint: asyncio.DatagramTransport | None = None

    def describe(self) -> str:
        return f"udp {self.options.host}:{self.options.port}"

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound ``(host, port)`` (useful with port 0).

        Raises:
            DriverConfigError: The transport is not open.
        """
        if self._endpoint is None:
            raise DriverConfigError(f"{self.describe()}: not open, no local address yet")
        host, port = self._endpoint.get_extra_info("sockname")[:2]
        return str(host), int(port)

    async def _open_link(self) -> None:
        loop = asyncio.get_running_loop()
        self._endpoint, _ = await loop.create_datagram_endpoint(
            lambda: _DatagramQueue(self._queue, self.counters),
            local_addr=(self.options.host, self.options.port),
        )

    async def _read_chunk(self) -> bytes | None:
        data = await self._queue.get()
        # A datagram is a whole message: end its last line even if the sender did not.
        return data if data.endswith((b"\n", b"\r")) else data + b"\n"

    async def _close_link(self) -> None:
        endpoint, self._endpoint = self._endpoint, None
        if endpoint is not None:
            endpoint.close()
