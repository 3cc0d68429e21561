"""Profile transfer: segmentation, the CRC-32 byte encoding, the device-side assembler."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.exosuit.codec import EncodeError, NackReason, ProfileCommit, ProfileSegment
from drivers.exosuit.profile import (
    MAX_PROFILE_POINTS,
    ProfileAssembler,
    ProfileTransfer,
    forces_to_raw,
    pack_tables,
    profile_crc32,
    segment_count,
    table_order,
    unpack_tables,
)


def crc32_reference(data: bytes) -> int:
    """Bit-by-bit CRC-32 (IEEE 802.3, reflected 0xEDB88320), independent of zlib."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_reference_crc_has_the_standard_check_value() -> None:
    assert crc32_reference(b"123456789") == 0xCBF43926


def test_crc_is_over_uint16_little_endian_counts() -> None:
    # 0.0, 0.1, 0.2, 25.6 N -> counts 0, 1, 2, 256 -> bytes 00 00 01 00 02 00 00 01
    raw = forces_to_raw([0.0, 0.1, 0.2, 25.6])
    assert raw == (0, 1, 2, 256)
    assert profile_crc32(raw) == crc32_reference(bytes.fromhex("0000010002000001"))


def test_crc_equals_crc_of_segment_force_bytes() -> None:
    rng = np.random.default_rng(4)
    transfer = ProfileTransfer.from_forces(rng.uniform(0, 300, 101), 9)
    payload = b"".join(bytes(s.to_frame().data)[2:] for s in transfer.segments())
    assert transfer.crc32 == crc32_reference(payload[: 2 * 101])
    assert transfer.commit() == ProfileCommit(9, 101, transfer.crc32)


def test_101_points_make_34_segments_and_a_commit() -> None:
    forces = np.linspace(0.0, 200.0, 101)  # 2 N steps
    transfer = ProfileTransfer.from_forces(forces, 3)
    segments = transfer.segments()
    assert segment_count(101) == len(segments) == 34
    assert [s.index for s in segments] == list(range(34))
    assert segments[0] == ProfileSegment(3, 0, (0.0, 2.0, 4.0))
    assert segments[-1] == ProfileSegment(3, 33, (198.0, 200.0, 0.0))  # one point + padding
    frames = transfer.frames()
    assert len(frames) == 35
    assert frames[-1].arbitration_id == 0x7B0
    assert transfer.forces_n == pytest.approx(forces, abs=0.05)


def test_numpy_integer_versions_are_accepted() -> None:
    transfer = ProfileTransfer.from_forces([1.0, 2.0], np.int64(7))  # type: ignore[arg-type]
    assert transfer.version == 7 and type(transfer.version) is int


def test_quantisation_is_to_the_nearest_tenth_newton() -> None:
    assert forces_to_raw([12.34, 12.36, 0.04, 6553.5]) == (123, 124, 0, 65535)


@pytest.mark.parametrize(
    ("forces", "version", "match"),
    [
        ([1.0, math.nan, 2.0], 1, "point 1"),
        ([1.0, math.inf], 1, "point 1"),
        ([-0.1, 1.0], 1, "point 0"),
        ([1.0, 6553.6], 1, "point 1"),
        ([1.0], 1, "1 points"),
        ([1.0] * (MAX_PROFILE_POINTS + 1), 1, "769 points"),
        ([1.0, 2.0], 0, "version"),
        ([1.0, 2.0], 256, "version"),
        ([1.0, 2.0], True, "version"),
        ([1.0, 2.0], 2.0, "version"),
    ],
)
def test_bad_tables_are_refused_before_anything_is_sent(
    forces: list[float], version: int, match: str
) -> None:
    with pytest.raises(EncodeError, match=match):
        ProfileTransfer.from_forces(forces, version)


def feed(assembler: ProfileAssembler, transfer: ProfileTransfer, skip: tuple[int, ...] = ()) -> None:
    for segment in transfer.segments():
        if segment.index not in skip:
            assembler.on_segment(segment)


def test_assembler_acks_a_good_table_in_any_segment_order() -> None:
    transfer = ProfileTransfer.from_forces(np.linspace(0, 250, 101), 5)
    assembler = ProfileAssembler(max_force_n=300.0)
    for segment in reversed(transfer.segments()):
        assembler.on_segment(segment)
    ack, table = assembler.on_commit(transfer.commit())
    assert ack.accepted and ack.version == 5
    assert table == transfer.forces_n
    again, table2 = assembler.on_commit(transfer.commit())  # lost ack: the retry is acked too
    assert again.accepted and table2 == table


