"""SkippingClock (virtual_hw/clock.py): a scaled clock that jumps ahead and wakes its sleepers."""

from __future__ import annotations

import asyncio

import pytest

from virtual_hw.clock import SkippingClock

pytestmark = pytest.mark.timeout(60)


async def test_a_skip_wakes_a_sleeper_due_at_the_new_time() -> None:
    clock = SkippingClock(1.0)  # real time: the sleeper below would sleep an hour
    woke: list[float] = []

    async def sleeper() -> None:
        await clock.sleep_until(3600.0)
        woke.append(clock.now())

    task = asyncio.create_task(sleeper())
    await asyncio.sleep(0)
    assert clock.skip_to(1800.0) > 0
    await asyncio.sleep(0)
    assert not woke  # half way: it sleeps on
    assert clock.skip_to(3600.0) == pytest.approx(1800.0, abs=1.0)
    async with asyncio.timeout(30):  # generous: the wake-up is a scheduling step, not a wait
        await task
    assert woke and woke[0] >= 3600.0
    assert clock.skipped_s == pytest.approx(3600.0, abs=1.0)


def test_a_skip_never_goes_back() -> None:
    clock = SkippingClock(10.0)
    clock.skip_to(500.0)
    before = clock.now()
    assert clock.skip_to(100.0) == 0.0
    assert clock.now() >= before >= 500.0
