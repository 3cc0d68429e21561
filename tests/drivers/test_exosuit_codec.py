"""Exosuit CAN codecs: the DBC, golden bytes, strict decoding, round trips, fuzz."""

from __future__ import annotations

import math

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import DecodeError
from drivers.exosuit.codec import (
    ASSISTANCE_OFF_ID,
    DECODE_REASONS,
    AssistanceOff,
    AssistanceOffReason,
    BridgeHeartbeat,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    EncodeError,
    ForceFeedback,
    NackReason,
    ProfileAck,
    ProfileCommit,
    ProfileSegment,
    database,
    decode_frame,
    frame_id,
)


def frame(arbitration_id: int, data: bytes | str, **kw: object) -> can.Message:
    payload = bytes.fromhex(data) if isinstance(data, str) else data
    return can.Message(arbitration_id=arbitration_id, data=payload,
                       is_extended_id=bool(kw.pop("is_extended_id", False)), **kw)


# --- the DBC ---------------------------------------------------------------------------------------


def test_identifiers_put_safety_first_and_bulk_last() -> None:
    ids = {m.name: m.frame_id for m in database().messages}
    assert ids["AssistanceOff"] == ASSISTANCE_OFF_ID == min(ids.values())
    assert ids["AssistanceOff"] < ids["BridgeHeartbeat"] < ids["ForceFeedback0"]
    assert ids["ForceFeedback1"] < ids["DeviceStatus0"] < ids["ProfileAck"]
    assert ids["ProfileSegment"] == max(ids.values())
    assert all(i <= 0x7FF for i in ids.values())  # CAN 2.0A
    assert ids["ForceFeedback1"] == ids["ForceFeedback0"] + 1
    assert ids["DeviceStatus1"] == ids["DeviceStatus0"] + 1


def test_identifiers_avoid_the_canopen_predefined_connection_set() -> None:
    free = [range(0x001, 0x080), range(0x101, 0x180), range(0x780, 0x7E0)]
    for message in database().messages:
        assert any(message.frame_id in r for r in free), message.name


def test_every_message_and_signal_is_commented() -> None:
    for message in database().messages:
        assert message.comment, message.name
        for signal in message.signals:
            assert signal.comment, f"{message.name}.{signal.name}"


def test_every_message_uses_all_its_bits() -> None:
    # No padding bits: then bytes -> message -> bytes is the identity (checked below).
    for message in database().messages:
        assert sum(s.length for s in message.signals) == 8 * message.length, message.name


@pytest.mark.parametrize(
    ("message", "signal", "enum_type"),
    [
        ("AssistanceOff", "Reason", AssistanceOffReason),
        ("BridgeHeartbeat", "State", BridgeState),
        ("DeviceStatus0", "Mode", DeviceMode),
        ("DeviceStatus1", "Mode", DeviceMode),
        ("ProfileAck", "Reason", NackReason),
    ],
)
def test_python_enums_equal_the_dbc_value_tables(message: str, signal: str, enum_type: type) -> None:
    sig = database().get_message_by_name(message).get_signal_by_name(signal)
    assert {int(k): str(v) for k, v in sig.choices.items()} == {
        int(e): e.name.lower() for e in enum_type  # type: ignore[attr-defined]
    }
    assert (sig.minimum, sig.maximum) == (min(sig.choices), max(sig.choices))


def test_fault_flags_are_the_status_bits_in_order() -> None:
    message = database().get_message_by_name("DeviceStatus0")
    faults = [s for s in message.signals if s.name.startswith("Fault")]
    assert [s.start for s in faults] == list(range(8, 16))
    assert [1 << (s.start - 8) for s in faults] == [int(f) for f in DeviceFault]


# --- golden bytes (hand-computed, little-endian) ------------------------------------------------------

GOLDEN = [
    (AssistanceOff(AssistanceOffReason.OPERATOR_STOP), 0x010, "01"),
    (AssistanceOff(AssistanceOffReason.INTERNAL_ERROR), 0x010, "06"),
    # counter, state, liveness: one byte each
    (BridgeHeartbeat(5, BridgeState.RUNNING), 0x020, "050100"),
    (BridgeHeartbeat(255, BridgeState.SHUTDOWN, 0x9A), 0x020, "ff039a"),
    # 123.4 N = 1234 = 0x04D2; -1.5 N = -15 = 0xFFF1; 42.5 % = 85 = 0x55; counter 200 = 0xC8
    (ForceFeedback(0, 123.4, -1.5, 42.5, 200), 0x110, "d204f1ff55c8"),
    (ForceFeedback(1, 0.0, 0.0, None, 0), 0x111, "00000000ff00"),
    # mode 1; faults ENCODER(bit 3)|EMERGENCY_STOP(bit 7) = 0x88; gait unknown = 0xFF
    (DeviceStatus(1, DeviceMode.ASSIST, DeviceFault.ENCODER | DeviceFault.EMERGENCY_STOP,
                  None, 3, 0, 9), 0x121, "0188ff030009"),
    (DeviceStatus(0, DeviceMode.FAULT, DeviceFault.OVERCURRENT, 100.0, 255, 7, 255),
     0x120, "0401c8ff07ff"),
    # 0.1 N = 1; 250 N = 2500 = 0x09C4; 6553.5 N = 65535
    (ProfileSegment(7, 2, (0.1, 250.0, 6553.5)), 0x7C0, "07020100c409ffff"),
    # 101 points = 0x0065; CRC 0xCBF43926
    (ProfileCommit(7, 101, 0xCBF43926), 0x7B0, "0765002639f4cb"),
    (ProfileAck.ack(7), 0x7A0, "0700000000"),
    (ProfileAck.nack(7, NackReason.MISSING_SEGMENT, 0x0102), 0x7A0, "0701040201"),
    (ProfileAck.nack(255, NackReason.BAD_VERSION), 0x7A0, "ff01060000"),
]


