"""A whole bridge session (:func:`bridge.run.run_session`, as ``hilbo run``) replaying each real
export through its vendor preset, with the virtual exosuit on a python-can virtual bus: the
session reads every breath of the file and ends when the replay does.
"""

from __future__ import annotations

import asyncio
import dataclasses
import uuid
from pathlib import Path

import msgspec
import pytest
from cart_exports import EXPORTS, needs_exports

from bridge.config import parse_config
from bridge.run import run_session
from bridge.sim.virtual import VirtualSimConfig, sim_config_text
from drivers.cart import CartConfig
from drivers.exosuit import CanBusConfig
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import SUIT_JOINTS, VirtualExosuit

pytestmark = pytest.mark.timeout(60)



@needs_exports
@pytest.mark.parametrize(("name", "fmt", "n_breaths"), [
    ("cosmed_test.xlsx", "cosmed", 10), ("cortex_test.xml", "cortex", 13), ("vyntus_test.txt", "vyntus", 7),
])
def test_session_replays_the_export_to_its_end(tmp_path: Path, name: str, fmt: str, n_breaths: int) -> None:
    assert EXPORTS is not None
    sim = VirtualSimConfig(minutes=30.0, seed=1)
    cfg = parse_config(sim_config_text(sim, tmp_path), source="<test>")
    channel = f"hilbo-replay-{uuid.uuid4().hex[:8]}"
    cfg = dataclasses.replace(
        cfg,
        cart=CartConfig.from_dict({"transport": "replay", "format": fmt,
                                   "options": {"path": str(EXPORTS / name), "speed": "max"}}),
        can=msgspec.structs.replace(cfg.can, bus=CanBusConfig("virtual", channel)),
    )

    async def run() -> dict[str, object]:
        async with VirtualExosuit(CanBusConfig("virtual", channel), ScaledClock(1.0),
                                  joints=SUIT_JOINTS[sim.preset], seed=1):
            result = await run_session(cfg, log_path=tmp_path / "s.mcap", auto_resume_s=0.0,
                                       operator_view=False, n_actuators=len(SUIT_JOINTS[sim.preset]))
        return result.summary

    summary = asyncio.run(run())
    assert summary["n_breaths"] == n_breaths
    assert (tmp_path / "s.mcap").stat().st_size > 0
