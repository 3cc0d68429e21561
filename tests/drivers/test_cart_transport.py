"""CartTransport base: framing, reconnection with capped backoff, idle watchdog, lifecycle."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from drivers.cart.reasons import RejectReason
from drivers.cart.transport import Backoff, CartTransport, TransportHooks, options_from_dict
from drivers.errors import DriverConfigError, TransportError

pytestmark = pytest.mark.timeout(10)


class FakeTime:
    """Simulated clock; sleeping advances it instead of waiting."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    async def sleep(self, delay_s: float) -> None:
        self.sleeps.append(delay_s)
        self.now += delay_s
        await asyncio.sleep(0)


Link = list[bytes | str | None] | str


class Scripted(CartTransport):
    """A transport whose links follow a script.

    Each open takes the next link: ``"refuse"`` fails the open; a list is played item by item —
    bytes are a chunk, None a clean end of stream, ``"hang"`` a link that goes silent without
    closing — and when the list is exhausted the link drops (the peer closed).
    """

    name = "scripted"

    def __init__(self, links: list[Link], backoff: Backoff | None, time: FakeTime, **kw: float) -> None:
        super().__init__(backoff=backoff, hooks=TransportHooks(sleep=time.sleep, clock=time.clock), **kw)
        self.links = list(links)
        self.current: list[bytes | str | None] = []
        self.opens = 0
        self.closes = 0

    def describe(self) -> str:
        return "scripted"

    async def _open_link(self) -> None:
        self.opens += 1
        link = self.links.pop(0) if self.links else "refuse"
        if isinstance(link, str):
            raise ConnectionRefusedError("refused")
        self.current = list(link)

    async def _read_chunk(self) -> bytes | None:
        await asyncio.sleep(0)
        if not self.current:
            raise ConnectionResetError("peer closed")
        item = self.current.pop(0)
        if item == "hang":
            await asyncio.Event().wait()
        return item if not isinstance(item, str) else None

    async def _close_link(self) -> None:
        self.closes += 1


async def collect(t: CartTransport, n: int | None = None) -> list[bytes]:
    out: list[bytes] = []
    async for line in t:
        out.append(line)
        if n is not None and len(out) == n:
            break
    return out


async def test_reconnects_after_a_drop_and_discards_the_cut_line() -> None:
    time = FakeTime()
    t = Scripted([[b"a\nb", b"\nhalf-a-li"], [b"c\n", b"d\n", None]], Backoff(initial_s=0.5), time)
    async with t:
        assert await collect(t, 4) == [b"a", b"b", b"c", b"d"]
    assert (t.drops, t.reconnects) == (1, 1)
    assert time.sleeps == [0.5]
    assert t.counters == {RejectReason.TRUNCATED: 1}
    assert not t.is_open


async def test_backoff_grows_caps_and_restarts_when_data_flows() -> None:
    time = FakeTime()
    links: list[Link] = [[b"1\n"], "refuse", "refuse", "refuse", "refuse", [b"2\n"], "refuse", [b"3\n", None]]
    t = Scripted(links, Backoff(initial_s=1.0, factor=2.0, max_s=5.0), time)
    async with t:
        assert await collect(t) == [b"1", b"2", b"3"]
    # drop 1: 1, 2, 4, 5 (capped), 5 then success; data flowed, so drop 2 starts over at 1.
    assert time.sleeps == [1.0, 2.0, 4.0, 5.0, 5.0, 1.0, 2.0]
    assert (t.drops, t.reconnects) == (2, 2)


async def test_gives_up_after_max_attempts_without_data() -> None:
    time = FakeTime()
    # A link that connects but drops with no data still counts towards max_attempts.
    t = Scripted([[b"x\n"], [], "refuse", "refuse"], Backoff(initial_s=0.1, max_attempts=3), time)
    async with t:
        with pytest.raises(TransportError, match="gave up after 3 reconnection attempts") as info:
            await collect(t)
    assert isinstance(info.value.__cause__, ConnectionRefusedError)
    assert time.sleeps == pytest.approx([0.1, 0.2, 0.4])
    assert t.reconnects == 1


async def test_without_backoff_a_drop_ends_with_transport_error() -> None:
    t = Scripted([[b"x\n"]], None, FakeTime())
    async with t:
        with pytest.raises(TransportError, match="link dropped: peer closed"):
            await collect(t)
    assert t.drops == 1 and t.reconnects == 0


async def test_first_open_fails_fast() -> None:
    time = FakeTime()
    t = Scripted(["refuse"], Backoff(), time)
    with pytest.raises(TransportError, match="scripted: cannot open: refused"):
        await t.open()
    assert time.sleeps == [] and t.opens == 1 and not t.is_open


