"""``hilbo run`` on a bus that another session's bridge already drives is refused before anything
is logged or sent (bridge/run.py; drivers.exosuit.CanEndpoint.check_no_other_bridge)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from test_session_end import replay_config, write_recording

from bridge.run import run_session
from drivers.errors import TransportError
from drivers.exosuit import CanBusConfig, CanEndpoint
from drivers.exosuit.codec import BridgeState

pytestmark = pytest.mark.timeout(120)


def test_a_second_session_on_a_driven_bus_is_refused_and_writes_nothing(tmp_path: Path) -> None:
    cfg, channel = replay_config(tmp_path, write_recording(tmp_path / "breaths.hbr", 20))
    log = tmp_path / "second.mcap"

    async def run() -> None:
        # The first session's bridge: its heartbeat says it is running a session.
        async with CanEndpoint(CanBusConfig("virtual", channel)) as first:
            first.bridge_state = BridgeState.RUNNING
            first.start_heartbeat()
            try:
                await run_session(cfg, log_path=log, operator_view=False, n_actuators=2)
            finally:
                await first.stop_heartbeat()

    with pytest.raises(TransportError, match="another bridge is already driving the exosuit"):
        asyncio.run(run())
    assert not log.exists()
    assert not log.with_suffix(".summary.json").exists()
