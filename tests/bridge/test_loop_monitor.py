"""The event-loop stall monitor (bridge/loop_monitor.py)."""

from __future__ import annotations

import asyncio
import time

import pytest

from bridge.errors import BridgeConfigError
from bridge.loop_monitor import LoopMonitor


class _JumpClock:
    """A clock that advances one period per reading, plus one jump at the given reading."""

    def __init__(self, period_s: float, jump_at: int, jump_s: float) -> None:
        self.t, self.n = 0.0, 0
        self.period_s, self.jump_at, self.jump_s = period_s, jump_at, jump_s

    def __call__(self) -> float:
        self.n += 1
        self.t += self.period_s + (self.jump_s if self.n == self.jump_at else 0.0)
        return self.t


async def _wakeups(mon: LoopMonitor, n: int) -> None:
    while mon.stats.wakeups < n:
        await asyncio.sleep(0)


def test_a_clock_jump_is_measured_as_exactly_that_stall() -> None:
    stalls: list[float] = []
    clock = _JumpClock(0.005, jump_at=10, jump_s=0.2)

    async def main() -> LoopMonitor:
        async with LoopMonitor(0.05, stalls.append, period_s=0.005, clock=clock) as mon:
            await _wakeups(mon, 20)
        return mon

    mon = asyncio.run(main())
    assert stalls == [pytest.approx(0.2)]
    assert mon.stats.worst_stall_ms == pytest.approx(200.0)
    assert mon.stats.stalls_over_threshold == 1
    assert mon.stats.to_json()["half_heartbeat_ms"] == 50.0


def test_a_blocking_call_on_the_loop_is_measured_and_reported() -> None:
    # 300 ms blocked against a 30 ms threshold: load can only lengthen what is measured, and
    # the monitor underestimates by at most one period (5 ms).
    stalls: list[float] = []

    async def main() -> LoopMonitor:
        async with LoopMonitor(0.03, stalls.append, period_s=0.005) as mon:
            await _wakeups(mon, 3)
            time.sleep(0.3)  # the injected stall (blocks the loop, on purpose)
            await _wakeups(mon, mon.stats.wakeups + 3)
        return mon

    mon = asyncio.run(main())
    assert max(stalls) >= 0.3 - 0.005
    assert mon.stats.worst_stall_ms == pytest.approx(1e3 * max(stalls))
    assert mon.stats.stalls_over_threshold == len(stalls) >= 1


def test_stalls_before_a_device_is_connected_do_not_count() -> None:
    stalls: list[float] = []
    clock = _JumpClock(0.005, jump_at=5, jump_s=0.2)
    connected = False

    async def main() -> LoopMonitor:
        nonlocal connected
        async with LoopMonitor(0.05, stalls.append, connected=lambda: connected,
                               period_s=0.005, clock=clock) as mon:
            while clock.n < 10:
                await asyncio.sleep(0)
            connected = True
            await _wakeups(mon, 5)
        return mon

    mon = asyncio.run(main())
    assert stalls == [] and mon.stats.stalls_over_threshold == 0
    assert mon.stats.worst_stall_ms < 1e-6


def test_a_failing_report_is_raised_when_the_monitor_ends() -> None:
    def report(stall_s: float) -> None:
        raise RuntimeError(f"log closed ({stall_s:.3f} s)")

    async def main() -> None:
        async with LoopMonitor(0.05, report, clock=_JumpClock(0.005, jump_at=3, jump_s=0.1)) as mon:
            while mon._task is not None and not mon._task.done():
                await asyncio.sleep(0)

    with pytest.raises(RuntimeError, match="log closed"):
        asyncio.run(main())


@pytest.mark.parametrize(("threshold_s", "period_s"), [(0.05, 0.0), (0.05, 0.05), (0.0, 0.005)])
def test_bad_periods_are_refused(threshold_s: float, period_s: float) -> None:
    with pytest.raises(BridgeConfigError, match="period_s"):
        LoopMonitor(threshold_s, print, period_s=period_s)
