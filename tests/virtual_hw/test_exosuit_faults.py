"""Each virtual-exosuit fault, switched on through the Python API and observed from the bridge side.

Fault times are simulated seconds on a ScaledClock whose epoch is the start of the test, at
SPEED simulated seconds per wall second. Not a VirtualClock: the gaps these tests measure are seen
by the bridge's wall-clock watchdogs, and the device's bus-level periods run on loop (wall) time
(virtual_hw/exosuit.py), so the tests wait on the device's ScaledClock for fault windows and on
the wall only where a wall-time rate is the point.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import time
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

from drivers.exosuit.codec import (
    AssistanceOff,
    BridgeHeartbeat,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    ForceFeedback,
    NackReason,
    ProfileAck,
    ProfileCommit,
    ProfileSegment,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, ProfileNackError, Subscription
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import VirtualExosuit

SPEED = 2.0
TABLE = np.round(200.0 * np.sin(np.linspace(0.0, np.pi, 101)) ** 2, 1)
_channels = itertools.count()


@contextlib.asynccontextmanager
async def rig(faults: list[str], **kwargs: Any) -> AsyncIterator[tuple[VirtualExosuit, CanEndpoint]]:
    config = CanBusConfig("virtual", f"vexo-fault-{os.getpid()}-{next(_channels)}")
    kwargs.setdefault("feedback_hz", 100.0)
    async with VirtualExosuit(config, ScaledClock(SPEED), seed=5, faults=faults, **kwargs) as exo, \
            CanEndpoint(config) as ep:
        ep.bridge_state = BridgeState.RUNNING
        ep.start_heartbeat()
        yield exo, ep


def drain(sub: Subscription) -> list[Any]:
    return [sub.get_nowait() for _ in range(sub.qsize())]


async def wait_mode(sub: Subscription, mode: DeviceMode, timeout_s: float = 20.0) -> DeviceStatus:
    """The DeviceStatus that completes "both actuators report ``mode``"."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    latest: dict[int, DeviceMode] = {}
    while True:
        item = await asyncio.wait_for(sub.get(), max(deadline - loop.time(), 0.001))
        message = item.message if hasattr(item, "message") else item
        if isinstance(message, DeviceStatus):
            latest[message.actuator] = message.mode
            if len(latest) == 2 and set(latest.values()) == {mode}:
                return message


def max_gap(times: list[float]) -> float:
    return max(b - a for a, b in itertools.pairwise(sorted(times)))


async def test_drop_status_stops_the_device_heartbeat_for_the_window_only() -> None:
    # 0.6..1.4 sim s = 0.3..0.7 wall s
    async with rig(["drop-status@0.6+0.8"]) as (exo, ep):
        with ep.subscribe(DeviceStatus, ForceFeedback, timestamps=True) as sub:
            t0 = time.time()
            await exo.clock.sleep_until(2.0)  # past the window's end (1.4) on the device's clock
            items = drain(sub)
    status_t = [t - t0 for t, m in items if isinstance(m, DeviceStatus) and m.actuator == 0]
    feedback_t = [t - t0 for t, m in items if isinstance(m, ForceFeedback) and m.actuator == 0]
    assert max_gap(status_t) >= 0.3  # the bridge's 100 ms device watchdog would fire
    assert max(status_t) > 0.75  # ...and the heartbeat comes back after the window
    gap_start = max(t for t in status_t if t < 0.45)
    assert any(gap_start < t < gap_start + 0.3 for t in feedback_t)  # feedback kept flowing
    assert exo.faults.active("drop-status", 1.0) and not exo.faults.active("drop-status", 1.5)


async def test_bus_off_silences_the_node_then_reports_a_bus_error_and_refuses_profiles() -> None:
    # bus-off 4.0..4.6 sim s = 2.0..2.3 wall s; error state until 9.6 sim s = 4.8 wall s. Wide
    # windows on purpose: on a busy machine the first push may take a second, and the push
    # that must be refused "busy" may come a second after the fault is seen.
    async with rig(["bus-off@4+0.6"], bus_error_hold_s=5.0) as (exo, ep):
        with ep.subscribe(DeviceStatus) as sub:
            await ep.push_profile(TABLE, 1)
            await wait_mode(sub, DeviceMode.ASSIST, timeout_s=20.0)
        with ep.subscribe(DeviceStatus, ForceFeedback, ProfileAck, timestamps=True) as sub:
            fault = await wait_mode(sub, DeviceMode.FAULT, timeout_s=20.0)
            with pytest.raises(ProfileNackError) as busy:  # still in the error state
                await ep.push_profile(TABLE, 2, retries=0, timeout_s=2.0, pace_s=0.0)
            after = await wait_mode(sub, DeviceMode.ASSISTANCE_OFF, timeout_s=20.0)
        # FaultBusError cleared itself; FaultHeartbeatLost (deaf for 0.3 s) stays latched until
        # the bridge clears it, the heartbeat having been back since the bus-off ended.
        cleared = await ep.clear_faults()
        await ep.push_profile(TABLE, 3)  # acked with the bridge running: the latch clears
        with ep.subscribe(DeviceStatus) as sub:
            await wait_mode(sub, DeviceMode.ASSIST)
    assert DeviceFault.BUS_ERROR in fault.faults
    assert DeviceFault.HEARTBEAT_LOST in fault.faults  # deaf for 0.3 s: the watchdog fired too
    assert busy.value.reason == NackReason.BUSY
    assert DeviceFault.BUS_ERROR not in after.faults
    assert DeviceFault.HEARTBEAT_LOST in after.faults
    assert (cleared.ok, cleared.cleared) == (True, DeviceFault.HEARTBEAT_LOST)
    assert exo.stats["bus_off_dropped"] > 0  # bridge heartbeats it could not hear
    assert exo.stats["bus_off_recovered"] == 1
    assert [v for v, _ in exo.applied_log] == [1, None, 3]


