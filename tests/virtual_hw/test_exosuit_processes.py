"""One contract for the virtual exosuit, in process and across processes, and its command line.

* ``virtual``: the device in this process, python-can's in-process virtual bus.
* ``vcan`` (marked ``vcan``): the device as its own process (``python -m virtual_hw.cli_exosuit
  --interface socketcan --channel vcan0``) over SocketCAN vcan0, natively or inside user-mode
  Linux (tests/conftest.py); stopped with SIGTERM, it must exit 0 and report what it did.

The bridge side is a CanEndpoint in this process; an AppliedProfileListener on the same bus
reconstructs the applied table the way a virtual cart in another process does.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from drivers.exosuit.codec import (
    BridgeState,
    DeviceMode,
    DeviceStatus,
    NackReason,
    ProfileAck,
    ProfileCommit,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, Subscription
from drivers.exosuit.profile import ProfileTransfer, forces_to_raw
from hilbo_core.profiles import ForceProfile
from virtual_hw.cli_exosuit import add_virtual_exosuit_parser, main, run
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import AppliedProfileListener, VirtualExosuit

SPEED = 2.0
# The contract is the profile path, not the watchdogs (test_exosuit_device.py covers those): inside
# user-mode Linux, beside CPU-burning processes, this process can stall for more than a second,
# which a real device would rightly treat as a lost bridge (seen: a latched fault, then BUSY
# instead of the BAD_CRC this test checks).
HEARTBEAT_TIMEOUT_S = 5.0
LIVENESS_TIMEOUT_S = 5.0
TABLE = np.round(180.0 * np.sin(np.linspace(0.0, np.pi, 101)) ** 2, 1)
_channels = itertools.count()


class DeviceProcess:
    """The device process, its stdout read line by line by a thread (reads never hang)."""

    def __init__(self, args: list[str]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "virtual_hw.cli_exosuit", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        if self.proc.stdout is not None:
            for line in self.proc.stdout:
                self.lines.put(line.strip())

    def record(self, timeout_s: float) -> dict[str, Any]:
        try:
            return json.loads(self.lines.get(timeout=timeout_s))
        except queue.Empty:
            stderr = self.proc.stderr.read() if self.proc.poll() is not None and self.proc.stderr else ""
            raise AssertionError(f"device process silent for {timeout_s} s; stderr: {stderr}") from None

    def stop(self, sig: signal.Signals = signal.SIGTERM) -> tuple[int, dict[str, Any]]:
        self.proc.send_signal(sig)
        status = self.proc.wait(timeout=15)
        return status, self.record(5.0)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@dataclass
class Device:
    config: CanBusConfig
    clock: ScaledClock
    stop: Callable[[], Awaitable[tuple[dict[str, int], list[list[Any]]]]]


@pytest.fixture(params=["virtual", pytest.param("vcan", marks=pytest.mark.vcan)])
async def device(request: pytest.FixtureRequest) -> AsyncIterator[Device]:
    epoch = time.time()
    clock = ScaledClock(SPEED, epoch)
    if request.param == "virtual":
        config = CanBusConfig("virtual", f"vexo-contract-{os.getpid()}-{next(_channels)}")
        exo = VirtualExosuit(config, clock, seed=1, feedback_hz=50.0,
                             heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S,
                             liveness_timeout_s=LIVENESS_TIMEOUT_S)
        await exo.open()

        async def stop_in_process() -> tuple[dict[str, int], list[list[Any]]]:
            assert await exo.close() is None
            return dict(exo.stats), [list(entry) for entry in exo.applied_log]

        try:
            yield Device(config, clock, stop_in_process)
        finally:
            await exo.close()
        return
    process = DeviceProcess([
        "--interface", "socketcan", "--channel", "vcan0", "--speed", str(SPEED),
        "--epoch", repr(epoch), "--seed", "1", "--feedback-hz", "50", "--lifetime", "120",
        "--heartbeat-timeout", str(HEARTBEAT_TIMEOUT_S),
        "--liveness-timeout", str(LIVENESS_TIMEOUT_S),
    ])
    try:
        ready = process.record(120.0)  # imports are slow inside user-mode Linux
        assert (ready["event"], ready["channel"], ready["epoch"]) == ("ready", "vcan0", epoch)
        assert ready["pid"] == process.proc.pid

        async def stop_process() -> tuple[dict[str, int], list[list[Any]]]:
            status, stopped = await asyncio.to_thread(process.stop)
            assert (status, stopped["event"], stopped["reason"]) == (0, "stopped", "SIGTERM")
            return stopped["stats"], stopped["applied"]

        yield Device(CanBusConfig("socketcan", "vcan0"), clock, stop_process)
    finally:
        process.kill()


async def statuses(sub: Subscription, n: int, timeout_s: float = 5.0) -> list[DeviceStatus]:
    return [await asyncio.wait_for(sub.get(), timeout_s) for _ in range(n)]


async def test_push_is_acked_and_applied_bit_for_bit_and_a_corrupted_one_never_is(
    device: Device,
) -> None:
    reports: list[tuple[tuple[ForceProfile, ...], float]] = []
    good = ProfileTransfer.from_forces(TABLE, 41)
    corrupt = ProfileTransfer.from_forces(TABLE[::-1], 42)
    # the listener is a node of its own, as in the virtual cart's process
    async with CanEndpoint(device.config) as ep, CanEndpoint(device.config) as cart_ep:
        ep.bridge_state = BridgeState.RUNNING
        ep.start_heartbeat()
        listener = AppliedProfileListener(cart_ep, device.clock,
                                          on_applied=lambda p, t: reports.append((p, t)))
        async with listener:
            with ep.subscribe(DeviceStatus) as sub:
                result = await ep.push_profile(TABLE, 41)
                loop = asyncio.get_running_loop()
                deadline = loop.time() + 10.0
                while not reports and loop.time() < deadline:
                    await asyncio.wait_for(sub.get(), 5.0)
            with ep.subscribe(ProfileAck) as acks:
                for frame in corrupt.frames()[:-1]:
                    await ep.send(frame)
                await ep.send(ProfileCommit(42, 101, corrupt.crc32 ^ 0xFFFF))
                nack = await asyncio.wait_for(acks.get(), 5.0)
            await device.clock.sleep(2.5)  # more than two strides
            with ep.subscribe(DeviceStatus) as sub:
                latest = await statuses(sub, 4)
        stats, applied = await device.stop()
        bridge_counters = dict(ep.counters)
    assert (result.version, result.attempts) == (41, 1)
    assert nack == ProfileAck.nack(42, NackReason.BAD_CRC)
    assert all((s.mode, s.profile_version_active, s.profile_version_pending)
               == (DeviceMode.ASSIST, 41, 0) for s in latest), (latest, stats, bridge_counters)
    # the listener rebuilt the applied table from the bus, bit for bit, once
    ((profiles, t_heard),) = reports
    assert [p.actuator for p in profiles] == ["hip"]
    assert forces_to_raw(profiles[0].force_n) == good.forces_raw
    assert listener.reports == [(41, t_heard)]
    # ...at about the gait boundary where the device switched (it backdates by the gait phase)
    ((version, t_switched),) = applied
    assert version == 41
    # Late by at most a status period plus this process's scheduling delay, which inside
    # user-mode Linux beside a CPU burner reached 0.23 s of wall time (0.46 s at SPEED 2);
    # without the backdating it would be late by up to a whole stride.
    assert -0.05 < t_heard - t_switched < 0.8
    assert (stats["acks"], stats["nack_bad_crc"], stats["switches"]) == (1, 1, 2)


# --- the command line (host only) ------------------------------------------------------------------


def test_parser_registers_the_subcommand_with_its_options() -> None:
    parser = argparse.ArgumentParser(prog="hilbo")
    add_virtual_exosuit_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args([
        "virtual-exosuit", "--interface", "virtual", "--channel", "demo", "--speed", "10",
        "--fault", "nack-busy@5x2", "--fault", "drop-status@9+1", "--max-force-n", "300",
        "--suit", "hip_ankle_4d",
    ])
    assert args.func is run
    assert (args.interface, args.channel, args.speed, args.max_force_n) == ("virtual", "demo",
                                                                           "10", 300.0)
    assert args.fault == ["nack-busy@5x2", "drop-status@9+1"]
    assert args.suit == "hip_ankle_4d"


@pytest.mark.parametrize("argv, message", [
    (["--speed", "max"], "cannot be shared"),
    (["--speed", "-1"], "speed"),
    (["--fault", "sparks@1"], "no fault 'sparks'"),
    (["--fault", "bus-off@3"], "lasts a while"),
    (["--max-force-n", "0"], "max_force_n"),
    (["--interface", "nonsense"], "can.interface"),
])
def test_bad_options_exit_2_with_the_reason(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--interface", "virtual", "--channel", "unused", *argv]) == 2
    out = capsys.readouterr()
    assert message in out.err and out.out == ""


def test_process_prints_ready_then_stops_cleanly_on_sigint() -> None:
    process = DeviceProcess(["--interface", "virtual", "--channel", "alone", "--feedback-hz", "100",
                             "--fault", "garbage@0x3", "--lifetime", "60"])
    try:
        ready = process.record(60.0)
        assert (ready["event"], ready["faults"], ready["joints"]) == (
            "ready", ["garbage@0x3"], ["hip", "hip"])
        time.sleep(0.3)  # a real device process runs on wall time: let it send >10 statuses
        t0 = time.monotonic()
        status, stopped = process.stop(signal.SIGINT)
        assert time.monotonic() - t0 < 6.0
    finally:
        process.kill()
    assert (status, stopped["event"], stopped["reason"]) == (0, "stopped", "SIGINT")
    assert stopped["stats"]["status_sent"] > 10 and stopped["stats"]["malformed_sent"] == 3
