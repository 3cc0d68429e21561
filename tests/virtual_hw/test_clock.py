"""Simulated clocks: discrete-event ordering and advancing, participants, holds, scaled wall time."""

from __future__ import annotations

import asyncio
import logging
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from virtual_hw.clock import (
    ParticipantState,
    ScaledClock,
    SimClock,
    VirtualClock,
    make_clock,
    parse_speed,
)
from virtual_hw.errors import ClockError, VirtualConfigError

pytestmark = pytest.mark.timeout(30)


# ------------------------------------------------------------------------ manual stepping
async def test_run_until_wakes_sleepers_in_time_order_and_ties_in_call_order() -> None:
    clock = VirtualClock()
    woke: list[tuple[str, float]] = []

    async def sleeper(name: str, t: float) -> None:
        await clock.sleep_until(t)
        woke.append((name, clock.now()))

    tasks = [asyncio.create_task(sleeper(n, t)) for n, t in (("c", 5.0), ("a", 2.0), ("b", 2.0))]
    await asyncio.sleep(0)
    assert clock.next_wakeup() == 2.0
    await clock.run_until(10.0)
    await asyncio.gather(*tasks)
    assert woke == [("a", 2.0), ("b", 2.0), ("c", 5.0)]
    assert clock.now() == 10.0


async def test_run_until_honours_wakeups_scheduled_on_the_way() -> None:
    clock = VirtualClock()
    woke: list[float] = []

    async def chain() -> None:
        for t in (1.0, 1.5, 2.25):  # each scheduled only after the previous wake-up
            await clock.sleep_until(t)
            woke.append(clock.now())

    async def late() -> None:
        await clock.sleep_until(2.0)
        woke.append(clock.now())

    tasks = [asyncio.create_task(chain()), asyncio.create_task(late())]
    await asyncio.sleep(0)
    await clock.advance(3.0)
    await asyncio.gather(*tasks)
    assert woke == [1.0, 1.5, 2.0, 2.25]


async def test_advance_stops_short_of_later_wakeups_and_never_goes_back() -> None:
    clock = VirtualClock(start_s=10.0)
    task = asyncio.create_task(clock.sleep(5.0))
    await asyncio.sleep(0)
    await clock.advance(4.0)
    assert clock.now() == 14.0 and not task.done()
    await clock.run_until(12.0)  # the past: nothing happens
    assert clock.now() == 14.0
    await clock.advance(1.0)
    await task
    assert clock.now() == 15.0


async def test_sleep_in_the_past_returns_at_once() -> None:
    clock = VirtualClock(start_s=3.0)
    await asyncio.wait_for(clock.sleep_until(1.0), timeout=1.0)
    assert clock.now() == 3.0