@pytest.mark.parametrize(
    ("setup", "reason", "detail"),
    [
        (lambda a, t: (feed(a, t, skip=(7,)), t.commit()), NackReason.MISSING_SEGMENT, 7),
        (lambda a, t: (feed(a, t), ProfileCommit(5, 101, t.crc32 ^ 0x80)), NackReason.BAD_CRC, 0),
        (lambda a, t: (feed(a, t), ProfileCommit(5, 100, t.crc32)), NackReason.BAD_CRC, 0),
        (lambda a, t: (feed(a, t), ProfileCommit(5, 104, t.crc32)), NackReason.MISSING_SEGMENT, 34),
        (lambda a, t: (feed(a, t), ProfileCommit(6, 101, t.crc32)), NackReason.MISSING_SEGMENT, 0),
        (lambda a, t: (feed(a, t), ProfileCommit(0, 101, t.crc32)), NackReason.BAD_VERSION, 0),
    ],
)
def test_assembler_nacks_with_reason_and_detail(setup: object, reason: NackReason, detail: int) -> None:
    transfer = ProfileTransfer.from_forces(np.linspace(0, 250, 101), 5)
    assembler = ProfileAssembler(max_force_n=300.0)
    _, commit = setup(assembler, transfer)  # type: ignore[operator]
    ack, table = assembler.on_commit(commit)
    assert (ack.accepted, ack.reason, ack.detail, table) == (False, reason, detail, None)


def test_assembler_limits_length_force_and_step() -> None:
    table = [0.0] * 50 + [150.0] + [0.0] * 50
    transfer = ProfileTransfer.from_forces(table, 8)
    short = ProfileAssembler(max_force_n=300.0, max_points=51)
    feed(short, transfer)
    ack = short.on_commit(transfer.commit())[0]
    assert (ack.reason, ack.detail) == (NackReason.BAD_LENGTH, 51)
    weak = ProfileAssembler(max_force_n=100.0)
    feed(weak, transfer)
    ack = weak.on_commit(transfer.commit())[0]
    assert (ack.reason, ack.detail) == (NackReason.OUT_OF_LIMITS, 50)
    steep = ProfileAssembler(max_force_n=300.0, max_step_n=100.0)
    feed(steep, transfer)
    ack = steep.on_commit(transfer.commit())[0]
    assert (ack.reason, ack.detail) == (NackReason.OUT_OF_LIMITS, 50)
    smooth = ProfileAssembler(max_force_n=300.0, max_step_n=150.0)
    feed(smooth, transfer)
    assert smooth.on_commit(transfer.commit())[0].accepted


def test_busy_device_nacks_busy_and_a_new_version_restarts_the_buffer() -> None:
    old = ProfileTransfer.from_forces([10.0] * 10, 1)
    new = ProfileTransfer.from_forces([20.0] * 10, 2)
    assembler = ProfileAssembler(max_force_n=300.0)
    feed(assembler, old)
    assembler.busy = True
    assert assembler.on_commit(old.commit())[0].reason == NackReason.BUSY
    assembler.busy = False
    assembler.on_segment(new.segments()[0])  # a segment of v2 drops the v1 buffer
    assert assembler.receiving_version == 2
    assert assembler.on_commit(old.commit())[0].reason == NackReason.MISSING_SEGMENT
    feed(assembler, new)
    assert assembler.on_commit(new.commit())[1] == (20.0,) * 10


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(0, 0xFFFF), min_size=2, max_size=MAX_PROFILE_POINTS),
    st.integers(1, 255),
)
def test_any_table_survives_segmenting_and_reassembly(raw: list[int], version: int) -> None:
    transfer = ProfileTransfer(version, tuple(raw))
    assembler = ProfileAssembler(max_force_n=6553.5)
    *segments, commit = transfer.frames()
    for f in segments:
        assembler.on_segment(ProfileSegment.from_frame(f))
    ack, table = assembler.on_commit(ProfileCommit.from_frame(commit))
    assert ack.accepted
    assert forces_to_raw(table) == tuple(raw)  # type: ignore[arg-type]


