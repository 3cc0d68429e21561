"""push_profile's ``permit`` hook: the bridge can stop a push before its first segment or before
its commit, and then no commit is on the bus (checked against a transcript of every frame)."""

from __future__ import annotations

import asyncio
import itertools
import os
from collections.abc import Callable, Iterator

import can
import numpy as np
import pytest

from drivers.errors import DriverConfigError, DriverError, ProfilePushAborted
from drivers.exosuit.codec import ProfileAck, ProfileCommit, ProfileSegment, decode_frame, frame_id
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, PushStage

_channels = itertools.count()
TABLE = np.concatenate([np.linspace(0, 220, 41), np.linspace(220, 0, 30), np.zeros(30)])
N_SEGMENTS = 34  # ceil(101 / 3)
COMMIT_ID = frame_id("ProfileCommit")


@pytest.fixture
def channel() -> str:
    return f"hilbo-permit-{os.getpid()}-{next(_channels)}"


@pytest.fixture
def tap(channel: str) -> Iterator[can.BusABC]:
    """A raw node on the bus that only listens: every frame the bridge sends lands in its queue."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def transcript(bus: can.BusABC) -> list[object]:
    """Every frame queued at ``bus`` so far, decoded (the virtual bus queues per receiver)."""
    out = []
    while (frame := bus.recv(timeout=0)) is not None:
        out.append(decode_frame(frame))
    return out


class Permit:
    """Records every question; refuses from the ``refuse_at``-th one (0-based) on."""

    def __init__(self, refuse_at: int | None = None) -> None:
        self.refuse_at = refuse_at
        self.asked: list[str] = []

    def __call__(self, stage: str) -> bool:
        self.asked.append(stage)
        return self.refuse_at is None or len(self.asked) <= self.refuse_at


async def acking_device(bus: can.BusABC) -> None:
    """Acks every commit it sees (a minimal device on a raw bus)."""
    while True:
        frame = await asyncio.to_thread(bus.recv, 0.05)
        if frame is not None and frame.arbitration_id == COMMIT_ID:
            bus.send(ProfileAck.ack(ProfileCommit.from_frame(frame).version).to_frame())


async def test_permit_is_asked_before_the_first_segment_and_before_the_commit(
    channel: str, tap: can.BusABC
) -> None:
    device_bus = can.Bus(interface="virtual", channel=channel)
    device = asyncio.create_task(acking_device(device_bus))
    try:
        async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
            permit = Permit()
            result = await ep.push_profile(TABLE, 7, pace_s=0, permit=permit)
    finally:
        device.cancel()
        with pytest.raises(asyncio.CancelledError):
            await device
        device_bus.shutdown()
    assert (result.version, result.attempts) == (7, 1)
    assert permit.asked == [PushStage.FIRST_SEGMENT, PushStage.COMMIT]
    assert permit.asked == ["first_segment", "commit"]  # plain strings for the callable
    sent = [m for m in transcript(tap) if not isinstance(m, ProfileAck)]
    assert [type(m) for m in sent] == [ProfileSegment] * N_SEGMENTS + [ProfileCommit]


async def test_refused_commit_sends_every_segment_but_no_commit(channel: str, tap: can.BusABC) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        permit = Permit(refuse_at=1)
        with pytest.raises(ProfilePushAborted) as aborted:
            await ep.push_profile(TABLE, 8, pace_s=0.0005, permit=permit)
    assert isinstance(aborted.value, DriverError)
    assert (aborted.value.version, aborted.value.stage, aborted.value.attempt,
            aborted.value.commits_sent) == (8, "commit", 1, 0)
    assert "commit" in str(aborted.value)
    frames = transcript(tap)
    assert [type(m) for m in frames] == [ProfileSegment] * N_SEGMENTS
    assert [m.index for m in frames] == list(range(N_SEGMENTS))  # type: ignore[attr-defined]


async def test_refused_first_segment_sends_nothing(channel: str, tap: can.BusABC) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        permit = Permit(refuse_at=0)
        with pytest.raises(ProfilePushAborted) as aborted:
            await ep.push_profile(TABLE, 9, permit=permit)
    assert (aborted.value.stage, aborted.value.attempt, aborted.value.commits_sent) == (
        "first_segment", 1, 0)
    assert permit.asked == ["first_segment"]
    assert transcript(tap) == []


async def test_a_pause_during_the_segments_stops_the_commit(channel: str, tap: can.BusABC) -> None:
    paused = asyncio.Event()
    watcher = can.Bus(interface="virtual", channel=channel)  # the operator's view of the bus

    async def operator() -> None:  # presses pause once five segments are out
        seen = 0
        while seen < 5:
            if await asyncio.to_thread(watcher.recv, 0.5) is not None:
                seen += 1
        paused.set()

    def permit(stage: str) -> bool:
        return not paused.is_set()

    try:
        async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
            press = asyncio.create_task(operator())
            with pytest.raises(ProfilePushAborted) as aborted:
                await ep.push_profile(TABLE, 10, pace_s=0.002, permit=permit)
            await press
    finally:
        watcher.shutdown()
    frames = transcript(tap)
    assert aborted.value.stage == "commit"
    assert 5 <= len(frames) <= N_SEGMENTS
    assert all(isinstance(m, ProfileSegment) for m in frames)


async def test_a_refused_retry_reports_the_commit_already_on_the_bus(
    channel: str, tap: can.BusABC
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:  # no device: no ack
        permit = Permit(refuse_at=2)  # first_segment, commit of attempt 1; refuse attempt 2
        with pytest.raises(ProfilePushAborted) as aborted:
            await ep.push_profile(TABLE, 11, pace_s=0, timeout_s=0.02, permit=permit)
    assert (aborted.value.stage, aborted.value.attempt, aborted.value.commits_sent) == (
        "first_segment", 2, 1)
    assert permit.asked == ["first_segment", "commit", "first_segment"]
    frames = transcript(tap)
    assert [type(m) for m in frames] == [ProfileSegment] * N_SEGMENTS + [ProfileCommit]


async def test_the_push_lock_is_released_after_an_abort_and_permit_errors_propagate(
    channel: str, tap: can.BusABC
) -> None:
    class Boom(Exception):
        pass

    def explode(stage: str) -> bool:
        raise Boom(stage)

    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        with pytest.raises(ProfilePushAborted):
            await ep.push_profile(TABLE, 12, permit=lambda stage: False)
        with pytest.raises(Boom, match="first_segment"):
            await ep.push_profile(TABLE, 12, permit=explode)
        with pytest.raises(DriverConfigError, match="permit must be a callable"):
            await ep.push_profile(TABLE, 12, permit=True)  # type: ignore[arg-type]
        with pytest.raises(ProfilePushAborted):  # the lock was released each time
            await asyncio.wait_for(ep.push_profile(TABLE, 12, permit=Permit(refuse_at=1),
                                                   pace_s=0), 2.0)
    assert not any(isinstance(m, ProfileCommit) for m in transcript(tap))


class CommitQueueFull(can.BusABC):
    """A virtual bus whose transmit queue is full the first time a commit is sent."""

    def __init__(self, channel: str, on_full: Callable[[], None]) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self._on_full = on_full
        self._full_once = True
        self.channel_info = "queue-full"
        super().__init__(channel=channel)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == COMMIT_ID and self._full_once:
            self._full_once = False
            self._on_full()
            raise can.CanOperationError("Transmit buffer full")
        self._inner.send(msg, timeout)

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()


async def test_permit_is_asked_again_before_a_transmit_retry_of_the_commit(
    channel: str, tap: can.BusABC
) -> None:
    paused = False

    def pause() -> None:  # the operator presses pause while the commit waits for the queue
        nonlocal paused
        paused = True

    asked: list[str] = []

    def permit(stage: str) -> bool:
        asked.append(stage)
        return not paused

    ep = CanEndpoint(CanBusConfig("virtual", channel),
                     bus_factory=lambda **kw: CommitQueueFull(channel, pause))
    async with ep:
        with pytest.raises(ProfilePushAborted) as aborted:
            await ep.push_profile(TABLE, 13, pace_s=0, permit=permit)
    assert aborted.value.stage == "commit"
    assert asked == ["first_segment", "commit", "commit"]
    assert ep.counters["send_retry"] == 1
    assert [type(m) for m in transcript(tap)] == [ProfileSegment] * N_SEGMENTS