async def test_cancelled_sleeper_is_forgotten() -> None:
    clock = VirtualClock()
    task = asyncio.create_task(clock.sleep_until(1.0))
    await asyncio.sleep(0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert clock.next_wakeup() is None


# ------------------------------------------------------------------------ participants
async def _ticker(clock: VirtualClock, name: str, period: float, end: float, log: list) -> None:
    with clock.participant(name) as me:
        t = period
        while t <= end:
            await me.sleep_until(t)
            log.append((clock.now(), name))
            t += period


async def test_participants_advance_time_alone_in_event_order() -> None:
    clock = VirtualClock()
    log: list[tuple[float, str]] = []
    await asyncio.wait_for(asyncio.gather(
        _ticker(clock, "a", 1.5, 6.0, log), _ticker(clock, "b", 2.0, 6.0, log),
    ), timeout=5.0)
    # At the 6.0 tie, b (which asked at 4.0) wakes before a (which asked at 4.5): FIFO.
    assert log == [(1.5, "a"), (2.0, "b"), (3.0, "a"), (4.0, "b"), (4.5, "a"), (6.0, "b"), (6.0, "a")]
    assert clock.now() == 6.0


async def test_a_busy_participant_holds_time_and_a_woken_one_is_busy_at_once() -> None:
    clock = VirtualClock()
    go = asyncio.Event()
    seen: list[float] = []

    async def worker() -> None:
        with clock.participant("worker") as me:
            await go.wait()  # busy: awaiting something without idle()
            seen.append(clock.now())
            await me.sleep_until(1.0)
            assert me.state is ParticipantState.BUSY
            seen.append(clock.now())

    async def other() -> None:
        with clock.participant("other") as me:
            await me.sleep_until(5.0)
            seen.append(clock.now())

    tasks = [asyncio.create_task(worker()), asyncio.create_task(other())]
    for _ in range(50):
        await asyncio.sleep(0)
    assert clock.now() == 0.0 and seen == []
    go.set()
    await asyncio.wait_for(asyncio.gather(*tasks), timeout=5.0)
    assert seen == [0.0, 1.0, 5.0]


async def test_an_idle_participant_lets_time_move_and_is_served_before_the_next_step() -> None:
    clock = VirtualClock()
    queue: asyncio.Queue[float] = asyncio.Queue()
    got: list[tuple[float, float]] = []

    async def consumer() -> None:
        with clock.participant("consumer") as me:
            for _ in range(3):
                with me.idle():
                    item = await queue.get()
                got.append((item, clock.now()))

    async def producer() -> None:
        with clock.participant("producer") as me:
            for t in (1.0, 2.0, 3.0):
                await me.sleep_until(t)
                queue.put_nowait(t)

    await asyncio.wait_for(asyncio.gather(consumer(), producer()), timeout=5.0)
    assert got == [(1.0, 1.0), (2.0, 2.0), (3.0, 3.0)]


async def test_loopback_tcp_data_reaches_an_idle_reader_before_time_moves_on() -> None:
    # The settle turns: a write at t must be read at t, not after the writer's next wake-up.
    clock = VirtualClock()
    server_writers: list[asyncio.StreamWriter] = []
    server = await asyncio.start_server(lambda r, w: server_writers.append(w), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    for _ in range(20):
        await asyncio.sleep(0)
    received: list[tuple[bytes, float]] = []

    async def read_side() -> None:
        with clock.participant("reader") as me:
            for _ in range(20):
                with me.idle():
                    line = await reader.readline()
                received.append((line, clock.now()))

    async def write_side() -> None:
        with clock.participant("writer") as me:
            for k in range(1, 21):
                await me.sleep_until(0.25 * k)
                server_writers[0].write(f"{0.25 * k}\n".encode())

    try:
        await asyncio.wait_for(asyncio.gather(read_side(), write_side()), timeout=5.0)
    finally:
        writer.close()
        server.close()
    assert [(float(line), t) for line, t in received] == [(0.25 * k, 0.25 * k) for k in range(1, 21)]


async def test_hold_stops_time_until_released() -> None:
    clock = VirtualClock()
    hold = clock.hold("estimator")

    async def sleeper() -> None:
        with clock.participant("sleeper") as me:
            await me.sleep_until(2.0)

    task = asyncio.create_task(sleeper())
    for _ in range(50):
        await asyncio.sleep(0)
    assert clock.now() == 0.0 and clock.holds == (hold,)
    hold.release()
    hold.release()  # idempotent
    await asyncio.wait_for(task, timeout=5.0)
    assert clock.now() == 2.0 and clock.holds == ()


async def test_without_participants_time_moves_only_when_told() -> None:
    clock = VirtualClock()
    task = asyncio.create_task(clock.sleep_until(1.0))
    for _ in range(50):
        await asyncio.sleep(0)
    assert not task.done() and clock.now() == 0.0
    await clock.advance(1.0)
    await task


async def test_stuck_clock_warns_naming_the_busy_participant(caplog: pytest.LogCaptureFixture) -> None:
    clock = VirtualClock(stall_warning_s=0.05)
    release = asyncio.Event()

    async def stuck() -> None:
        with clock.participant("estimator"):
            await release.wait()

    async def sleeper() -> None:
        with clock.participant("cart") as me:
            await me.sleep_until(1.0)

    with caplog.at_level(logging.WARNING, logger="virtual_hw.clock"):
        tasks = [asyncio.create_task(stuck()), asyncio.create_task(sleeper())]
        # stall_warning_s is wall time by design (a stuck session is stuck in wall time): wait,
        # bounded, for the warning itself rather than a fixed 0.2 s.
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 5.0
        while "participant 'estimator' busy" not in caplog.text and loop.time() < deadline:
            await asyncio.sleep(0.01)  # the watched-for warning is raised after wall time passes
        release.set()
        await asyncio.wait_for(asyncio.gather(*tasks), timeout=5.0)
    assert "participant 'estimator' busy" in caplog.text


async def test_same_event_order_at_speed_max_and_scaled() -> None:
    async def scenario(clock: SimClock) -> list[str]:
        log: list[str] = []
        queue: asyncio.Queue[str] = asyncio.Queue()

        async def device() -> None:
            with clock.participant("device") as me:
                for k in range(1, 4):
                    await me.sleep_until(1.0 * k)
                    queue.put_nowait(f"breath{k}")
                    log.append(f"sent{k}")

        async def bridge() -> None:
            with clock.participant("bridge") as me:
                for _ in range(3):
                    with me.idle():
                        item = await queue.get()
                    log.append(f"got-{item}")
                    await me.sleep(0.4)  # processing that takes sim time
                    log.append(f"done-{item}")

        await asyncio.gather(device(), bridge())
        return log

    fast = await asyncio.wait_for(scenario(VirtualClock()), timeout=5.0)
    # Paced: 200 ms of wall time between events, a margin for a loaded machine's timer jitter.
    paced = await asyncio.wait_for(scenario(ScaledClock(3.0)), timeout=5.0)
    assert fast == paced
    assert fast[:4] == ["sent1", "got-breath1", "done-breath1", "sent2"]


async def test_participant_outside_a_loop_and_bad_times_are_refused() -> None:
    clock = VirtualClock()
    with pytest.raises(ClockError, match="finite"):
        await clock.sleep_until(math.nan)
    with clock.participant("p") as me:
        with pytest.raises(ClockError, match="finite"):
            await me.sleep(math.inf)
    with pytest.raises(ClockError, match="closed"):
        await me.sleep_until(1.0)


def test_participant_needs_a_running_loop() -> None:
    with pytest.raises(ClockError, match="event loop"):
        VirtualClock().participant("p")


# ------------------------------------------------------------------------ scaled clock
def test_scaled_clocks_sharing_an_epoch_agree() -> None:
    wall = [1_000.0]
    a = ScaledClock(10.0, epoch_wall=990.0, wall_time=lambda: wall[0])
    b = ScaledClock(10.0, epoch_wall=990.0, wall_time=lambda: wall[0])
    assert a.now() == b.now() == 100.0
    wall[0] = 1_000.5
    assert a.now() == b.now() == 105.0
    before_epoch = ScaledClock(2.0, epoch_wall=1_010.5, wall_time=lambda: wall[0])
    assert before_epoch.now() == -20.0


def test_scaled_clocks_on_the_real_wall_clock_agree() -> None:
    a = ScaledClock(5.0)
    b = ScaledClock(5.0, epoch_wall=a.epoch_wall)
    assert abs(a.now() - b.now()) < 0.05  # two reads of time.time(), scaled by 5


async def test_scaled_sleep_until_reaches_the_target() -> None:
    clock = ScaledClock(1000.0)
    target = clock.now() + 20.0  # 20 ms of wall time
    await asyncio.wait_for(clock.sleep_until(target), timeout=2.0)
    assert clock.now() >= target
    with clock.participant("p") as me, me.idle():
        await me.sleep(5.0)
    with clock.hold("nothing"):
        assert clock.now() > target


# ------------------------------------------------------------------------ factory
def test_make_clock_max_is_virtual_and_a_factor_is_scaled() -> None:
    assert isinstance(make_clock("max"), VirtualClock)
    assert math.isinf(make_clock("MAX").speed)
    scaled = make_clock("10", epoch_wall=123.0)
    assert isinstance(scaled, ScaledClock)
    assert scaled.speed == 10.0 and scaled.epoch_wall == 123.0
    assert isinstance(make_clock(1.0), SimClock)


@pytest.mark.parametrize("bad", ["fast", "0", "-1", "nan", 0.0, -2.0, True])
def test_bad_speeds_are_refused_by_name(bad: object) -> None:
    with pytest.raises(VirtualConfigError, match="speed"):
        make_clock(bad)  # type: ignore[arg-type]


def test_an_epoch_with_max_is_refused() -> None:
    with pytest.raises(VirtualConfigError, match="epoch"):
        make_clock("max", epoch_wall=1.0)


def test_virtual_clock_options_are_checked() -> None:
    with pytest.raises(VirtualConfigError, match="settle_turns"):
        VirtualClock(settle_turns=0)
    with pytest.raises(VirtualConfigError, match="settle_wall_s"):
        VirtualClock(settle_wall_s=-1.0)
    with pytest.raises(VirtualConfigError, match="start_s"):
        VirtualClock(start_s=math.nan)


@given(st.floats(min_value=1e-6, max_value=1e6, allow_nan=False, allow_infinity=False))
def test_parse_speed_reads_back_any_positive_factor(factor: float) -> None:
    assert parse_speed(repr(factor)) == factor
    assert parse_speed(factor) == factor
