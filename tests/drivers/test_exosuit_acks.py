"""push_profile's answer accounting: an ack before its commit is rejected, and repeated or stale
answers are counted (``ack_before_commit``, ``ack_repeated``, ``ack_stale``), against the
scripted responder (exosuit_responder.py) on python-can ``virtual``."""

from __future__ import annotations

import asyncio
import itertools
import os
from collections.abc import AsyncIterator

import numpy as np
import pytest
from exosuit_responder import Behaviour, Responder
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.exosuit.codec import ProfileAck, ProfileCommit
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint

_channels = itertools.count()
TABLE = np.concatenate([np.linspace(0, 220, 41), np.linspace(220, 0, 30), np.zeros(30)])
ACK_COUNTERS = ("ack_before_commit", "ack_repeated", "ack_stale")


class Rig:
    def __init__(self, bridge: CanEndpoint, listener: CanEndpoint, responder: Responder) -> None:
        self.bridge = bridge
        self.listener = listener  # a third node that sees the answers but never pushes
        self.responder = responder

    def ack_counts(self, endpoint: CanEndpoint | None = None) -> dict[str, int]:
        counters = (endpoint or self.bridge).counters
        return {k: counters[k] for k in ACK_COUNTERS if k in counters}


async def rig(behaviour: Behaviour, responder: Responder | None = None) -> AsyncIterator[Rig]:
    config = CanBusConfig("virtual", f"hilbo-acks-{os.getpid()}-{next(_channels)}")
    responder = responder or Responder(behaviour)
    async with CanEndpoint(config) as device, CanEndpoint(config) as bridge, \
            CanEndpoint(config) as listener:
        sub = device.subscribe()

        async def serve() -> None:
            async for message in sub:
                await responder.handle(device, message)

        task = asyncio.create_task(serve())
        try:
            yield Rig(bridge, listener, responder)
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task


async def settle(endpoint: CanEndpoint, n_acks: int, timeout_s: float = 2.0) -> None:
    """Wait until ``endpoint`` has received ``n_acks`` ProfileAck frames."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while endpoint.received.get("ProfileAck", 0) < n_acks:
        assert loop.time() < deadline, f"only {endpoint.received.get('ProfileAck', 0)} acks"
        await asyncio.sleep(0.005)  # acks cross python-can's bus thread: bounded poll


async def test_an_ack_before_the_commit_is_rejected_and_counted() -> None:
    # The device acks v5 on its first segment, then stays silent on the first commit: had the
    # early ack been taken, the push would have ended at once with 1 attempt.
    async for r in rig(Behaviour(early_ack_first=1, silent_first=1)):
        result = await r.bridge.push_profile(TABLE, 5, timeout_s=0.1, pace_s=0.0005)
        assert (result.attempts, result.timeouts) == (2, 1)
        assert r.ack_counts() == {"ack_before_commit": 1}
        assert [v for v, _ in r.responder.seen.acked] == [5]


async def test_early_ack_with_the_real_one_following_completes_on_the_real_one() -> None:
    async for r in rig(Behaviour(early_ack_first=1)):
        result = await r.bridge.push_profile(TABLE, 6, pace_s=0.0005)
        assert (result.attempts, result.timeouts, result.nacks) == (1, 0, ())
        await settle(r.bridge, 2)
        assert r.ack_counts() == {"ack_before_commit": 1}


async def test_a_second_ack_of_the_same_commit_is_counted_repeated() -> None:
    async for r in rig(Behaviour(duplicate_acks=2)):
        await r.bridge.push_profile(TABLE, 7, pace_s=0)
        await settle(r.bridge, 3)  # (a duplicate of v7 arriving during the push of v8 is stale)
        await r.bridge.push_profile(TABLE, 8, pace_s=0)
        await settle(r.bridge, 6)
        await settle(r.listener, 6)
        assert r.ack_counts() == {"ack_repeated": 4}
        assert r.ack_counts(r.listener) == {}  # a node that never pushed judges nothing


async def test_an_ack_of_an_older_version_is_counted_stale() -> None:
    async for r in rig(Behaviour(stale_ack=True)):
        result = await r.bridge.push_profile(TABLE, 1, pace_s=0)  # stale answer: v255
        assert result.attempts == 1
        await settle(r.bridge, 2)
        await r.bridge.push_profile(TABLE, 2, pace_s=0)  # stale answer: v1
        await settle(r.bridge, 4)
        assert r.ack_counts() == {"ack_stale": 2}


class LateFirstAnswer(Responder):
    """Answers the first commit 150 ms late (after the bridge's 100 ms timeout)."""

    def __init__(self) -> None:
        super().__init__(Behaviour())
        self.delayed: list[asyncio.Task[None]] = []

    async def handle(self, endpoint: CanEndpoint, message: object) -> None:
        if isinstance(message, ProfileCommit) and not self.delayed:
            async def later() -> None:
                # Wall (loop time): the bridge's 100 ms ack timeout is loop time by design.
                await asyncio.sleep(0.15)
                await super(LateFirstAnswer, self).handle(endpoint, message)

            self.delayed.append(asyncio.create_task(later()))
            return
        await super().handle(endpoint, message)


async def test_a_late_answer_to_a_timed_out_commit_answers_the_retry_and_nothing_is_rejected() -> None:
    # One answer per commit sent: the push of v9 sends 2 commits (the first answer is late) and
    # receives 2 answers; neither is rejected, a third one is.
    responder = LateFirstAnswer()
    async for r in rig(Behaviour(), responder):
        result = await r.bridge.push_profile(TABLE, 9, timeout_s=0.1, pace_s=0)
        await asyncio.gather(*responder.delayed)
        await settle(r.bridge, 2)
        assert result.timeouts == 1
        assert r.ack_counts() == {}
        await r.listener.send(ProfileAck.ack(9))  # a third answer for two commits
        await settle(r.bridge, 3)
        assert r.ack_counts() == {"ack_repeated": 1}


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(
    st.tuples(st.just("push"), st.integers(1, 3)),
    st.tuples(st.just("commit"), st.just(0)),
    st.tuples(st.just("ack"), st.integers(1, 3)),
), max_size=40))
def test_every_answer_is_accepted_once_per_commit_or_counted(events: list[tuple[str, int]]) -> None:
    ep = CanEndpoint(CanBusConfig("virtual", "unused"))  # the accounting needs no open bus
    version: int | None = None
    commits = accepted = judged = total_accepted = 0
    for kind, value in events:
        if kind == "push":  # what push_profile does when it starts
            version, commits, accepted = value, 0, 0
            ep._ack_version, ep._ack_commits, ep._ack_answers = value, 0, 0
        elif kind == "commit" and version is not None:
            commits += 1
            ep._ack_commits += 1
        elif kind == "ack":
            ok = ep._answers_push(ProfileAck.ack(value))
            judged += version is not None
            assert not ok or (value == version and accepted < commits)
            accepted += ok
            total_accepted += ok
            assert accepted <= commits
    assert total_accepted + sum(ep.counters.get(k, 0) for k in ACK_COUNTERS) == judged
