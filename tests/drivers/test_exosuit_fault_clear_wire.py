"""The fault-clear step: ClearFaults / ClearFaultsAck codecs, golden bytes, the endpoint's
request and answers on the wire, and the fault names the operator sees."""

from __future__ import annotations

import asyncio
import itertools
import os
from collections.abc import Iterator

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.errors import DecodeError, DriverConfigError
from drivers.exosuit.busload import budget_table
from drivers.exosuit.codec import (
    ClearFaults,
    ClearFaultsAck,
    DeviceFault,
    EncodeError,
    database,
    decode_frame,
    frame_id,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint
from drivers.exosuit.faults import (
    CLEARABLE_FAULTS,
    FAULT_INFO,
    describe_faults,
    fault_names,
    faults_text,
)

_channels = itertools.count()


def frame(arbitration_id: int, data: str) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=bytes.fromhex(data), is_extended_id=False)


# --- the DBC and the codec ---------------------------------------------------------------------------


def test_identifiers_sit_between_the_periodic_traffic_and_the_profile_transfer() -> None:
    ids = {m.name: m.frame_id for m in database().messages}
    assert (ids["ClearFaults"], ids["ClearFaultsAck0"], ids["ClearFaultsAck1"]) == (
        0x790, 0x791, 0x792)
    assert ids["DeviceStatus1"] < ids["ClearFaults"] < ids["ProfileAck"] < ids["ProfileSegment"]
    assert database().get_message_by_name("ClearFaults").senders == ["Bridge"]
    assert database().get_message_by_name("ClearFaultsAck1").senders == ["Exosuit"]


GOLDEN = [
    # sequence 3, actuator all = 0xFF, mask HEARTBEAT_LOST = bit 4 = 0x10
    (ClearFaults(3, DeviceFault.HEARTBEAT_LOST), 0x790, "03ff10"),
    (ClearFaults(255, DeviceFault.FORCE_LIMIT | DeviceFault.OVERCURRENT, 1), 0x790, "ff0121"),
    (ClearFaults(0, DeviceFault(0), 0), 0x790, "000000"),
    # actuator 1 -> 0x792; cleared 0x10, held FORCE_LIMIT = bit 5 = 0x20
    (ClearFaultsAck(1, 3, DeviceFault.HEARTBEAT_LOST, DeviceFault.FORCE_LIMIT), 0x792, "031020"),
    (ClearFaultsAck(0, 9, DeviceFault(0), DeviceFault(0)), 0x791, "090000"),
]


@pytest.mark.parametrize(("message", "arbitration_id", "data"), GOLDEN)
def test_golden_bytes(message: object, arbitration_id: int, data: str) -> None:
    f = message.to_frame()  # type: ignore[attr-defined]
    assert (f.arbitration_id, bytes(f.data).hex(), f.is_extended_id) == (arbitration_id, data, False)
    assert decode_frame(frame(arbitration_id, data)) == message


@pytest.mark.parametrize(
    ("f", "reason"),
    [
        (frame(0x790, "030210"), "bad_value"),  # actuator 2 does not exist (only 0, 1, all)
        (frame(0x790, "03ff"), "bad_length"),
        (frame(0x791, "0310"), "bad_length"),
        (frame(0x793, "031020"), "unknown_id"),
    ],
)
def test_bad_frames_raise_decode_error(f: can.Message, reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        decode_frame(f)
    assert info.value.reason == reason


@pytest.mark.parametrize(
    "make",
    [
        lambda: ClearFaults(256, DeviceFault(0)),
        lambda: ClearFaults(0, DeviceFault(0), 2),
        lambda: ClearFaults(0, 0x100),  # type: ignore[arg-type]
        lambda: ClearFaults(0, -1),  # type: ignore[arg-type]
        lambda: ClearFaultsAck(2, 0, DeviceFault(0), DeviceFault(0)),
        lambda: ClearFaultsAck(0, 0, DeviceFault(0), 0x1FF),  # type: ignore[arg-type]
    ],
)
def test_unencodable_requests_and_answers_raise_encode_error(make: object) -> None:
    with pytest.raises(EncodeError):
        make().to_frame()  # type: ignore[operator]


u8 = st.integers(0, 255)
faults = u8.map(DeviceFault)


@settings(max_examples=150, deadline=None)
@given(st.one_of(
    st.builds(ClearFaults, u8, faults, st.one_of(st.none(), st.integers(0, 1))),
    st.builds(ClearFaultsAck, st.integers(0, 1), u8, faults, faults),
))
def test_round_trip(message: object) -> None:
    assert decode_frame(message.to_frame()) == message  # type: ignore[attr-defined]


# --- the operator's words -------------------------------------------------------------------------


def test_fault_names_and_what_clears_them() -> None:
    assert fault_names(16) == ("heartbeat_lost",)
    assert fault_names(DeviceFault.FORCE_LIMIT | DeviceFault.OVERCURRENT) == (
        "overcurrent", "force_limit")
    assert fault_names(0x100) == ("bit8",)
    assert describe_faults(16) == (
        "heartbeat_lost (cleared by the bridge once the bridge heartbeat is back for 100 ms)",)
    assert "clears itself" in describe_faults(DeviceFault.BUS_ERROR)[0]
    assert faults_text(0) == "none"
    assert faults_text(0x30).count(";") == 1
    # every bit is named after its DBC signal
    signals = [s.name for s in database().get_message_by_name("DeviceStatus0").signals
               if s.name.startswith("Fault")]
    assert [FAULT_INFO[f].name.replace("_", "") for f in DeviceFault] == [
        s.removeprefix("Fault").lower() for s in signals]
    assert CLEARABLE_FAULTS == DeviceFault(0xFF) & ~DeviceFault.BUS_ERROR
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="faults"):
            fault_names(bad)  # type: ignore[arg-type]


