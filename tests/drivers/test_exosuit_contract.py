"""One contract for the profile push, heartbeat and assistance-off, over every transport.

* ``virtual``: python-can's in-process virtual bus.
* ``slcan-pty``: the endpoint opens a pseudo-terminal with python-can's ``slcan`` interface, as it
  would a USB adapter; a scaffold slcan peer bridges it to a virtual channel (slcan_peer.py).
* ``remote``: across processes through a python-can-remote server (``python -m can_remote
  --interface=virtual``), the path for a Windows or macOS PC running the virtual demo.
* ``socketcan-vcan0`` (marked ``vcan``): SocketCAN vcan0, natively or inside user-mode Linux.

The device side is the test scaffold responder (exosuit_responder.py).
"""

from __future__ import annotations

import asyncio
import itertools
import os
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from contextlib import ExitStack

import numpy as np
import pytest
from exosuit_responder import Behaviour, Responder
from slcan_peer import SlcanPtyPeer

from drivers.errors import ProfilePushError
from drivers.exosuit.codec import (
    AssistanceOffReason,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    NackReason,
    ProfileAck,
    ProfileCommit,
)
from drivers.exosuit.endpoint import DEFAULT_PACE_S, CanBusConfig, CanEndpoint, ProfileNackError
from drivers.exosuit.profile import ProfileTransfer

_channels = itertools.count()
TABLE = np.concatenate([np.linspace(0, 220, 41), np.linspace(220, 0, 30), np.zeros(30)])


