"""The bridge heartbeat from a cyclic sender: it goes on while the event loop is blocked, and
only its liveness counter waits for the loop (PROTOCOL.md, "Heartbeats and their timeouts")."""

from __future__ import annotations

import asyncio
import itertools
import os
import threading
import time

import can
import pytest

from drivers.exosuit.codec import BridgeHeartbeat, BridgeState
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint

_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"hilbo-hb-{os.getpid()}-{next(_channels)}"


def _collect(channel: str, n: int, seen: list[BridgeHeartbeat], done: threading.Event) -> None:
    """Play the device in a thread: keep the first ``n`` heartbeats received (30 s at most)."""
    with can.Bus(interface="virtual", channel=channel) as bus:
        deadline = time.monotonic() + 30.0
        while len(seen) < n and time.monotonic() < deadline:
            f = bus.recv(0.1)
            if f is not None and f.arbitration_id == 0x020:
                seen.append(BridgeHeartbeat.from_frame(f))
    done.set()


async def test_heartbeats_go_on_while_the_event_loop_is_blocked_and_liveness_waits(
    channel: str,
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        ep.bridge_state = BridgeState.RUNNING
        ep.start_heartbeat(period_s=0.01)
        seen: list[BridgeHeartbeat] = []
        done = threading.Event()
        device = threading.Thread(target=_collect, args=(channel, 8, seen, done), daemon=True)
        device.start()
        # The event loop is blocked (a long GC pause, a descheduled process) until the device
        # has received 8 heartbeats: nothing of this loop runs meanwhile.
        blocked = done.wait(30.0)
        await asyncio.to_thread(device.join, 5.0)
    assert blocked and len(seen) == 8
    counters = [h.counter for h in seen]
    assert all(b == (a + 1) % 256 for a, b in itertools.pairwise(counters))
    assert {h.state for h in seen} == {BridgeState.RUNNING}
    assert len({h.liveness for h in seen}) == 1  # only the loop advances it


async def test_the_liveness_counter_advances_with_the_loop_and_state_changes_reach_the_frames(
    channel: str,
) -> None:
    device = can.Bus(interface="virtual", channel=channel)
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        ep.start_heartbeat(period_s=0.005, liveness_period_s=0.02)
        liveness: set[int] = set()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 10.0
        while len(liveness) < 3 and loop.time() < deadline:
            f = await asyncio.to_thread(device.recv, 0.5)
            if f is not None:
                liveness.add(BridgeHeartbeat.from_frame(f).liveness)
        ep.bridge_state = BridgeState.PAUSED
        states = []
        while BridgeState.PAUSED not in states and loop.time() < deadline:
            f = await asyncio.to_thread(device.recv, 0.5)
            if f is not None:
                states.append(BridgeHeartbeat.from_frame(f).state)
        await ep.stop_heartbeat()
    device.shutdown()
    assert len(liveness) >= 3
    assert states[-1] == BridgeState.PAUSED and set(states) <= {BridgeState.IDLE, BridgeState.PAUSED}


async def test_stopping_the_heartbeat_stops_the_cyclic_sender(channel: str) -> None:
    device = can.Bus(interface="virtual", channel=channel)
    try:
        async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
            ep.start_heartbeat(period_s=0.005)
            assert await asyncio.to_thread(device.recv, 2.0) is not None
            await ep.stop_heartbeat()
            while await asyncio.to_thread(device.recv, 0.0) is not None:
                pass  # frames sent before the stop
            assert await asyncio.to_thread(device.recv, 0.2) is None
    finally:
        device.shutdown()
