"""A stall of the bridge's event loop (a descheduled process on a busy PC) costs no pause: the
device's statuses that arrived meanwhile are still in the receive path, and the bridge heartbeat
comes from a cyclic sender the stall does not stop (drivers/PROTOCOL.md, "Heartbeats")."""

from __future__ import annotations

import asyncio
import time

import pytest

from bridge.log.reader import read_log
from bridge.runtime import BridgeSession
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim

pytestmark = pytest.mark.slow

STALL_S = 0.3  # three times the 100 ms watchdogs on both sides


def test_a_300_ms_stall_of_the_bridge_loop_pauses_nothing(tmp_path) -> None:
    stalled: list[float] = []

    def stall_once(session: BridgeSession) -> None:
        async def stall() -> None:
            st = session.status
            while not (st.evaluation == 2 and st.breaths_in_setting >= 2):
                await asyncio.sleep(0.01)
            t0 = time.monotonic()
            time.sleep(STALL_S)  # on purpose: the loop (bridge and in-process device) stalls
            stalled.append(time.monotonic() - t0)
        asyncio.get_running_loop().create_task(stall())

    cfg = VirtualSimConfig(minutes=4.0, seed=2, n_explore=3, max_breaths=10, warmup_s=20.0,
                           proposal_worker="thread")
    asyncio.run(run_virtual_sim(cfg, tmp_path, on_session=stall_once))
    assert stalled and stalled[0] >= STALL_S
    events = read_log(tmp_path / "session.mcap").data("/events")
    assert any(e["kind"] == "loop_stall" for e in events)  # the stall happened, and was seen
    lost = [e["message"] for e in events
            if e["kind"] in ("pause", "watchdog_pause", "heartbeat_lost", "device_fault")
            and "between bouts" not in e["message"]]
    assert lost == []
    assert not any(e["kind"] == "evaluation_cancelled" for e in events)
