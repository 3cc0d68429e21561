"""Replay transport: reads a recorded file, paces by breath time on an injected clock."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest

from drivers.cart.replay import ReplayOptions, ReplayTransport
from drivers.cart.transport import TransportHooks
from drivers.errors import DriverConfigError, TransportError

pytestmark = pytest.mark.timeout(10)


class FakeTime:
    def __init__(self, start: float = 100.0) -> None:
        self.now = start
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    async def sleep(self, delay_s: float) -> None:
        self.sleeps.append(delay_s)
        self.now += delay_s
        await asyncio.sleep(0)


async def test_reads_every_line_then_ends(tmp_path: Path) -> None:
    path = tmp_path / "rec.txt"
    path.write_bytes(b"a\r\n\r\nb\nc")  # blank line skipped, last line without newline kept
    t = ReplayTransport(ReplayOptions(str(path), speed="max"))
    async with t:
        assert [line async for line in t] == [b"a", b"b", b"c"]
        assert [line async for line in t] == []  # stays ended


async def test_pacing_follows_breath_time_at_speed(tmp_path: Path) -> None:
    path = tmp_path / "rec.txt"
    path.write_bytes(b"")
    time = FakeTime()
    t = ReplayTransport(
        ReplayOptions(str(path), speed=2.0), TransportHooks(sleep=time.sleep, clock=time.clock)
    )
    async with t:
        await t.pace(10.0)  # first breath anchors the schedule: no wait
        await t.pace(12.0)  # due 1 s later at 2x
        time.now += 0.25  # processing took 0.25 s: waits only the rest (no drift)
        await t.pace(14.0)
        await t.pace(14.5)
        await t.pace(30.0)  # a real 15.5-s gap is replayed too, at 2x
    assert time.sleeps == pytest.approx([1.0, 0.75, 0.25, 7.75])
    assert time.now == pytest.approx(100.0 + 10.0)


async def test_behind_schedule_does_not_sleep(tmp_path: Path) -> None:
    path = tmp_path / "rec.txt"
    path.write_bytes(b"")
    time = FakeTime()
    t = ReplayTransport(
        ReplayOptions(str(path), speed=1.0), TransportHooks(sleep=time.sleep, clock=time.clock)
    )
    async with t:
        await t.pace(0.0)
        time.now += 5.0
        await t.pace(3.0)
    assert time.sleeps == []


async def test_max_speed_never_sleeps(tmp_path: Path) -> None:
    path = tmp_path / "rec.txt"
    path.write_bytes(b"")
    time = FakeTime()
    t = ReplayTransport(
        ReplayOptions(str(path), speed="max"), TransportHooks(sleep=time.sleep, clock=time.clock)
    )
    async with t:
        for s in range(100):
            await t.pace(float(s) * 60.0)
    assert time.sleeps == []


async def test_missing_file_fails_fast(tmp_path: Path) -> None:
    with pytest.raises(TransportError, match=r"nope\.txt"):
        await ReplayTransport(ReplayOptions(str(tmp_path / "nope.txt"))).open()


def test_options() -> None:
    assert ReplayOptions("f", speed="max").speed == math.inf
    assert ReplayOptions("f", speed="max").is_max_speed
    assert ReplayOptions("f", speed=3).speed == 3.0
    assert ReplayOptions(Path("dir/f"), speed=0.5).path == str(Path("dir/f"))  # type: ignore[arg-type]
    for bad in (0, -1.0, "fast", math.nan, True):
        with pytest.raises(DriverConfigError, match=r"speed = .*: expected a number > 0 or 'max'"):
            ReplayOptions("f", speed=bad)  # type: ignore[arg-type]
    with pytest.raises(DriverConfigError, match="path = ''"):
        ReplayOptions("")
