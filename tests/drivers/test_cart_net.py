"""TCP and UDP transports over loopback: reading, the server closing, reconnect, overflow."""

from __future__ import annotations

import asyncio
import socket

import pytest

from drivers.cart.net import TcpOptions, TcpTransport, UdpOptions, UdpTransport
from drivers.cart.reasons import RejectReason
from drivers.cart.transport import Backoff, TransportHooks
from drivers.errors import DriverConfigError, TransportError

pytestmark = pytest.mark.timeout(20)


class FakeSleep:
    def __init__(self) -> None:
        self.sleeps: list[float] = []

    async def __call__(self, delay_s: float) -> None:
        self.sleeps.append(delay_s)
        await asyncio.sleep(0)


class CartServer:
    """A TCP server on 127.0.0.1 playing one batch of bytes per connection, then closing it."""

    def __init__(self, batches: list[bytes]) -> None:
        self.batches = list(batches)
        self.connections = 0
        self.server: asyncio.Server | None = None

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        if self.batches:
            writer.write(self.batches.pop(0))
            await writer.drain()
        writer.close()
        await writer.wait_closed()

    async def __aenter__(self) -> CartServer:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.server is not None
        self.server.close()
        await self.server.wait_closed()

    @property
    def port(self) -> int:
        assert self.server is not None
        return int(self.server.sockets[0].getsockname()[1])


async def take(t: TcpTransport | UdpTransport, n: int) -> list[bytes]:
    async def run() -> list[bytes]:
        out: list[bytes] = []
        async for line in t:
            out.append(line)
            if len(out) == n:
                break
        return out

    return await asyncio.wait_for(run(), 5)


async def test_tcp_reconnects_each_time_the_cart_closes() -> None:
    batches = [b"l1\r\nl2\r\nhalf", b"l3\r\n", b"l4\r\nl5\r\n"]
    sleep = FakeSleep()
    async with CartServer(batches) as server:
        opts = TcpOptions("127.0.0.1", server.port, backoff=Backoff(initial_s=0.3))
        t = TcpTransport(opts, TransportHooks(sleep=sleep))
        async with t:
            assert await take(t, 5) == [b"l1", b"l2", b"l3", b"l4", b"l5"]
    assert server.connections == 3
    assert (t.drops, t.reconnects) == (2, 2)
    assert sleep.sleeps == [0.3, 0.3]  # data flowed on every link: backoff restarts each time
    assert t.counters == {RejectReason.TRUNCATED: 1}


async def test_tcp_gives_up_when_the_cart_is_gone() -> None:
    sleep = FakeSleep()
    async with CartServer([b"only\n"]) as server:
        port = server.port
        opts = TcpOptions(
            "127.0.0.1", port, connect_timeout_s=1.0, backoff=Backoff(initial_s=0.1, max_attempts=3)
        )
        t = TcpTransport(opts, TransportHooks(sleep=sleep))
        await t.open()
    # The server is closed now; every reconnection is refused.
    try:
        assert await take(t, 1) == [b"only"]
        with pytest.raises(TransportError, match="gave up after 3") as info:
            await take(t, 1)
        assert isinstance(info.value.__cause__, OSError)
    finally:
        await t.close()
    assert sleep.sleeps == pytest.approx([0.1, 0.2, 0.4])


async def test_tcp_first_connect_refused_fails_fast() -> None:
    with socket.socket() as s:  # a port that was free a moment ago and has no listener
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t = TcpTransport(TcpOptions("127.0.0.1", port))
    with pytest.raises(TransportError, match=f"tcp 127.0.0.1:{port}: cannot open"):
        await t.open()


async def test_udp_datagrams_are_whole_lines() -> None:
    t = UdpTransport(UdpOptions(port=0))
    async with t:
        host, port = t.local_address
        assert host == "127.0.0.1" and port > 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"one\r\n", (host, port))
            tx.sendto(b"two-without-newline", (host, port))
            tx.sendto(b"three\nfour\n", (host, port))
            tx.sendto(b"", (host, port))  # ignored
            tx.sendto(b"five", (host, port))
            assert await take(t, 5) == [b"one", b"two-without-newline", b"three", b"four", b"five"]


async def test_udp_overflow_is_counted_not_buffered() -> None:
    t = UdpTransport(UdpOptions(port=0, queue_size=2))
    async with t:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for i in range(5):
                tx.sendto(f"d{i}\n".encode(), t.local_address)
            async with asyncio.timeout(5.0):  # bounded: datagrams cross a real socket
                while t.counters[RejectReason.OVERFLOW] < 3:
                    await asyncio.sleep(0.01)  # real UDP socket: poll the counter, bounded
            assert await take(t, 2) == [b"d0", b"d1"]
    assert t.counters == {RejectReason.OVERFLOW: 3}


async def test_udp_local_address_needs_an_open_transport() -> None:
    with pytest.raises(DriverConfigError, match="not open"):
        _ = UdpTransport(UdpOptions(port=0)).local_address


async def test_udp_bind_failure_fails_fast() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        t = UdpTransport(UdpOptions(port=busy.getsockname()[1]))
        with pytest.raises(TransportError, match="cannot open"):
            await t.open()


@pytest.mark.parametrize(
    ("cls", "kwargs", "match"),
    [
        (TcpOptions, {"host": "h", "port": 0}, r"port = 0: expected an integer in \[1, 65535\]"),
        (TcpOptions, {"host": "", "port": 1}, "host = ''"),
        (TcpOptions, {"host": "h", "port": "5000"}, "port = '5000'"),
        (TcpOptions, {"host": "h", "port": 1, "connect_timeout_s": -1}, "connect_timeout_s = -1"),
        (TcpOptions, {"host": "h", "port": 1, "backoff": {"max_s": 1}}, "backoff = "),
        (UdpOptions, {"port": 70000}, "port = 70000"),
        (UdpOptions, {"port": 1, "queue_size": 0}, "queue_size = 0"),
    ],
)
def test_bad_options(cls: type, kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        cls(**kwargs)
