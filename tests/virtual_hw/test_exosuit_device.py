"""The virtual exosuit against a bridge-side CanEndpoint over python-can's in-process virtual bus."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np
import pytest

from drivers.exosuit.codec import (
    ASSISTANCE_OFF_ID,
    AssistanceOff,
    AssistanceOffReason,
    BridgeHeartbeat,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    ForceFeedback,
    NackReason,
    ProfileAck,
    ProfileCommit,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, ProfileNackError, Subscription
from drivers.exosuit.profile import ProfileTransfer, forces_to_raw, pack_tables
from hilbo_core.profiles import ForceProfile, hip_ankle_profiles
from virtual_hw.clock import ScaledClock, SimClock, VirtualClock
from virtual_hw.exosuit import HEARTBEAT_TIMEOUT_S, DeviceLimits, VirtualExosuit

SPEED = 4.0  # simulated s per wall s: a 1.1 s stride takes 0.28 s
GRID = np.linspace(0.0, 100.0, 101)
TABLE = np.round(200.0 * np.sin(np.linspace(0.0, np.pi, 101)) ** 2, 1)  # peak 200 N at 50 %GC
_channels = itertools.count()


@dataclass
class Rig:
    exo: VirtualExosuit
    ep: CanEndpoint
    clock: SimClock
    applied: list[tuple[tuple[ForceProfile, ...], float]] = field(default_factory=list)


@contextlib.asynccontextmanager
async def rig(*, state: BridgeState | None = BridgeState.RUNNING, clock: SimClock | None = None,
              on_applied: Callable[..., None] | None = None, **kwargs: Any) -> AsyncIterator[Rig]:
    """A device and a bridge endpoint on a fresh virtual channel (heartbeat in ``state``)."""
    config = CanBusConfig("virtual", f"vexo-{os.getpid()}-{next(_channels)}")
    clock = clock or ScaledClock(SPEED)
    kwargs.setdefault("feedback_hz", 100.0)
    # A busy machine may deschedule this process for hundreds of ms; the device's 100 ms watchdog
    # on the bridge heartbeat would then turn assistance off in the middle of a test about
    # something else. The tests of that watchdog give it its real timeout.
    kwargs.setdefault("heartbeat_timeout_s", 2.0)
    applied: list[tuple[tuple[ForceProfile, ...], float]] = []
    record = on_applied or (lambda profiles, t: applied.append((profiles, t)))
    async with VirtualExosuit(config, clock, seed=3, on_applied=record, **kwargs) as exo, \
            CanEndpoint(config) as ep:
        if state is not None:
            ep.bridge_state = state
            ep.start_heartbeat()
        yield Rig(exo, ep, clock, applied)


async def until(sub: Subscription, predicate: Callable[[Any], bool], timeout_s: float = 20.0) -> Any:
    """The first message (as the subscription delivers it) that satisfies ``predicate``."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while True:
        remaining = deadline - loop.time()
        if remaining <= 0:
            raise AssertionError(f"no matching message within {timeout_s} s")
        item = await asyncio.wait_for(sub.get(), remaining)
        if predicate(item):
            return item


async def until_all(sub: Subscription, predicate: Callable[[DeviceStatus], bool],
                    n_actuators: int = 2, timeout_s: float = 20.0) -> list[DeviceStatus]:
    """Every DeviceStatus received until each actuator's latest one satisfies ``predicate``."""
    seen: list[DeviceStatus] = []
    latest: dict[int, DeviceStatus] = {}

    def done(status: DeviceStatus) -> bool:
        seen.append(status)
        latest[status.actuator] = status
        return len(latest) == n_actuators and all(predicate(s) for s in latest.values())

    await until(sub, done, timeout_s)
    return seen


def assisting(version: int) -> Callable[[DeviceStatus], bool]:
    return lambda s: s.mode == DeviceMode.ASSIST and s.profile_version_active == version


