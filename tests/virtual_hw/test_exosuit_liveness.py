"""The virtual exosuit's liveness watchdog: a bridge whose cyclic sender still beats but whose
liveness counter stands still (a hung bridge) loses assistance (PROTOCOL.md, "Heartbeats")."""

from __future__ import annotations

import asyncio

import can
from test_exosuit_device import TABLE, heartbeat_back, push_and_assist, rig, until

from drivers.exosuit.codec import (
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    heartbeat_sequence,
)


async def test_a_hung_bridge_whose_cyclic_sender_still_beats_loses_assistance() -> None:
    async with rig(liveness_timeout_s=0.4) as r:
        await push_and_assist(r, TABLE, 31)
        await r.ep.stop_heartbeat()
        # What the kernel's broadcast manager does for a hung bridge: the same 256 frames on
        # and on, Counter advancing, Liveness standing still.
        hung = can.Bus(interface="virtual", channel=r.ep.config.channel)
        try:
            cyclic = hung.send_periodic(heartbeat_sequence(BridgeState.RUNNING, 77), 0.02)
            loop = asyncio.get_running_loop()
            t_hung = loop.time()
            with r.ep.subscribe(DeviceStatus) as sub:
                off = await until(sub, lambda s: s.mode == DeviceMode.ASSISTANCE_OFF, timeout_s=10.0)
            elapsed = loop.time() - t_hung
            held = await r.ep.clear_faults()  # the counter advances, yet the bridge is not back
            cyclic.stop()
        finally:
            hung.shutdown()
        assert DeviceFault.HEARTBEAT_LOST in off.faults
        assert elapsed >= 0.4 - 0.05  # the liveness watchdog, not the 100 ms bus watchdog
        assert (r.exo.stats["liveness_lost"], r.exo.stats["heartbeat_lost"]) == (1, 0)
        assert DeviceFault.HEARTBEAT_LOST in held.held
        r.ep.start_heartbeat()  # the bridge is back: Counter and Liveness advance
        await heartbeat_back(r)
        assert (await r.ep.clear_faults()).ok
        await push_and_assist(r, TABLE, 32)
        applied = [v for v, _ in r.exo.applied_log]  # before the rig's bridge stops beating
    assert applied == [31, None, 32]


async def test_an_advancing_liveness_keeps_the_device_assisting() -> None:
    async with rig(liveness_timeout_s=0.3) as r:
        await push_and_assist(r, TABLE, 33)
        await asyncio.sleep(1.0)  # wall time on purpose: three liveness watchdog periods pass
        modes = [r.exo.mode(a) for a in (0, 1)]
    assert modes == [DeviceMode.ASSIST, DeviceMode.ASSIST]
    assert r.exo.stats["liveness_lost"] == 0
