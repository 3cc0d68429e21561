"""Across two processes on SocketCAN vcan0 (natively, or inside user-mode Linux; see conftest).

The device side is the scaffold responder (exosuit_responder.py) run as its own process with the
project's interpreter, one process for the module (each test uses its own profile versions); the
bridge side is a CanEndpoint in this process.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import queue
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.exosuit.codec import BridgeState, NackReason, ProfileAck, ProfileCommit
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint
from drivers.exosuit.profile import ProfileTransfer

pytestmark = pytest.mark.vcan

RESPONDER = Path(__file__).with_name("exosuit_responder.py")
VCAN = CanBusConfig("socketcan", "vcan0")
TABLE = np.round(150.0 * np.sin(np.linspace(0.0, np.pi, 101)) ** 2, 1)
CORRUPT_ONCE = 35  # the responder corrupts the first transfer of this version


class ResponderProcess:
    """The responder process, with its stdout lines read by a thread (reads never hang)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        if self.proc.stdout is not None:
            for line in self.proc.stdout:
                self.lines.put(line.strip())

    def line(self, timeout_s: float) -> str:
        try:
            return self.lines.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError(f"responder silent for {timeout_s} s") from None

    def stats(self) -> dict[str, Any]:
        if self.proc.stdin is None:
            raise RuntimeError("responder stdin missing")
        self.proc.stdin.write("STATS\n")
        self.proc.stdin.flush()
        return json.loads(self.line(10.0))


@pytest.fixture(scope="module")
def device() -> Iterator[ResponderProcess]:
    proc = subprocess.Popen(
        [sys.executable, str(RESPONDER), "--interface", "socketcan", "--channel", "vcan0",
         "--lifetime", "120", "--corrupt-once-version", str(CORRUPT_ONCE)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        handle = ResponderProcess(proc)
        assert handle.line(30.0) == "READY"
        yield handle
        if proc.stdin is not None:
            proc.stdin.close()  # the responder's signal to stop
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


async def test_101_point_profile_pushes_commits_and_acks_across_processes(
    device: ResponderProcess,
) -> None:
    async with CanEndpoint(VCAN) as ep:
        ep.bridge_state = BridgeState.RUNNING
        ep.start_heartbeat(period_s=0.01)
        result = await ep.push_profile(TABLE, 33)
        # The device is another process on a real (v)CAN bus: poll its stats, bounded, until it
        # has counted 3 running heartbeats, instead of sleeping a fixed time for them.
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 10.0
        while True:
            seen = device.stats()
            running = [c for c, state in seen["heartbeats"] if state == BridgeState.RUNNING]
            if len(running) >= 3 or loop.time() > deadline:
                break
            await asyncio.sleep(0.01)  # real bus, other process: a bounded poll, not a fixed wait
        await ep.stop_heartbeat()
    transfer = ProfileTransfer.from_forces(TABLE, 33)
    assert (result.version, result.n_points, result.attempts) == (33, 101, 1)
    assert [33, list(transfer.forces_n)] in seen["acked"]
    counters = [c for c, state in seen["heartbeats"] if state == BridgeState.RUNNING]
    assert len(counters) >= 3
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(counters))


async def test_corrupted_transfer_is_nacked_across_processes(device: ResponderProcess) -> None:
    transfer = ProfileTransfer.from_forces(TABLE, 34)
    async with CanEndpoint(VCAN) as ep:
        with ep.subscribe(ProfileAck) as acks:
            for frame in transfer.frames()[:-1]:
                await ep.send(frame)
            await ep.send(ProfileCommit(34, 101, transfer.crc32 ^ 0xFFFF))
            nack = await asyncio.wait_for(acks.get(), 5.0)
    assert nack == ProfileAck.nack(34, NackReason.BAD_CRC)
    seen = device.stats()
    assert [34, "BAD_CRC"] in seen["nacked"]
    assert all(version != 34 for version, _ in seen["acked"])


async def test_push_recovers_from_a_corrupted_transfer_across_processes(
    device: ResponderProcess,
) -> None:
    async with CanEndpoint(VCAN) as ep:
        result = await ep.push_profile(TABLE, CORRUPT_ONCE, pace_s=0.001)
    assert (result.attempts, result.nacks) == (2, (NackReason.BAD_CRC,))
    seen = device.stats()
    assert [CORRUPT_ONCE, "BAD_CRC"] in seen["nacked"]
    assert [v for v, _ in seen["acked"]].count(CORRUPT_ONCE) == 1
