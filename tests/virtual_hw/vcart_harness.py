"""Test harness: a virtual cart on a VirtualClock read back by the drivers' BreathStream.

The reader is a clock participant that is idle only while its transport waits for bytes
(``TransportHooks.waiting``) and sleeps its reconnection backoff on simulated time, so the
session runs at ``max`` speed with the same order of events as at speed 1. Two things cross a
thread, which the clock cannot see (virtual_hw/clock.py): pyserial reads and opens the pty in an
executor thread. Reopening happens while the reader is busy, so time waits for it; and at each
``disconnect`` the harness holds time until the reader has seen the drop. Without both, a
descheduled thread lets the cart run on, even to the session's end, before the reader notices.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field

from drivers.cart import Backoff, BreathStream, TransportHooks, UdpOptions, UdpTransport
from hilbo_core.presets import hip_6d
from hilbo_core.types import BreathRecord
from virtual_hw.cart import CartFault, CartLink, EmittedBreath, LinkKind, VirtualCart
from virtual_hw.clock import VirtualClock
from virtual_hw.faults import FaultSpec
from virtual_hw.wearer import SimulatedWearer, WearerConfig

__all__ = ["QUIET", "SPACE", "Session", "run_session", "same_breath"]

SPACE = hip_6d()
QUIET = WearerConfig(noise_frac=(0.0, 0.0))
"""A wearer without breath-to-breath noise: every breath's watts is the model's m(t)."""

_WALL_TIMEOUT_S = 10.0
_DROP_POLL_WALL_S = 0.001


@dataclass
class Session:
    """What one read-back session produced."""

    cart: VirtualCart
    stream: BreathStream
    records: list[BreathRecord] = field(default_factory=list)
    received_s: list[float] = field(default_factory=list)

    def readable(self) -> list[EmittedBreath]:
        """The breaths the reader must have accepted, in the order the cart wrote them."""
        return sorted((e for e in self.cart.history if e.readable), key=lambda e: e.t_sent_s)

    def undelivered_seqs(self) -> int:
        """Numbered breaths that reached no client."""
        return sum(1 for e in self.cart.history if e.seq is not None and e.clients == 0)


def same_breath(a: BreathRecord, b: BreathRecord, *, t_tol_s: float = 0.0) -> bool:
    """Equal records, the time within ``t_tol_s`` (CSV clock times are written to the µs)."""
    if abs(a.t_s - b.t_s) > t_tol_s:
        return False
    return (a.vo2_ml_min, a.vco2_ml_min, a.ve_l_min, a.rer, a.hr_bpm) == (
        b.vo2_ml_min, b.vco2_ml_min, b.ve_l_min, b.rer, b.hr_bpm
    )


async def run_session(
    kind: LinkKind = LinkKind.TCP,
    *,
    faults: Iterable[str | FaultSpec] = (),
    end_s: float = 240.0,
    fmt: str = "hilbo-line",
    wearer: SimulatedWearer | None = None,
    seed: int = 5,
    during: Callable[[VirtualCart, VirtualClock], Awaitable[None]] | None = None,
) -> Session:
    """Serve ``end_s`` simulated seconds and read every breath back; return what was read.

    Args:
        kind: The link.
        faults: Cart fault specs.
        end_s: Session length in simulated seconds.
        fmt: Cart format.
        wearer: The wearer (default: a seeded noisy one).
        seed: Wearer seed when ``wearer`` is None.
        during: Runs beside the session as its own clock participant (e.g. applies a profile).
    """
    clock = VirtualClock()
    wearer = wearer if wearer is not None else SimulatedWearer(SPACE, seed)
    reader = clock.participant("reader")
    hooks = TransportHooks(sleep=reader.sleep, clock=clock.now, waiting=reader.idle)
    udp: UdpTransport | None = None
    if kind is LinkKind.UDP:
        udp = UdpTransport(UdpOptions(port=0), hooks)
        await udp.open()
        link = CartLink(kind, port=udp.local_address[1])
    else:
        link = CartLink(kind)
    cart = VirtualCart(wearer, clock, link=link, fmt=fmt, faults=faults, end_s=end_s,
                       wait_for_client=True)
    async with cart:
        if udp is not None:
            stream = BreathStream(udp, cart.client_config().make_parser())
        else:
            config = cart.client_config(backoff=Backoff(initial_s=0.5, max_s=2.0))
            stream = BreathStream.from_config(config, hooks)
        session = Session(cart, stream)
        progress = asyncio.Event()

        async def read() -> None:
            with reader:
                async with stream:
                    while True:
                        record = await anext(stream)
                        session.records.append(record)
                        session.received_s.append(clock.now())
                        progress.set()

        async def hold_until_each_drop_is_seen() -> None:
            starts = sorted(s.start_s for s in cart.faults.specs
                            if s.kind == CartFault.DISCONNECT and s.start_s < end_s)
            with clock.participant("drop-watch") as me:
                for seen, t0 in enumerate(starts, start=1):
                    await me.sleep_until(t0)  # woken busy at the cart's link-down tick
                    while stream.transport.drops < seen and not tasks[0].done():
                        await asyncio.sleep(_DROP_POLL_WALL_S)

        tasks = [asyncio.create_task(read(), name="reader")]
        if udp is None:
            tasks.append(asyncio.create_task(hold_until_each_drop_is_seen(), name="drop-watch"))
        if during is not None:
            tasks.append(asyncio.create_task(during(cart, clock), name="during"))
        try:
            async with asyncio.timeout(_WALL_TIMEOUT_S):
                await cart.wait()
                readable = session.readable()
                last = readable[-1].record if readable else None
                while last is not None and not (
                    session.records and same_breath(session.records[-1], last, t_tol_s=1e-6)
                ):
                    if tasks[0].done():
                        tasks[0].result()  # the reader failed: show why
                    await progress.wait()
                    progress.clear()
        finally:
            for task in tasks:
                task.cancel()
            results = await asyncio.gather(*tasks, return_exceptions=True)
            await stream.transport.close()
        for result in results:
            if isinstance(result, BaseException) and not isinstance(result, asyncio.CancelledError):
                raise result
    assert math.isclose(clock.now(), end_s)
    return session