def test_bus_budget_of_protocol_md_still_holds() -> None:
    # ClearFaults and its answers are sporadic and never overlap a push (the endpoint serialises
    # them), so the segments' worst case is the table PROTOCOL.md quotes, unchanged.
    with open(os.path.join(os.path.dirname(__file__), "../../drivers/PROTOCOL.md"),
              encoding="utf-8") as fh:
        assert budget_table() in fh.read()


# --- the endpoint: request and answers on the wire ---------------------------------------------------


@pytest.fixture
def channel() -> str:
    return f"hilbo-clear-{os.getpid()}-{next(_channels)}"


@pytest.fixture
def peer(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


async def test_request_goes_out_and_only_answers_with_its_sequence_count(
    channel: str, peer: can.BusABC
) -> None:
    wire: list[tuple[str, int, str]] = []  # (direction, id, bytes), in order

    async def device() -> None:
        f = await asyncio.to_thread(peer.recv, 2.0)
        assert f is not None
        wire.append(("rx", f.arbitration_id, bytes(f.data).hex()))
        request = ClearFaults.from_frame(f)
        for answer in [
            ClearFaultsAck(0, (request.sequence - 1) % 256, DeviceFault(0), DeviceFault(0)),  # stale
            ClearFaultsAck(0, request.sequence, DeviceFault.HEARTBEAT_LOST, DeviceFault(0)),
            ClearFaultsAck(1, request.sequence, DeviceFault.HEARTBEAT_LOST,
                           DeviceFault.FORCE_LIMIT),
        ]:
            out = answer.to_frame()
            wire.append(("tx", out.arbitration_id, bytes(out.data).hex()))
            peer.send(out)

    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        task = asyncio.create_task(device())
        result = await ep.clear_faults(DeviceFault.HEARTBEAT_LOST | DeviceFault.FORCE_LIMIT)
        await task
        second = ep.clear_faults(0, actuator=1, timeout_s=0.05)  # nobody answers this one
        unanswered = await second
        counters = dict(ep.counters)
    assert wire == [("rx", 0x790, "00ff30"), ("tx", 0x791, "ff0000"), ("tx", 0x791, "001000"),
                    ("tx", 0x792, "001020")]
    assert counters == {"clear_ack_stale": 1}
    assert (result.sequence, result.missing, result.ok) == (0, (), False)
    assert result.cleared == DeviceFault.HEARTBEAT_LOST
    assert result.held == DeviceFault.FORCE_LIMIT
    assert result.describe() == (
        "cleared heartbeat_lost; still held: force_limit (cleared by the bridge once the "
        "measured force is back under the limit)")
    assert (unanswered.sequence, unanswered.missing, unanswered.ok) == (1, (1,), False)
    assert "no answer from actuator(s) 1" in unanswered.describe()
    sent = peer.recv(timeout=1.0)
    assert sent is not None and bytes(sent.data).hex() == "010100"  # sequence 1, actuator 1, mask 0


async def test_clear_faults_rejects_bad_arguments(channel: str) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        with pytest.raises(DriverConfigError, match="timeout_s"):
            await ep.clear_faults(timeout_s=0)
        with pytest.raises(DriverConfigError, match="n_actuators"):
            await ep.clear_faults(n_actuators=3)
        with pytest.raises(EncodeError, match="actuator"):
            await ep.clear_faults(actuator=5)
        with pytest.raises(EncodeError, match="fault bits"):
            await ep.clear_faults(0x100)
        assert frame_id("ClearFaults") == 0x790
