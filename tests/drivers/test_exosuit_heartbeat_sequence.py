"""The frames the bridge heartbeat's cyclic sender cycles through (PROTOCOL.md, "Heartbeats")."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.exosuit.codec import (
    HEARTBEAT_SEQUENCE_LEN,
    BridgeHeartbeat,
    BridgeState,
    EncodeError,
    heartbeat_sequence,
)


@given(st.sampled_from(BridgeState), st.integers(0, 255))
def test_every_frame_is_what_the_codec_encodes_with_counter_equal_to_its_index(
    state: BridgeState, liveness: int
) -> None:
    frames = heartbeat_sequence(state, liveness)
    assert len(frames) == HEARTBEAT_SEQUENCE_LEN == 256
    for k in (0, 1, 127, 254, 255):
        expected = BridgeHeartbeat(k, state, liveness).to_frame()
        assert frames[k].arbitration_id == expected.arbitration_id == 0x020
        assert bytes(frames[k].data) == bytes(expected.data)
        assert BridgeHeartbeat.from_frame(frames[k]) == BridgeHeartbeat(k, state, liveness)


def test_cycling_through_the_sequence_advances_the_counter_on_every_frame() -> None:
    frames = heartbeat_sequence(BridgeState.RUNNING, 3)
    counters = [BridgeHeartbeat.from_frame(frames[i % 256]).counter for i in range(250, 262)]
    assert all(b != a for a, b in itertools.pairwise(counters))
    assert counters[5:7] == [255, 0]  # wraps like a mod-256 counter


def test_a_liveness_outside_a_byte_is_refused() -> None:
    with pytest.raises(EncodeError):
        heartbeat_sequence(BridgeState.RUNNING, 256)