@pytest.mark.parametrize(("message", "arbitration_id", "data"), GOLDEN)
def test_golden_bytes(message: object, arbitration_id: int, data: str) -> None:
    f = message.to_frame()  # type: ignore[attr-defined]
    assert f.arbitration_id == arbitration_id
    assert not f.is_extended_id
    assert bytes(f.data).hex() == data
    assert decode_frame(frame(arbitration_id, data)) == message


def test_frame_id_lookup() -> None:
    assert frame_id("ProfileAck") == 0x7A0
    assert frame_id("AssistanceOff") == ASSISTANCE_OFF_ID


# --- strict decoding --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("f", "reason"),
    [
        (frame(0x7FF, "00"), "unknown_id"),
        (frame(0x011, "01"), "unknown_id"),
        (frame(0x010, "01", is_extended_id=True), "extended_id"),
        (can.Message(arbitration_id=0x020, is_remote_frame=True, dlc=3, is_extended_id=False),
         "remote_frame"),
        (can.Message(arbitration_id=0, is_error_frame=True), "error_frame"),
        (can.Message(arbitration_id=0x020, data=b"\x00" * 12, is_fd=True, is_extended_id=False),
         "fd_frame"),
        (frame(0x020, "05"), "bad_length"),  # heartbeat needs 3 bytes
        (frame(0x020, "0501"), "bad_length"),  # the version-1 heartbeat, without Liveness
        (frame(0x020, "05010000"), "bad_length"),
        (frame(0x010, ""), "bad_length"),
        (frame(0x020, "050900"), "bad_value"),  # state 9
        (frame(0x010, "00"), "bad_value"),  # reason 0 is not defined
        (frame(0x120, "0900ff000000"), "bad_value"),  # mode 9
        (frame(0x110, "00000000c900"), "bad_value"),  # gait phase 201 * 0.5 %
        (frame(0x7A0, "0700010000"), "bad_value"),  # ack with a reason
        (frame(0x7A0, "0701000000"), "bad_value"),  # nack without one
        (frame(0x7A0, "0702000000"), "bad_value"),  # result 2
        (frame(0x7B0, "00650000000000"), "bad_value"),  # version 0
        (frame(0x7B0, "07010000000000"), "bad_value"),  # 1 point
        (frame(0x7B0, "07010300000000"), "bad_value"),  # 769 points
        (frame(0x7C0, "0000000000000000"), "bad_value"),  # segment of version 0
    ],
)
def test_bad_frames_raise_decode_error_with_reason(f: can.Message, reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        decode_frame(f)
    assert info.value.reason == reason
    assert reason in DECODE_REASONS


def test_range_edges_decode_despite_inexact_scaling() -> None:
    # 32767 × 0.1 and 65535 × 0.1 are not exact in binary; both are valid extremes
    f = decode_frame(frame(0x110, "ffffff7f0000"))
    assert f.desired_force_n == pytest.approx(6553.5)  # type: ignore[union-attr]
    assert f.measured_force_n == pytest.approx(3276.7)  # type: ignore[union-attr]
    assert decode_frame(frame(0x110, "000000800000")).measured_force_n == pytest.approx(-3276.8)  # type: ignore[union-attr]


def test_gait_phase_sentinel_and_edges() -> None:
    assert decode_frame(frame(0x110, "00000000ff00")).gait_phase_pct is None  # type: ignore[union-attr]
    assert decode_frame(frame(0x110, "00000000c800")).gait_phase_pct == 100.0  # type: ignore[union-attr]
    assert decode_frame(frame(0x110, "000000000000")).gait_phase_pct == 0.0  # type: ignore[union-attr]


# --- strict encoding ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [
        lambda: ForceFeedback(0, math.nan, 0.0, None, 0),
        lambda: ForceFeedback(0, 10.0, math.inf, None, 0),
        lambda: ForceFeedback(0, -0.5, 0.0, None, 0),
        lambda: ForceFeedback(0, 6600.0, 0.0, None, 0),
        lambda: ForceFeedback(0, 1.0, 0.0, 100.5, 0),
        lambda: ForceFeedback(2, 1.0, 0.0, 10.0, 0),
        lambda: ForceFeedback(-1, 1.0, 0.0, 10.0, 0),
        lambda: BridgeHeartbeat(256, BridgeState.IDLE),
        lambda: BridgeHeartbeat(-1, BridgeState.IDLE),
        lambda: BridgeHeartbeat(0, BridgeState.IDLE, 256),
        lambda: DeviceStatus(0, DeviceMode.OFF, DeviceFault(0), None, 256, 0, 0),
        lambda: DeviceStatus(0, DeviceMode.OFF, DeviceFault(0x100), None, 1, 0, 0),
        lambda: ProfileSegment(0, 0, (0.0, 0.0, 0.0)),
        lambda: ProfileSegment(1, 256, (0.0, 0.0, 0.0)),
        lambda: ProfileSegment(1, 0, (0.0, 0.0)),  # type: ignore[arg-type]
        lambda: ProfileCommit(1, 769, 0),
        lambda: ProfileCommit(1, 101, 1 << 32),
    ],
)
def test_unencodable_values_raise_encode_error(make: object) -> None:
    with pytest.raises(EncodeError):
        make().to_frame()  # type: ignore[operator]


