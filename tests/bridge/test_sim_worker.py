"""A session whose proposal worker process dies goes on in a thread and says so in its log."""

from __future__ import annotations

import asyncio
import os
import signal

import pytest

from bridge.log.reader import read_log
from bridge.runtime import BridgeSession
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim

pytestmark = pytest.mark.slow


def test_killed_worker_costs_no_evaluation(tmp_path) -> None:
    killed: list[int] = []

    def killer(session: BridgeSession) -> None:
        async def kill_after_two_evaluations() -> None:
            while not (len(session.records) >= 2 and session.proposal_worker.pid is not None):
                await asyncio.sleep(0.02)  # polls a real worker process's pid; ends with the session
            pid = session.proposal_worker.pid
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        session_task = asyncio.get_running_loop().create_task(kill_after_two_evaluations())
        tasks.append(session_task)

    tasks: list[asyncio.Task[None]] = []
    # 8 minutes of walking (the session's time counts transitions too), so a loaded
    # machine still leaves evaluations after the kill.
    cfg = VirtualSimConfig(minutes=8.0, seed=4, n_explore=3, max_breaths=10, warmup_s=20.0)
    s = asyncio.run(run_virtual_sim(cfg, tmp_path, on_session=killer))
    assert killed and all(t.done() and t.exception() is None for t in tasks)
    log = read_log(tmp_path / "session.mcap")
    events = log.data("/events")
    lost = [e for e in events if e["kind"] == "proposal_worker_lost"]
    assert len(lost) == 1 and "continue in a thread" in lost[0]["message"]
    # Every evaluation once, in order, and proposals went on after the worker died.
    indices = [e["index"] for e in s["evaluations"]]
    assert indices == list(range(len(indices))) and len(indices) > 3
    assert [o["params"] for o in log.data("/observations")] == [e["params"] for e in s["evaluations"]]
    assert events[-1]["kind"] == "session_end"