# --- multi-actuator table layout ---------------------------------------------------------------


def test_table_order_is_the_first_appearance_of_each_joint() -> None:
    assert table_order(("hip", "hip")) == ("hip",)
    assert table_order(("hip", "ankle")) == ("hip", "ankle")
    assert table_order(["ankle", "hip", "ankle"]) == ("ankle", "hip")
    for bad in [(), ("hip", ""), ("hip", 3)]:
        with pytest.raises(EncodeError, match="joint"):
            table_order(bad)  # type: ignore[arg-type]


def test_golden_layout_tables_are_concatenated_in_order() -> None:
    packed = pack_tables([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    assert packed.shape == (6,) and packed.dtype == np.float64
    assert packed.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert [t.tolist() for t in unpack_tables(packed, 2)] == [[1, 2, 3], [4, 5, 6]]
    assert [t.tolist() for t in unpack_tables(packed, 1)] == [[1, 2, 3, 4, 5, 6]]


def test_golden_layout_on_the_wire_hip_then_ankle_101_points_each() -> None:
    # Point j of table i is point i*m + j: the ankle's 0 %GC (point 101) is the third force of
    # segment 33, after the hip's 100 %GC (points 99, 100).
    hip = np.linspace(0.0, 100.0, 101)
    ankle = np.linspace(200.0, 300.0, 101)
    transfer = ProfileTransfer.from_forces(pack_tables([hip, ankle]), 5)
    segments = transfer.segments()
    assert (transfer.n_points, len(segments)) == (202, 68)
    assert segments[0].forces_n == (0.0, 1.0, 2.0)
    assert segments[33].forces_n == (99.0, 100.0, 200.0)
    assert segments[34].forces_n == (201.0, 202.0, 203.0)
    assert segments[66].forces_n == (297.0, 298.0, 299.0)
    assert segments[67].forces_n == (300.0, 0.0, 0.0)  # 202 = 67*3 + 1: two padding points
    # The device side (raw counts, as received) splits it back, bit for bit.
    hip_raw, ankle_raw = unpack_tables(np.asarray(transfer.forces_raw), 2)
    assert tuple(hip_raw.tolist()) == forces_to_raw(hip)
    assert tuple(ankle_raw.tolist()) == forces_to_raw(ankle)
    assert hip_raw.dtype.kind == "i"


@pytest.mark.parametrize(
    ("tables", "match"),
    [
        ([], "at least one table"),
        ([[1.0, 2.0], [1.0, 2.0, 3.0]], "expected one length"),
        ([[1.0]], ">= 2 points"),
        ([np.zeros(385), np.zeros(385)], "<= 768 in all"),
        ([np.zeros((2, 3))], "shape"),
        (np.zeros(4), "sequence of tables"),
    ],
)
def test_pack_rejects_tables_that_do_not_fit_the_layout(tables: object, match: str) -> None:
    with pytest.raises(EncodeError, match=match):
        pack_tables(tables)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("n", "k", "match"),
    [(7, 2, "7 points does not split into 2"), (2, 2, "does not split"), (6, 0, "n_tables"),
     (6, True, "n_tables")],
)
def test_unpack_rejects_a_table_that_does_not_split(n: int, k: int, match: str) -> None:
    with pytest.raises(EncodeError, match=match):
        unpack_tables(np.zeros(n), k)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 4).flatmap(
        lambda k: st.integers(2, MAX_PROFILE_POINTS // k).flatmap(
            lambda m: st.lists(
                st.lists(st.floats(0.0, 6553.5, allow_nan=False), min_size=m, max_size=m),
                min_size=k, max_size=k,
            )
        )
    )
)
def test_pack_unpack_round_trip(tables: list[list[float]]) -> None:
    packed = pack_tables(tables)
    assert packed.shape == (len(tables) * len(tables[0]),)
    back = unpack_tables(packed, len(tables))
    assert [t.tolist() for t in back] == tables
    np.testing.assert_array_equal(pack_tables(back), packed)
    # ...and through the wire: the device's split of the transfer is the quantised tables.
    transfer = ProfileTransfer.from_forces(packed, 1)
    raw_parts = unpack_tables(np.asarray(transfer.forces_raw), len(tables))
    assert [tuple(p.tolist()) for p in raw_parts] == [forces_to_raw(t) for t in tables]
