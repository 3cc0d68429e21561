"""Two bridges on one exosuit bus: the second is refused before it sends anything, and a bridge
whose bus another bridge's heartbeat appears on fails its bus (DESIGN.md, safety invariants)."""

from __future__ import annotations

import asyncio
import itertools
import os

import can
import pytest

from drivers.errors import DriverConfigError, DriverError, TransportError
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint

_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"hilbo-2br-{os.getpid()}-{next(_channels)}"


async def _until(predicate, timeout_s: float = 10.0) -> bool:
    """Poll ``predicate`` on the loop until true or ``timeout_s`` (a bound, not a wait)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not predicate():
        if loop.time() > deadline:
            return False
        await asyncio.sleep(0.005)
    return True


async def test_a_second_bridge_is_refused_while_the_first_sends_its_heartbeat(channel: str) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as first:
        first.start_heartbeat(period_s=0.01)
        async with CanEndpoint(CanBusConfig("virtual", channel)) as second:
            with pytest.raises(TransportError, match="another bridge is already driving"):
                await second.check_no_other_bridge()
            # It sent nothing: the first bridge never saw a heartbeat that was not its own.
            assert second.received["BridgeHeartbeat"] > 0
        assert first.received.get("BridgeHeartbeat", 0) == 0
        first.send_nowait(can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False))
        await first.stop_heartbeat()


async def test_a_bus_without_another_bridge_passes_the_check(channel: str) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as device, \
            CanEndpoint(CanBusConfig("virtual", channel)) as bridge:
        await bridge.check_no_other_bridge(listen_s=0.05)
        bridge.start_heartbeat(period_s=0.01)
        # The device-side endpoint hears the heartbeat and judges nothing (it never sends one).
        assert await _until(lambda: device.received.get("BridgeHeartbeat", 0) >= 3)
        await bridge.stop_heartbeat()
        with pytest.raises(DriverError, match="endpoint is not open"):
            await CanEndpoint(CanBusConfig("virtual", channel)).check_no_other_bridge()


async def test_the_check_refuses_a_bad_listen_time_and_a_running_own_heartbeat(channel: str) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as bridge:
        for bad in (0.0, -1.0, float("nan"), "0.1"):
            with pytest.raises(DriverConfigError, match="listen_s="):
                await bridge.check_no_other_bridge(listen_s=bad)  # type: ignore[arg-type]
        bridge.start_heartbeat(period_s=0.01)
        with pytest.raises(DriverError, match="after start_heartbeat"):
            await bridge.check_no_other_bridge()
        await bridge.stop_heartbeat()


async def test_two_bridges_started_together_both_fail_their_bus(channel: str) -> None:
    # Both checked an empty bus at the same moment and started: each hears the other's
    # heartbeat, and each bus fails, which ends each session with assistance-off.
    async with CanEndpoint(CanBusConfig("virtual", channel)) as a, \
            CanEndpoint(CanBusConfig("virtual", channel)) as b:
        await asyncio.gather(a.check_no_other_bridge(listen_s=0.02),
                             b.check_no_other_bridge(listen_s=0.02))
        a.start_heartbeat(period_s=0.01)
        b.start_heartbeat(period_s=0.01)
        errors = await asyncio.wait_for(asyncio.gather(a.wait_failed(), b.wait_failed()), 10.0)
        for err in errors:
            assert isinstance(err, TransportError)
            assert "another bridge is sending heartbeats on this bus" in str(err)
        for ep in (a, b):
            await ep.stop_heartbeat()


async def test_its_own_echoed_heartbeat_is_not_another_bridge(channel: str) -> None:
    # With receive_own_messages the bus hands back this bridge's own frames (is_rx False).
    config = CanBusConfig("virtual", channel, options={"receive_own_messages": True})
    async with CanEndpoint(config) as bridge:
        await bridge.check_no_other_bridge(listen_s=0.02)
        bridge.start_heartbeat(period_s=0.01)
        assert await _until(lambda: bridge.received.get("BridgeHeartbeat", 0) >= 5)
        failed = asyncio.ensure_future(bridge.wait_failed())
        await asyncio.sleep(0)
        assert not failed.done()
        failed.cancel()
        await bridge.stop_heartbeat()