async def push_and_assist(r: Rig, table: np.ndarray, version: int) -> None:
    with r.ep.subscribe(DeviceStatus) as sub:
        await r.ep.push_profile(table, version)
        await until_all(sub, assisting(version))


async def heartbeat_back(r: Rig, timeout_s: float = 5.0) -> None:
    """Wait until the device has seen the bridge heartbeat back for its clear period."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while r.exo.heartbeat_back_s() < r.exo.heartbeat_clear_s:
        assert loop.time() < deadline, "the bridge heartbeat did not come back"
        await asyncio.sleep(0.01)  # the device's heartbeat-back time is loop time: bounded poll


async def test_profile_is_pending_then_active_at_a_gait_boundary_and_applied_bit_for_bit() -> None:
    async with rig() as r:
        t_before = r.clock.now()
        with r.ep.subscribe(DeviceStatus) as sub:
            result = await r.ep.push_profile(TABLE, 5)
            t_acked = r.clock.now()
            seen = await until_all(sub, assisting(5))
    assert (result.version, result.attempts, result.nacks) == (5, 1, ())
    # each actuator reports the table pending before it reports it active; the leg whose boundary
    # comes second is pending for at least half a stride, so it is seen pending
    for a in (0, 1):
        states = [(s.profile_version_active, s.profile_version_pending)
                  for s in seen if s.actuator == a]
        first_active = states.index((5, 0))
        assert all(active == 0 for active, _ in states[:first_active])
    assert any(s.profile_version_pending == 5 and s.profile_version_active == 0 for s in seen)
    raw = ProfileTransfer.from_forces(TABLE, 5).forces_raw
    assert r.exo.active_table(0).forces_raw == raw  # type: ignore[union-attr]
    assert r.exo.active_table(1) is r.exo.active_table(0)
    assert r.exo.pending_table is None
    ((profiles, t_applied),) = r.applied
    (hip,) = profiles
    assert hip.actuator == "hip"
    assert forces_to_raw(hip.force_n) == raw
    # applied at the gait-cycle boundary of the second leg, within one stride of the ack
    gait = r.exo.gait_model
    assert gait is not None
    assert min(gait.phase_pct(a, t_applied) for a in (0, 1)) == pytest.approx(0.0, abs=1e-9)
    assert t_before < t_applied < t_acked + 1.25
    assert r.exo.applied_log == ((5, t_applied),)


async def test_corrupted_or_incomplete_transfer_is_nacked_and_never_applied() -> None:
    async with rig() as r:
        bad_crc = ProfileTransfer.from_forces(TABLE, 6)
        gap = ProfileTransfer.from_forces(TABLE, 7).frames()
        with r.ep.subscribe(ProfileAck) as acks:
            for frame in bad_crc.frames()[:-1]:
                await r.ep.send(frame)
            await r.ep.send(ProfileCommit(6, 101, bad_crc.crc32 ^ 1))
            nack_crc = await asyncio.wait_for(acks.get(), 2.0)
            for frame in gap[:4] + gap[5:]:  # segment 4 lost on the way
                await r.ep.send(frame)
            nack_gap = await asyncio.wait_for(acks.get(), 2.0)
        await r.clock.sleep(2.5)  # more than two strides
        with r.ep.subscribe(DeviceStatus) as sub:
            latest = [await asyncio.wait_for(sub.get(), 1.0) for _ in range(4)]
    assert nack_crc == ProfileAck.nack(6, NackReason.BAD_CRC)
    assert nack_gap == ProfileAck.nack(7, NackReason.MISSING_SEGMENT, 4)
    assert all((s.profile_version_active, s.profile_version_pending) == (0, 0) for s in latest)
    assert all(s.mode == DeviceMode.TRANSPARENT for s in latest)
    assert r.applied == []
    assert r.exo.active_table(0) is None and r.exo.pending_table is None
    assert (r.exo.stats["nack_bad_crc"], r.exo.stats["nack_missing_segment"]) == (1, 1)


async def test_tables_outside_the_device_limits_are_nacked_out_of_limits() -> None:
    limits = DeviceLimits(max_force_n=150.0, max_slope_n_per_pct=10.0)
    steep = np.r_[np.zeros(50), np.full(51, 100.0)]  # a 100 N step at point 50; 10 N allowed
    async with rig(limits=limits) as r:
        with pytest.raises(ProfileNackError) as too_strong:
            await r.ep.push_profile(TABLE, 8)
        with pytest.raises(ProfileNackError) as too_steep:
            await r.ep.push_profile(steep, 9)
        await r.ep.push_profile(np.minimum(TABLE, 150.0), 10)  # within both limits: acked
    first_above = int(np.argmax(TABLE > 150.0))
    assert (too_strong.value.reason, too_strong.value.detail, too_strong.value.attempts) == (
        NackReason.OUT_OF_LIMITS, first_above, 1)
    assert (too_steep.value.reason, too_steep.value.detail) == (NackReason.OUT_OF_LIMITS, 50)
    assert r.exo.stats["nack_out_of_limits"] == 2
    assert r.exo.stats["acks"] == 1


async def test_hip_ankle_suit_splits_the_concatenated_table_hip_first() -> None:
    hip, ankle = hip_ankle_profiles(
        {"hip_t_peak": 25.0, "hip_t_offset": 45.0, "ankle_t1": 35.0, "ankle_t2": 55.0})
    table = pack_tables([hip.force_n, ankle.force_n])
    assert np.array_equal(table, np.r_[hip.force_n, ankle.force_n])
    async with rig(joints=("hip", "ankle")) as r:
        with r.ep.subscribe(DeviceStatus) as sub:
            await r.ep.push_tables([hip.force_n, ankle.force_n], 10)  # the bridge's path
            await until_all(sub, assisting(10))
        with pytest.raises(ProfileNackError) as odd:
            await r.ep.push_profile(table[:-1], 11)
    ((profiles, _),) = r.applied
    assert [p.actuator for p in profiles] == ["hip", "ankle"]
    raw = ProfileTransfer.from_forces(table, 10).forces_raw
    assert forces_to_raw(profiles[0].force_n) + forces_to_raw(profiles[1].force_n) == raw
    assert (odd.value.reason, odd.value.detail) == (NackReason.BAD_LENGTH, 768)


async def test_feedback_tracks_the_desired_force_within_5_percent_of_peak() -> None:
    async with rig(feedback_hz=200.0) as r:
        await push_and_assist(r, TABLE, 12)
        frames: list[ForceFeedback] = []
        with r.ep.subscribe(ForceFeedback) as sub:
            end = asyncio.get_running_loop().time() + 1.5 * 1.1 / SPEED  # 1.5 strides
            while asyncio.get_running_loop().time() < end:
                frames.append(await asyncio.wait_for(sub.get(), 1.0))
    assert {f.actuator for f in frames} == {0, 1}
    desired = np.array([f.desired_force_n for f in frames])
    error = np.array([f.measured_force_n for f in frames]) - desired
    assert desired.max() > 190.0 and desired.min() < 5.0  # a whole cycle, peak included
    assert np.abs(error).max() <= 0.05 * 200.0
    assert error.std() > 0.2  # lag and sensor noise: not a copy of the desired force
    # the desired force is the table at the reported phase (0.5 %GC steps on the wire: ±1.6 N)
    expected = np.interp([f.gait_phase_pct for f in frames], GRID, TABLE)
    assert np.abs(desired - expected).max() <= 1.7
    counters = [f.counter for f in frames if f.actuator == 0]
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(counters))


async def test_assistance_off_command_zeroes_the_force_latches_and_a_new_ack_resumes() -> None:
    async with rig(feedback_hz=200.0) as r:
        await push_and_assist(r, TABLE, 13)
        with r.ep.subscribe(ForceFeedback, DeviceStatus, timestamps=True) as sub:
            # Wall: force feedback is a loop-time rate (200 Hz), so windows of it are wall time.
            await asyncio.sleep(0.1)
            t_off = time.time()
            await r.ep.send(AssistanceOff(AssistanceOffReason.OPERATOR_STOP))  # heartbeat: running
            await asyncio.sleep(0.4)  # wall: a window of 200 Hz (loop-time) feedback after the stop
            items = [sub.get_nowait() for _ in range(sub.qsize())]
        await push_and_assist(r, TABLE, 14)  # acked while running: the latch clears
    before = [m for t, m in items if isinstance(m, ForceFeedback) and t < t_off]
    after = [m for t, m in items if isinstance(m, ForceFeedback) and t > t_off + 0.05]
    statuses = [m for t, m in items if isinstance(m, DeviceStatus) and t > t_off + 0.05]
    assert max(f.desired_force_n for f in before) > 50.0
    assert after and all(f.desired_force_n == 0.0 for f in after)
    assert all(abs(f.measured_force_n) < 5.0 for f in after)  # cable slack
    assert statuses and all(s.mode == DeviceMode.ASSISTANCE_OFF for s in statuses)
    assert [v for v, _ in r.exo.applied_log] == [13, None, 14]
    assert r.applied[1][0] == ()
    assert r.exo.stats["assistance_off_received"] == 1


async def test_assistance_off_identifier_with_a_malformed_payload_still_stops_the_device() -> None:
    async with rig() as r:
        await push_and_assist(r, TABLE, 15)
        with r.ep.subscribe(DeviceStatus) as sub:
            await r.ep.send(can.Message(arbitration_id=ASSISTANCE_OFF_ID, data=b"",
                                        is_extended_id=False))
            await until_all(sub, lambda s: s.mode == DeviceMode.ASSISTANCE_OFF)
        assert r.exo.endpoint.counters["bad_length"] == 1  # not decodable, still obeyed
    assert r.exo.stats["assistance_off_received"] == 1
    assert [v for v, _ in r.exo.applied_log] == [15, None]


async def test_lost_bridge_heartbeat_stops_assistance_even_if_a_stale_counter_repeats() -> None:
    async with rig(heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S) as r:
        await push_and_assist(r, TABLE, 16)
        with r.ep.subscribe(DeviceStatus) as sub:
            await r.ep.stop_heartbeat()
            loop = asyncio.get_running_loop()
            t_stop = loop.time()

            async def stale() -> None:  # a hung bridge whose adapter repeats the last frame
                while True:
                    await r.ep.send(BridgeHeartbeat(200, BridgeState.RUNNING))
                    await asyncio.sleep(0.02)  # a bridge heartbeat period (loop time, as the watchdog)

            repeater = asyncio.create_task(stale())
            off = await until(sub, lambda s: s.mode == DeviceMode.ASSISTANCE_OFF)
            elapsed = loop.time() - t_stop
            repeater.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await repeater
        assert DeviceFault.HEARTBEAT_LOST in off.faults
        assert 0.07 <= elapsed  # not before the watchdog's 100 ms (after it: when scheduled)
        # The recovery below is not about the watchdog: a busy machine must not trip it again
        # between the clear and the push (the push was then refused "busy").
        r.exo.heartbeat_timeout_s = 2.0
        r.ep.start_heartbeat()
        await heartbeat_back(r)
        assert (await r.ep.clear_faults()).ok  # the fault-clear step (PROTOCOL.md)
        await push_and_assist(r, TABLE, 17)
        with r.ep.subscribe(DeviceStatus) as sub:
            back = await asyncio.wait_for(sub.get(), 1.0)
    assert back.faults == DeviceFault(0) and back.mode == DeviceMode.ASSIST
    assert [v for v, _ in r.exo.applied_log] == [16, None, 17]


async def test_watchdog_waits_for_heartbeats_queued_while_the_device_loop_was_stalled() -> None:
    async with rig(state=None, heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S) as r:
        channel = r.ep.config.channel
        stop = threading.Event()

        def bridge_in_another_thread() -> None:  # keeps beating while this loop is stalled
            with can.Bus(interface="virtual", channel=channel) as bus:
                for counter in itertools.cycle(range(256)):
                    if stop.is_set():
                        return
                    # Liveness advances too (every 10 frames), as the bridge's loop does.
                    bus.send(BridgeHeartbeat(counter, BridgeState.RUNNING,
                                             counter // 10).to_frame())
                    time.sleep(0.02)  # a heartbeat period in a real thread: the watchdog is wall time

        beater = threading.Thread(target=bridge_in_another_thread, daemon=True)
        beater.start()
        try:
            await push_and_assist(r, TABLE, 23)
            time.sleep(0.3)  # the device's event loop (this one) stalls for 3 watchdog periods
            await asyncio.sleep(0.2)  # wall: room for a false watchdog expiry after the stall
            modes = [r.exo.mode(a) for a in (0, 1)]
        finally:
            stop.set()
            await asyncio.to_thread(beater.join, 2.0)
    assert modes == [DeviceMode.ASSIST, DeviceMode.ASSIST]
    assert r.exo.stats["watchdog_deferred"] >= 1 and r.exo.stats["heartbeat_lost"] == 0


async def test_idle_bridge_gets_the_table_but_no_assistance_until_running_and_paused_stops() -> None:
    async with rig(state=BridgeState.IDLE) as r:
        with r.ep.subscribe(DeviceStatus) as sub:
            await r.ep.push_profile(TABLE, 18)
            await until_all(sub, lambda s: s.profile_version_active == 18)
            assert all(r.exo.mode(a) == DeviceMode.TRANSPARENT for a in (0, 1))
            assert r.applied == []
            r.ep.bridge_state = BridgeState.RUNNING
            await until_all(sub, assisting(18))
            r.ep.bridge_state = BridgeState.PAUSED
            await until_all(sub, lambda s: s.mode == DeviceMode.ASSISTANCE_OFF)
    assert [v for v, _ in r.exo.applied_log] == [18, None]


async def test_repeated_commit_of_the_active_table_is_acked_again_without_a_switch() -> None:
    async with rig() as r:
        await push_and_assist(r, TABLE, 19)
        switches = r.exo.stats["switches"]
        result = await r.ep.push_profile(TABLE, 19)  # e.g. the first ack was lost
        await r.clock.sleep(1.5)
    assert result.attempts == 1
    assert r.exo.stats["switches"] == switches
    assert r.exo.pending_table is None
    assert len(r.applied) == 1


async def test_device_takes_an_open_python_can_bus() -> None:
    channel = f"vexo-bus-{os.getpid()}"
    bus = can.Bus(interface="virtual", channel=channel)
    async with VirtualExosuit(bus, ScaledClock(SPEED), feedback_hz=0) as exo, \
            CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        result = await ep.push_profile(TABLE, 20)
    assert result.attempts == 1 and exo.stats["acks"] == 1
    assert exo.stats["feedback_sent"] == 0


async def test_on_applied_error_is_surfaced_by_wait_and_on_exit() -> None:
    def broken(profiles: tuple[ForceProfile, ...], t_s: float) -> None:
        raise RuntimeError(f"cart refused the profile at {t_s:.3f} s")

    with pytest.raises(RuntimeError, match="cart refused"):
        async with rig(on_applied=broken) as r:
            await r.ep.push_profile(TABLE, 21)
            with pytest.raises(RuntimeError, match="cart refused"):
                await asyncio.wait_for(r.exo.wait(), 5.0)


async def test_virtual_clock_jumps_straight_to_the_boundary() -> None:
    clock = VirtualClock()
    async with rig(clock=clock) as r:
        wall0 = time.monotonic()
        await push_and_assist(r, TABLE, 22)
        wall = time.monotonic() - wall0
        ((_, t_applied),) = r.applied
        assert clock.now() == t_applied > 0.0  # time moved to the boundary and stopped there
    assert wall < 1.0  # no waiting for a stride