async def test_bus_off_leaves_a_gap_in_all_device_traffic() -> None:
    async with rig(["bus-off@0.6+0.8"]) as (exo, ep):  # 0.3..0.7 wall s
        with ep.subscribe(timestamps=True) as sub:
            t0 = time.time()
            await exo.clock.sleep_until(2.0)  # past the window's end (1.4) on the device's clock
            times = [t - t0 for t, _ in drain(sub)]
    assert max_gap(times) >= 0.35
    assert max(times) > 0.75


async def test_counted_nacks_hit_the_next_commits_with_their_reasons() -> None:
    async with rig(["nack-busy@0x2", "nack-bad-length@0x1"]) as (exo, ep):
        with pytest.raises(ProfileNackError) as refused:  # bad_length is not worth retrying
            await ep.push_profile(TABLE, 1, timeout_s=0.05)
        result = await ep.push_profile(TABLE, 2, timeout_s=0.05)  # busy, busy, then ack
    assert (refused.value.reason, refused.value.detail, refused.value.attempts) == (
        NackReason.BAD_LENGTH, 768, 1)
    assert (result.attempts, result.nacks) == (3, (NackReason.BUSY, NackReason.BUSY))
    assert exo.faults.taken["nack-busy"] == 2 and exo.faults.left("nack-busy") == 0


async def test_nack_window_refuses_every_commit_until_it_closes() -> None:
    async with rig(["nack-bad-crc@0+1.2"]) as (exo, ep):  # 0..0.6 wall s
        with pytest.raises(ProfileNackError) as refused:
            await ep.push_profile(TABLE, 1, retries=1, timeout_s=0.05, pace_s=0.0)
        await exo.clock.sleep_until(1.3)
        result = await ep.push_profile(TABLE, 2)
    assert (refused.value.reason, refused.value.attempts) == (NackReason.BAD_CRC, 2)
    assert result.attempts == 1


async def test_malformed_frames_are_counted_by_the_bridge_and_valid_traffic_still_flows() -> None:
    faults = ["wrong-dlc@0+100", "unknown-id@0+100", "garbage@0+100"]
    async with rig(faults, malformed_rate_hz=200.0) as (exo, ep):
        with ep.subscribe(DeviceStatus) as statuses, \
                ep.subscribe(AssistanceOff, BridgeHeartbeat, ProfileSegment, ProfileCommit) as own:
            await asyncio.sleep(0.5)  # wall: the malformed rate (200 Hz) is a loop-time rate by design
            sent = dict(exo.stats)
            loop = asyncio.get_running_loop()
            deadline = loop.time() + 2.0
            while loop.time() < deadline and not (  # the frames in flight reach the bridge
                ep.counters["bad_length"] >= sent["malformed_wrong-dlc"]
                and ep.counters["unknown_id"] >= sent["malformed_unknown-id"]
            ):
                await asyncio.sleep(0.01)  # they cross python-can's bus thread: a bounded poll
            n_status = statuses.qsize()
            impersonated = own.qsize()
        counters = dict(ep.counters)
    assert sent["malformed_wrong-dlc"] > 20 and sent["malformed_unknown-id"] > 20
    assert counters["bad_length"] >= sent["malformed_wrong-dlc"]
    assert counters["unknown_id"] >= sent["malformed_unknown-id"]
    assert n_status >= 30  # ~50 expected: the bridge still hears the device heartbeat
    assert impersonated == 0  # garbage never uses the bridge's identifiers


async def test_counted_malformed_burst_sends_exactly_that_many_frames() -> None:
    async with rig(["unknown-id@0.2x7"], malformed_rate_hz=100.0) as (exo, ep):
        # The burst starts at 0.2 sim s and takes 70 ms wall at 100 Hz, longer on a busy machine
        # (the loop skips the ticks it missed): wait for its 7 frames to be counted (bounded,
        # generous), then 30 more periods, in which an 8th frame, if any, would be sent.
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 20.0
        while ep.counters["unknown_id"] < 7 and loop.time() < deadline:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.3)
        counted = ep.counters["unknown_id"]
    assert exo.stats["malformed_sent"] == 7
    assert counted == 7