@pytest.fixture(scope="module")
def remote_server() -> Iterator[str]:
    """A python-can-remote server on loopback, serving one virtual channel; yields its URL."""
    pytest.importorskip("can_remote", reason="python-can-remote (a dev extra) is not installed")
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, "-m", "can_remote", "--interface", "virtual", "--channel", "hilbo",
         "--host", "127.0.0.1", "--port", str(port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 20.0
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError as err:
                if server.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(
                        f"can_remote server did not start (rc {server.poll()})"
                    ) from err
                time.sleep(0.05)  # a real server process starting: bounded poll of its port
        yield f"ws://127.0.0.1:{port}/"
    finally:
        server.kill()
        server.wait()


@pytest.fixture(
    params=[
        "virtual",
        "slcan-pty",
        "remote",
        pytest.param("socketcan-vcan0", marks=pytest.mark.vcan),
    ]
)
def link(request: pytest.FixtureRequest) -> Iterator[tuple[CanBusConfig, CanBusConfig]]:
    """(bridge-side config, device-side config) of one transport."""
    channel = f"hilbo-contract-{os.getpid()}-{next(_channels)}"
    with ExitStack() as stack:
        if request.param == "virtual":
            yield CanBusConfig("virtual", channel), CanBusConfig("virtual", channel)
        elif request.param == "remote":
            url = request.getfixturevalue("remote_server")
            yield CanBusConfig("remote", url), CanBusConfig("remote", url)
        elif request.param == "slcan-pty":
            peer = stack.enter_context(SlcanPtyPeer(channel))
            yield (
                CanBusConfig("slcan", peer.path, options={"sleep_after_open": 0}),
                CanBusConfig("virtual", channel),
            )
        else:
            yield CanBusConfig("socketcan", "vcan0"), CanBusConfig("socketcan", "vcan0")


class Rig:
    def __init__(self, endpoint: CanEndpoint, responder: Responder, device: CanEndpoint) -> None:
        self.endpoint = endpoint
        self.responder = responder
        self.device = device


async def _rig(link: tuple[CanBusConfig, CanBusConfig], behaviour: Behaviour) -> AsyncIterator[Rig]:
    bridge_cfg, device_cfg = link
    responder = Responder(behaviour)
    async with CanEndpoint(device_cfg) as device, CanEndpoint(bridge_cfg) as endpoint:
        sub = device.subscribe()

        async def serve() -> None:
            async for message in sub:
                await responder.handle(device, message)

        task = asyncio.create_task(serve())
        try:
            yield Rig(endpoint, responder, device)
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task


@pytest.fixture
async def rig(link: tuple[CanBusConfig, CanBusConfig]) -> AsyncIterator[Rig]:
    async for r in _rig(link, Behaviour()):
        yield r


async def test_101_point_profile_pushes_commits_and_acks(rig: Rig) -> None:
    result = await rig.endpoint.push_profile(TABLE, 17)
    expected = ProfileTransfer.from_forces(TABLE, 17)
    assert (result.version, result.n_points, result.attempts) == (17, 101, 1)
    assert result.crc32 == expected.crc32
    assert rig.responder.seen.acked == [(17, expected.forces_n)]
    # Paced: the commit goes 34 paces after the first segment (1 ms each by default, ≈ 34 ms);
    # the upper bound is only a sanity bound (a busy machine may take longer than the pacing).
    assert 34 * DEFAULT_PACE_S - 0.001 < result.elapsed_s < 20.0


async def test_corrupted_transfer_is_nacked_bad_crc(rig: Rig) -> None:
    transfer = ProfileTransfer.from_forces(TABLE, 18)
    with rig.endpoint.subscribe(ProfileAck) as acks:
        for segment in transfer.segments():
            await rig.endpoint.send(segment)
        await rig.endpoint.send(ProfileCommit(18, 101, transfer.crc32 ^ 0x0100))
        ack = await asyncio.wait_for(acks.get(), 2.0)
    assert ack == ProfileAck.nack(18, NackReason.BAD_CRC)
    assert rig.responder.seen.acked == []


@pytest.mark.parametrize(
    ("behaviour", "nacks", "timeouts"),
    [
        (Behaviour(corrupt_first=1), (NackReason.BAD_CRC,), 0),
        (Behaviour(drop_first=2), (NackReason.MISSING_SEGMENT,) * 2, 0),
        (Behaviour(silent_first=1), (), 1),
    ],
    ids=["bad-crc", "missing-segment", "lost-ack"],
)
async def test_push_retries_transient_failures(
    link: tuple[CanBusConfig, CanBusConfig], behaviour: Behaviour,
    nacks: tuple[NackReason, ...], timeouts: int,
) -> None:
    async for rig in _rig(link, behaviour):
        # The ack timeout is the point only where an ack is lost; elsewhere a generous one, so an
        # ack that a busy machine delays is not counted as a timeout (an extra attempt).
        result = await rig.endpoint.push_profile(TABLE, 19, timeout_s=1.0 if timeouts else 10.0,
                                                 pace_s=0.0005)
        assert result.attempts == len(nacks) + timeouts + 1
        assert (result.nacks, result.timeouts) == (nacks, timeouts)
        assert [v for v, _ in rig.responder.seen.acked] == [19]


async def test_push_gives_up_after_bounded_retries(link: tuple[CanBusConfig, CanBusConfig]) -> None:
    async for rig in _rig(link, Behaviour(silent_first=100)):
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(ProfilePushError, match="no ack after 3 attempt"):
            await rig.endpoint.push_profile(TABLE, 20, timeout_s=0.1, retries=2, pace_s=0)
        assert 0.3 <= loop.time() - t0 < 20.0  # three timeouts at least; the rest is scheduling
        # The third commit was sent 0.1 s before the push gave up; on a busy host (user-mode
        # Linux beside a burner) the responder may not have read it yet: a bounded poll.
        deadline = loop.time() + 5.0
        while rig.responder.seen.commits < 3 and loop.time() < deadline:
            await asyncio.sleep(0.01)
        assert rig.responder.seen.commits == 3


async def test_out_of_limits_is_not_retried(link: tuple[CanBusConfig, CanBusConfig]) -> None:
    async for rig in _rig(link, Behaviour(max_force_n=200.0)):
        with pytest.raises(ProfileNackError) as info:
            await rig.endpoint.push_profile(TABLE, 21, pace_s=0, timeout_s=10.0)  # a late nack is no timeout
        assert (info.value.reason, info.value.attempts) == (NackReason.OUT_OF_LIMITS, 1)
        assert info.value.detail == int(np.argmax(TABLE > 200.0))
        assert rig.responder.seen.commits == 1


async def test_heartbeat_status_and_assistance_off_cross_the_link(rig: Rig) -> None:
    ep = rig.endpoint
    statuses = ep.subscribe(DeviceStatus)
    ep.bridge_state = BridgeState.RUNNING
    ep.start_heartbeat(period_s=0.005)
    status = DeviceStatus(1, DeviceMode.ASSIST, DeviceFault.FORCE_LIMIT, 37.5, 17, 0, 4)
    await rig.device.send(status)
    assert await asyncio.wait_for(statuses.get(), 2.0) == status
    await ep.send_assistance_off(AssistanceOffReason.OPERATOR_STOP)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 2.0
    seen = rig.responder.seen
    while loop.time() < deadline and not (
        seen.assistance_off and seen.heartbeats and seen.heartbeats[-1][1] == BridgeState.PAUSED
    ):
        await asyncio.sleep(0.01)  # frames cross a real websocket to the server: bounded poll
    await ep.stop_heartbeat()
    assert seen.assistance_off == [AssistanceOffReason.OPERATOR_STOP]
    counters = [c for c, _ in seen.heartbeats]
    assert len(counters) >= 2
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(counters))
    assert seen.heartbeats[0][1] == BridgeState.RUNNING
    assert seen.heartbeats[-1][1] == BridgeState.PAUSED
