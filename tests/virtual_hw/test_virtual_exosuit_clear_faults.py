"""The virtual exosuit's side of the fault-clear step (PROTOCOL.md, "Clearing a latched fault"):
a latched fault blocks profiles until the bridge clears it, and a request clears it only once
its cause is gone."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

from drivers.exosuit.codec import (
    BridgeState,
    ClearFaults,
    ClearFaultsAck,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    NackReason,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, ProfileNackError, Subscription
from virtual_hw.clock import ScaledClock
from virtual_hw.errors import FaultSpecError
from virtual_hw.exosuit import EXOSUIT_FAULTS, HARDWARE_FAULTS, VirtualExosuit

SPEED = 4.0
TABLE = np.round(200.0 * np.sin(np.linspace(0.0, np.pi, 101)) ** 2, 1)
_channels = itertools.count()


@contextlib.asynccontextmanager
async def rig(**kwargs: Any) -> AsyncIterator[tuple[VirtualExosuit, CanEndpoint]]:
    config = CanBusConfig("virtual", f"vexo-clear-{os.getpid()}-{next(_channels)}")
    kwargs.setdefault("feedback_hz", 50.0)
    async with VirtualExosuit(config, ScaledClock(SPEED), seed=9, **kwargs) as exo, \
            CanEndpoint(config) as ep:
        ep.bridge_state = BridgeState.RUNNING
        ep.start_heartbeat()
        yield exo, ep


async def until_all(sub: Subscription, predicate: Callable[[DeviceStatus], bool],
                    timeout_s: float = 5.0) -> dict[int, DeviceStatus]:
    """The latest DeviceStatus of both actuators once both satisfy ``predicate``."""
    latest: dict[int, DeviceStatus] = {}
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not (len(latest) == 2 and all(predicate(s) for s in latest.values())):
        status = await asyncio.wait_for(sub.get(), max(deadline - loop.time(), 0.001))
        latest[status.actuator] = status
    return latest


async def wait_for(check: Callable[[], bool], timeout_s: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not check():
        assert loop.time() < deadline, "condition not reached"
        await asyncio.sleep(0.01)  # state set by frames from python-can's bus thread: bounded poll


async def push_and_assist(ep: CanEndpoint, version: int) -> None:
    with ep.subscribe(DeviceStatus) as sub:
        await ep.push_profile(TABLE, version)
        await until_all(sub, lambda s: s.mode == DeviceMode.ASSIST
                        and s.profile_version_active == version)


async def test_heartbeat_lost_is_cleared_only_once_the_heartbeat_is_back_then_a_commit_resumes() -> None:
    async with rig(heartbeat_clear_s=1.0) as (exo, ep):
        await push_and_assist(ep, 1)
        with ep.subscribe(DeviceStatus) as sub:
            await ep.stop_heartbeat()  # the bridge stalls: the device's watchdog fires
            lost = await until_all(sub, lambda s: DeviceFault.HEARTBEAT_LOST in s.faults)
        assert all(s.mode == DeviceMode.ASSISTANCE_OFF for s in lost.values())
        ep.start_heartbeat()
        await wait_for(lambda: exo.heartbeat_back_s() > 0.0)
        # Latched: a profile is refused busy until the fault is cleared...
        with pytest.raises(ProfileNackError) as busy:
            await ep.push_profile(TABLE, 2, retries=0, pace_s=0)
        # ...and a clear while the heartbeat has been back for less than 1 s is refused too.
        early = await ep.clear_faults()
        assert exo.heartbeat_back_s() < 1.0
        with ep.subscribe(DeviceStatus) as sub:
            still = await until_all(sub, lambda s: True)
        await wait_for(lambda: exo.heartbeat_back_s() >= 1.0)
        done = await ep.clear_faults()
        with ep.subscribe(DeviceStatus) as sub:
            clean = await until_all(sub, lambda s: s.faults == DeviceFault(0))
            # Wall: a negative claim (no assist without a commit) needs a window of device traffic.
            await asyncio.sleep(0.3)  # cleared, but not assisting without a new commit
            idle = await until_all(sub, lambda s: True)
        await push_and_assist(ep, 3)
    assert busy.value.reason == NackReason.BUSY
    assert (early.ok, early.cleared, early.held) == (False, DeviceFault(0), DeviceFault.HEARTBEAT_LOST)
    assert sorted(early.answers) == [0, 1]
    assert all(DeviceFault.HEARTBEAT_LOST in s.faults for s in still.values())
    assert (done.ok, done.cleared, done.held) == (True, DeviceFault.HEARTBEAT_LOST, DeviceFault(0))
    assert all(s.mode == DeviceMode.ASSISTANCE_OFF for s in clean.values())
    assert all(s.mode == DeviceMode.ASSISTANCE_OFF for s in idle.values())
    assert [v for v, _ in exo.applied_log] == [1, None, 3]
    assert (exo.stats["clear_requests"], exo.stats["held_heartbeat_lost"],
            exo.stats["cleared_heartbeat_lost"]) == (2, 1, 1)


async def test_a_hardware_fault_whose_cause_persists_stays_latched() -> None:
    # force-limit from 4 sim s for 2 sim s = 1.0 .. 1.5 wall s, after the first table is applied
    async with rig(faults=["force-limit@4+2"]) as (exo, ep):
        await push_and_assist(ep, 1)
        with ep.subscribe(DeviceStatus) as sub:
            fault = await until_all(sub, lambda s: s.mode == DeviceMode.FAULT)
        assert exo.faults.active("force-limit", exo.clock.now())
        during = await ep.clear_faults(DeviceFault.FORCE_LIMIT, actuator=0)
        with pytest.raises(ProfileNackError) as busy:
            await ep.push_profile(TABLE, 2, retries=0, pace_s=0)
        await wait_for(lambda: not exo.faults.active("force-limit", exo.clock.now()))
        with ep.subscribe(DeviceStatus) as sub:  # the cause is gone, the bit is still latched
            after = await until_all(sub, lambda s: True)
        cleared = await ep.clear_faults()
        await push_and_assist(ep, 3)
    assert all(s.faults == DeviceFault.FORCE_LIMIT for s in fault.values())
    assert (during.ok, during.cleared, during.held) == (False, DeviceFault(0), DeviceFault.FORCE_LIMIT)
    assert sorted(during.answers) == [0]  # only the addressed actuator answers
    assert busy.value.reason == NackReason.BUSY
    assert all(s.faults == DeviceFault.FORCE_LIMIT and s.mode == DeviceMode.FAULT
               for s in after.values())
    assert (cleared.ok, cleared.cleared) == (True, DeviceFault.FORCE_LIMIT)
    assert [v for v, _ in exo.applied_log] == [1, None, 3]


async def test_a_request_for_other_faults_leaves_a_latched_one_alone() -> None:
    async with rig() as (exo, ep):
        with ep.subscribe(DeviceStatus) as sub:
            await until_all(sub, lambda s: True)
            await ep.stop_heartbeat()
            await until_all(sub, lambda s: DeviceFault.HEARTBEAT_LOST in s.faults)
        ep.start_heartbeat()
        await wait_for(lambda: exo.heartbeat_back_s() >= exo.heartbeat_clear_s)
        other = await ep.clear_faults(DeviceFault.OVERCURRENT)
        query = await ep.clear_faults(0)
        with ep.subscribe(ClearFaultsAck) as answers:  # addressed to actuator 1 alone
            await ep.send(ClearFaults(200, DeviceFault.HEARTBEAT_LOST, 1))
            late = await asyncio.wait_for(answers.get(), 2.0)
    assert (other.cleared, other.held) == (DeviceFault(0), DeviceFault.HEARTBEAT_LOST)
    assert (query.cleared, query.held) == (DeviceFault(0), DeviceFault.HEARTBEAT_LOST)
    assert late == ClearFaultsAck(1, 200, DeviceFault.HEARTBEAT_LOST, DeviceFault(0))


def test_hardware_fault_kinds_are_windows_in_the_catalog() -> None:
    assert sorted(HARDWARE_FAULTS) == sorted(
        ["overcurrent", "overtemperature", "force-sensor", "encoder", "force-limit",
         "emergency-stop"])
    assert EXOSUIT_FAULTS.parse("emergency-stop@3+1").duration_s == 1.0
    with pytest.raises(FaultSpecError):
        EXOSUIT_FAULTS.parse("force-limit@3x1")