async def test_clean_end_flushes_the_last_line() -> None:
    t = Scripted([[b"a\nlast-without-newline", None]], Backoff(), FakeTime())
    async with t:
        assert await collect(t) == [b"a", b"last-without-newline"]
    assert t.drops == 0 and not t.counters


async def test_idle_watchdog_reconnects_a_silent_link() -> None:
    time = FakeTime()
    # The first link goes silent without closing (a half-open TCP connection).
    t = Scripted([[b"a\n", "hang"], [b"b\n"]], Backoff(initial_s=0.25), time, idle_timeout_s=0.05)
    async with t:
        assert await asyncio.wait_for(collect(t, 2), 5) == [b"a", b"b"]
    assert t.drops == 1 and t.reconnects == 1 and time.sleeps == [0.25]


async def test_iteration_after_close_stops() -> None:
    t = Scripted([[b"a\n"]], Backoff(), FakeTime())
    async with t:
        pass
    assert await collect(t) == []
    assert t.closes >= 1


def test_backoff_delays_and_overflow() -> None:
    b = Backoff(initial_s=0.5, factor=3.0, max_s=10.0)
    assert [b.delay_s(k) for k in range(5)] == [0.5, 1.5, 4.5, 10.0, 10.0]
    assert b.delay_s(100_000) == 10.0  # no OverflowError after a long outage
    assert Backoff(initial_s=2.0, factor=1.0, max_s=2.0).delay_s(10**6) == 2.0


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"initial": 1.0}, r"unknown key backoff.initial = 1.0 \(did you mean 'initial_s'\?\); "
         r"allowed keys in \[backoff\]: factor, initial_s, max_attempts, max_s"),
        ({"initial_s": 0}, r"backoff.initial_s = 0: expected a finite number in \(0, inf\]"),
        ({"factor": 0.5}, r"backoff.factor = 0.5"),
        ({"initial_s": 5.0, "max_s": 1.0}, r"backoff.max_s = 1.0"),
        ({"max_attempts": 0}, r"backoff.max_attempts = 0: expected an integer in \[1, inf\]"),
        ({"max_attempts": True}, r"backoff.max_attempts = True"),
    ],
)
def test_backoff_from_dict_errors(data: dict[str, object], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        Backoff.from_dict(data)


@dataclass(frozen=True)
class DemoOptions:
    host: str
    port: int
    backoff: Backoff = field(default_factory=Backoff)


def test_options_from_dict() -> None:
    opts = options_from_dict(DemoOptions, {"host": "h", "port": 1, "backoff": {"max_s": 3.0}}, "cart.options")
    assert opts == DemoOptions("h", 1, Backoff(max_s=3.0))
    with pytest.raises(DriverConfigError, match=r"cart.options: missing required key\(s\) \['port'\]"):
        options_from_dict(DemoOptions, {"host": "h"}, "cart.options")
    with pytest.raises(DriverConfigError, match=r"unknown key cart\.options\.baud = 9600"):
        options_from_dict(DemoOptions, {"host": "h", "port": 1, "baud": 9600}, "cart.options")
    with pytest.raises(DriverConfigError, match=r"unknown key cart\.options\.backoff\.cap = 3"):
        options_from_dict(DemoOptions, {"host": "h", "port": 1, "backoff": {"cap": 3}}, "cart.options")
    with pytest.raises(DriverConfigError, match=r"cart.options = \[1\]: expected a table"):
        options_from_dict(DemoOptions, [1], "cart.options")  # type: ignore[arg-type]


async def test_the_waiting_hook_wraps_reads_only_never_the_recovery() -> None:
    """A simulated clock may run on while the link is read, not while it is reopened."""
    time = FakeTime()
    log: list[str] = []

    @contextlib.contextmanager
    def waiting() -> Iterator[None]:
        log.append("wait")
        try:
            yield
        finally:
            log.append("done")

    t = Scripted([[b"a\n"], [b"b\n", None]], Backoff(initial_s=0.5), time)
    real_sleep, real_open = time.sleep, t._open_link

    async def sleep(delay_s: float) -> None:
        log.append("backoff")
        await real_sleep(delay_s)

    async def open_link() -> None:
        log.append("open")
        await real_open()

    t._hooks = TransportHooks(sleep=sleep, clock=time.clock, waiting=waiting)
    t._open_link = open_link  # type: ignore[method-assign]
    async with t:
        assert await collect(t) == [b"a", b"b"]
    # open, read a, read (drop), backoff, reopen, read b, read (end)
    assert log == ["open", "wait", "done", "wait", "done", "backoff", "open",
                   "wait", "done", "wait", "done"]
