"""A real ``kill -9`` of ``hilbo run`` on the virtual devices, then ``hilbo run --resume``.

The devices run as processes of their own on a python-can-remote bus (as in
test_sim_processes.py's ``hilbo run`` test); ``hilbo run`` with the example config (short
protocol: 20 s warm-ups, 3 exploration points) is SIGKILLed at a chosen moment, read off its own
log while it is written: in the exploration bout, right after the optimisation bout's first
setting is acknowledged (the first setting measured after a warm-up), and in the optimisation
bout. ``hilbo run --resume LOG`` must then accept the cut log and finish the session with every
evaluation the killed process completed, once.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest
from test_sim_processes import _free_port, example_for_a_test, needs, started

from bridge.log import Topic
from bridge.log.reader import read_log
from bridge.log.resume import rebuild_optimizer
from bridge.sim.processes import ChildProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

ROOT = Path(__file__).resolve().parents[2]
HILBO = [sys.executable, "-m", "bridge.cli.main"]
#: Three exploration points: the hyperparameters are then first fitted ahead while the last
#: exploration setting is measured, and first used by the optimisation bout's first proposal.
N_EXPLORE = 3


def _ready(log: Path, moment: str) -> bool:
    """Whether the log being written has reached ``moment``."""
    try:
        c = read_log(log, topics=[Topic.PROPOSALS, Topic.ACKS, Topic.OBSERVATIONS])
    except Exception:  # a log whose header is not on disk yet
        return False
    proposals = c.records(Topic.PROPOSALS)
    if moment == "exploration":
        return len(c.records(Topic.OBSERVATIONS)) >= 1 and len(proposals) >= 2
    k = N_EXPLORE if moment == "first optimisation setting" else N_EXPLORE + 1
    at = [i for i, m in enumerate(c.messages) if m.topic == Topic.PROPOSALS and m.record.index == k]
    return bool(at) and any(m.topic == Topic.ACKS for m in c.messages[at[0]:])


async def _run(config: Path, *extra: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        *HILBO, "run", str(config), "--no-view", "--auto-resume", "0", *extra, cwd=ROOT,
        stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)


@pytest.mark.parametrize("moment", ["exploration", "first optimisation setting", "optimisation"])
async def test_kill_9_then_resume_loses_and_doubles_no_evaluation(tmp_path: Path, moment: str) -> None:
    needs("remote")
    cart_port, can_port = _free_port(), _free_port()
    url = f"ws://127.0.0.1:{can_port}/"
    server = ChildProcess("can-remote", [
        sys.executable, "-m", "can_remote", "--interface", "virtual", "--channel", "demo",
        "--host", "127.0.0.1", "--port", str(can_port)], tmp_path / "can-remote.log")
    config = example_for_a_test(tmp_path, cart_port=cart_port, can_url=url)
    config.write_text(config.read_text().replace("n_explore = 2 ", f"n_explore = {N_EXPLORE} "))
    clock = ["--speed", "20", "--epoch", repr(time.time())]
    can = ["--interface", "remote", "--channel", url]
    exosuit = ChildProcess("virtual-exosuit", [*HILBO, "virtual-exosuit", *can, *clock, "--seed", "1",
                                               "--feedback-hz", "50", "--heartbeat-timeout", "0.5"],
                           tmp_path / "exosuit.log")
    cart = ChildProcess("virtual-cart", [
        *HILBO, "virtual-cart", "--transport", "tcp", "--host", "127.0.0.1", "--port", str(cart_port),
        *clock, "--seed", "1", "--can-interface", "remote", "--can-channel", url], tmp_path / "cart.log")
    sessions = tmp_path / "sessions"
    async with started(server):
        await server.wait_listening("127.0.0.1", can_port)
        async with started(exosuit, cart):
            assert json.loads(await exosuit.first_line())["event"] == "ready"
            assert await cart.first_line() == f"tcp 127.0.0.1 {cart_port}"
            first = await _run(config)
            try:
                async with asyncio.timeout(150):
                    while True:
                        logs = sorted(sessions.glob("*.mcap"))
                        if logs and _ready(logs[0], moment):
                            break
                        assert first.returncode is None, "hilbo run ended before the moment"
                        await asyncio.sleep(0.02)
                os.kill(first.pid, signal.SIGKILL)
            finally:
                if first.returncode is None:
                    first.kill()
                await first.communicate()
            assert first.returncode == -signal.SIGKILL
            crashed = logs[0]
            killed = read_log(crashed)
            assert killed.truncated
            done = [o.index for o in killed.records(Topic.OBSERVATIONS)]
            rebuilt, info = rebuild_optimizer(crashed)
            second = await _run(config, "--resume", str(crashed))
            async with asyncio.timeout(150):
                out, err = await second.communicate()
    assert second.returncode == 0, err.decode()
    log_path = Path(out.decode().split()[0])
    resumed = read_log(log_path)
    assert resumed.previous_log == str(crashed)
    final = [e for m in resumed.records(Topic.OPTIMIZER_STATE) if m.reason == "end"
             for e in [m.state["evaluations"]]][-1]
    # Every evaluation the killed process completed is in the resumed session, once, unchanged.
    assert [e["index"] for e in final] == list(range(len(final)))
    assert final[:len(rebuilt.evaluations)] == [e.to_json() for e in rebuilt.evaluations]
    assert len(rebuilt.evaluations) >= len(done) and len(final) > len(rebuilt.evaluations)
    print(f"{moment}: killed with {len(done)} evaluations logged complete, {info.n_evaluations} "
          f"recovered ({info.n_replayed} by replay), discarded {info.discarded_breaths} breaths of the "
          f"setting cut off; the resumed session ended with {len(final)}")
