"""Serial transport over a real pseudo-terminal pair: reading, unplug and replug, options."""

from __future__ import annotations

import asyncio
import os
import sys
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.cart.serial_port import SerialOptions, SerialTransport
from drivers.cart.transport import Backoff, TransportHooks
from drivers.errors import DriverConfigError, TransportError

pytestmark = [
    pytest.mark.timeout(20),
    pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX"),
]


class Pty:
    """A pseudo-terminal pair: the test writes to the master like a cart on the wire."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line discipline: bytes pass through unchanged
        self.name = os.ttyname(self.slave)

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def unplug(self) -> None:
        os.close(self.master)  # readers of the slave now get EIO, as from a pulled USB adapter

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass  # already closed by unplug()


@pytest.fixture
def ptys() -> Iterator[list[Pty]]:
    made: list[Pty] = []
    yield made
    for p in made:
        p.close()


class FakeSleep:
    def __init__(self) -> None:
        self.sleeps: list[float] = []

    async def __call__(self, delay_s: float) -> None:
        self.sleeps.append(delay_s)
        await asyncio.sleep(0)


async def next_line(t: SerialTransport) -> bytes:
    return await asyncio.wait_for(t.__anext__(), 5)


async def test_reads_lines_split_across_writes(ptys: list[Pty]) -> None:
    ptys.append(Pty())
    pty = ptys[0]
    t = SerialTransport(SerialOptions(port=pty.name, baudrate=115200, read_timeout_s=0.05))
    async with t:
        pty.write(b"$HBR,1,1.0,")
        pty.write(b"500.0,400.0,,,*ABCD\r\nsecond\r")
        pty.write(b"\n")
        assert await next_line(t) == b"$HBR,1,1.0,500.0,400.0,,,*ABCD"
        assert await next_line(t) == b"second"
    assert not t.is_open


async def test_unplug_and_replug_reconnects(ptys: list[Pty], tmp_path: Path) -> None:
    # The config names a stable symlink (like /dev/serial/by-id/...); replugging the adapter
    # gives a new tty behind the same name.
    first = Pty()
    ptys.append(first)
    link = tmp_path / "cart-serial"
    link.symlink_to(first.name)
    sleep = FakeSleep()
    opts = SerialOptions(port=str(link), read_timeout_s=0.05, backoff=Backoff(initial_s=0.2, max_attempts=5))
    t = SerialTransport(opts, TransportHooks(sleep=sleep))
    async with t:
        first.write(b"before\r\nhalf-of-a-li")
        assert await next_line(t) == b"before"
        second = Pty()
        ptys.append(second)
        link.unlink()
        link.symlink_to(second.name)
        # Wall: the bytes cross a real pty and pyserial's executor thread; no event to wait on.
        await asyncio.sleep(0.1)  # let the partial line reach the reader before the unplug
        first.unplug()
        reading = asyncio.ensure_future(next_line(t))
        async with asyncio.timeout(5.0):  # bounded: the reconnect happens in an executor thread
            while t.reconnects == 0 and not reading.done():
                await asyncio.sleep(0.01)  # real pty: poll for the reconnect, bounded
        second.write(b"after\r\n")
        assert await reading == b"after"
    assert t.drops == 1 and t.reconnects == 1
    assert sleep.sleeps == [0.2]
    assert t.counters["truncated"] == 1


async def test_gives_up_when_the_port_stays_gone(ptys: list[Pty], tmp_path: Path) -> None:
    first = Pty()
    ptys.append(first)
    link = tmp_path / "cart-serial"
    link.symlink_to(first.name)
    sleep = FakeSleep()
    opts = SerialOptions(port=str(link), read_timeout_s=0.05, backoff=Backoff(initial_s=0.1, max_attempts=2))
    t = SerialTransport(opts, TransportHooks(sleep=sleep))
    async with t:
        link.unlink()
        first.unplug()
        with pytest.raises(TransportError, match="gave up after 2 reconnection attempts"):
            await next_line(t)
    assert sleep.sleeps == pytest.approx([0.1, 0.2])


async def test_missing_port_fails_fast(tmp_path: Path) -> None:
    t = SerialTransport(SerialOptions(port=str(tmp_path / "no-such-tty")))
    with pytest.raises(TransportError, match="no-such-tty"):
        await t.open()


async def test_close_while_a_read_is_pending(ptys: list[Pty]) -> None:
    ptys.append(Pty())
    t = SerialTransport(SerialOptions(port=ptys[0].name, read_timeout_s=0.05))
    async with t:
        reader = asyncio.ensure_future(t.__anext__())
        async with asyncio.timeout(5.0):
            while t._pending is None:  # the read is in pyserial's executor thread: pending
                await asyncio.sleep(0)
        reader.cancel()
        with pytest.raises(asyncio.CancelledError):
            await reader
    assert t._pending is None and t._port is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"port": ""}, "port = ''"),
        ({"port": "/dev/x", "baudrate": 0}, "baudrate = 0"),
        ({"port": "/dev/x", "parity": "X"}, "parity = 'X': expected one of 'N', 'E'"),
        ({"port": "/dev/x", "stopbits": 3}, "stopbits = 3"),
        ({"port": "/dev/x", "bytesize": 9}, "bytesize = 9"),
        ({"port": "/dev/x", "read_timeout_s": 0}, "read_timeout_s = 0"),
    ],
)
def test_bad_options(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        SerialOptions(**kwargs)  # type: ignore[arg-type]