def test_encode_error_is_a_value_error_naming_the_field() -> None:
    with pytest.raises(ValueError, match="DesiredForce"):
        ForceFeedback(0, math.nan, 0.0, None, 0).to_frame()


def test_inconsistent_ack_cannot_be_built() -> None:
    with pytest.raises(EncodeError, match="accepted"):
        ProfileAck(1, True, NackReason.BAD_CRC)
    with pytest.raises(EncodeError):
        ProfileAck(1, False, NackReason.NONE)


# --- round trips (hypothesis) -----------------------------------------------------------------------

u8 = st.integers(0, 255)
version = st.integers(1, 255)


def scaled(raw: int, step: float) -> float:
    return raw * step  # the DBC conversion: raw * scale + 0


gait = st.one_of(st.none(), st.integers(0, 200).map(lambda r: scaled(r, 0.5)))
force_u16 = st.integers(0, 0xFFFF).map(lambda r: scaled(r, 0.1))
force_i16 = st.integers(-0x8000, 0x7FFF).map(lambda r: scaled(r, 0.1))

messages = st.one_of(
    st.builds(AssistanceOff, st.sampled_from(AssistanceOffReason)),
    st.builds(BridgeHeartbeat, u8, st.sampled_from(BridgeState), u8),
    st.builds(ForceFeedback, st.integers(0, 1), force_u16, force_i16, gait, u8),
    st.builds(DeviceStatus, st.integers(0, 1), st.sampled_from(DeviceMode),
              st.integers(0, 255).map(DeviceFault), gait, u8, u8, u8),
    st.builds(ProfileSegment, version, u8, st.tuples(force_u16, force_u16, force_u16)),
    st.builds(ProfileCommit, version, st.integers(2, 768), st.integers(0, 2**32 - 1)),
    st.builds(ProfileAck.ack, version),
    st.builds(ProfileAck.nack, version, st.sampled_from(list(NackReason)[1:]),
              st.integers(0, 0xFFFF)),
)


@settings(max_examples=150, deadline=None)
@given(messages)
def test_message_to_frame_to_message_is_identity(message: object) -> None:
    assert decode_frame(message.to_frame()) == message  # type: ignore[attr-defined]


@settings(max_examples=150, deadline=None)
@given(st.sampled_from([m.frame_id for m in database().messages]), st.binary(min_size=8, max_size=8))
def test_frame_to_message_to_frame_is_identity(arbitration_id: int, data: bytes) -> None:
    length = database().get_message_by_frame_id(arbitration_id).length
    f = frame(arbitration_id, data[:length])
    try:
        message = decode_frame(f)
    except DecodeError as err:
        assert err.reason == "bad_value"  # right id and length: only a value can be wrong
        return
    assert bytes(message.to_frame().data) == bytes(f.data)


@settings(max_examples=300, deadline=None)
@given(
    arbitration_id=st.one_of(
        st.sampled_from([m.frame_id for m in database().messages]), st.integers(0, 0x1FFFFFFF)
    ),
    data=st.binary(max_size=8),
    extended=st.booleans(),
    remote=st.booleans(),
    error=st.booleans(),
)
def test_fuzzed_frames_only_ever_raise_decode_error(
    arbitration_id: int, data: bytes, extended: bool, remote: bool, error: bool
) -> None:
    f = can.Message(
        arbitration_id=arbitration_id if extended else arbitration_id & 0x7FF,
        data=None if remote else data, dlc=len(data), is_extended_id=extended,
        is_remote_frame=remote, is_error_frame=error,
    )
    try:
        decode_frame(f)
    except DecodeError as err:
        assert err.reason in DECODE_REASONS
