"""CanEndpoint on python-can ``virtual``: config, receive path, counters, fuzz, failures."""

from __future__ import annotations

import asyncio
import itertools
import os

import can
import numpy as np
import pytest

from drivers.errors import DriverConfigError, DriverError, TransportError
from drivers.exosuit.codec import (
    AssistanceOff,
    AssistanceOffReason,
    BridgeHeartbeat,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    EncodeError,
    ForceFeedback,
    ProfileAck,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, Stamped

_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"hilbo-ep-{os.getpid()}-{next(_channels)}"


@pytest.fixture
def peer(channel: str) -> can.BusABC:
    """A raw python-can bus on the same virtual channel (plays the device)."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def status(counter: int = 0) -> DeviceStatus:
    return DeviceStatus(0, DeviceMode.ASSIST, DeviceFault(0), 12.5, 1, 0, counter)


async def next_item(sub: object, timeout_s: float = 2.0) -> object:
    return await asyncio.wait_for(sub.get(), timeout_s)  # type: ignore[attr-defined]


# --- config ----------------------------------------------------------------------------------------


def test_config_builds_bus_kwargs_per_interface() -> None:
    assert CanBusConfig("socketcan", "can0").bus_kwargs() == {
        "interface": "socketcan", "channel": "can0",  # bitrate is set with `ip link`
    }
    assert CanBusConfig("pcan", "PCAN_USBBUS1", 500_000, {"fd": False}).bus_kwargs() == {
        "interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": 500_000, "fd": False,
    }
    assert CanBusConfig("kvaser", 0).bus_kwargs()["bitrate"] == 1_000_000


def test_config_from_mapping_takes_flat_and_nested_options() -> None:
    cfg = CanBusConfig.from_mapping({
        "interface": "slcan", "channel": "/dev/ttyACM0", "tty_baudrate": 115200,
        "options": {"sleep_after_open": 0.5},
    })
    assert cfg.options == {"tty_baudrate": 115200, "sleep_after_open": 0.5}
    assert cfg.bitrate == 1_000_000


@pytest.mark.parametrize(
    ("mapping", "match"),
    [
        ({"interface": "socketcan"}, "missing key.*channel"),
        ({"interface": "nope", "channel": "x"}, "can.interface = 'nope'"),
        ({"interface": "socketcan", "channel": ""}, "can.channel"),
        ({"interface": "socketcan", "channel": "can0", "bitrate": 12}, "can.bitrate = 12"),
        ({"interface": "socketcan", "channel": "can0", "bitrate": True}, "can.bitrate"),
        ({"interface": "socketcan", "channel": "can0", "tty_baudrate": 9600},
         "tty_baudrate not known for interface 'socketcan'"),
        ({"interface": "virtual", "channel": "x", "options": {"bogus": 1}}, "bogus"),
        ({"interface": "virtual", "channel": "x", "options": 3}, "can.options must be a table"),
    ],
)
def test_config_rejects_unknown_and_bad_keys(mapping: dict[str, object], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        CanBusConfig.from_mapping(mapping)


def test_config_is_frozen_and_its_options_read_only() -> None:
    cfg = CanBusConfig("virtual", "x", options={"rx_queue_size": 10})
    with pytest.raises(AttributeError):
        cfg.channel = "y"  # type: ignore[misc]
    with pytest.raises(TypeError):
        cfg.options["rx_queue_size"] = 1  # type: ignore[index]


async def test_open_failure_is_a_transport_error(tmp_path: object) -> None:
    cfg = CanBusConfig("slcan", "/nonexistent/ttyHILBO", options={"sleep_after_open": 0})
    with pytest.raises(TransportError, match="cannot open CAN bus slcan"):
        async with CanEndpoint(cfg):
            pass


# --- receive path ----------------------------------------------------------------------------------


async def test_decoded_messages_reach_matching_subscriptions(channel: str, peer: can.BusABC) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        statuses = ep.subscribe(DeviceStatus)
        everything = ep.subscribe(timestamps=True)
        peer.send(ForceFeedback(1, 10.0, 9.5, 50.0, 3).to_frame())
        peer.send(status(7).to_frame())
        assert await next_item(statuses) == status(7)
        first = await next_item(everything)
        assert isinstance(first, Stamped)
        assert first.message == ForceFeedback(1, 10.0, 9.5, 50.0, 3)
        assert first.t_s > 0
        assert (await next_item(everything)).message == status(7)  # type: ignore[attr-defined]
        assert dict(ep.received) == {"ForceFeedback": 1, "DeviceStatus": 1}
        statuses.close()
        peer.send(status(8).to_frame())
        assert (await next_item(everything)).message == status(8)  # type: ignore[attr-defined]
        assert statuses.qsize() == 0


async def test_bad_frames_are_counted_by_reason_and_never_stop_the_endpoint(
    channel: str, peer: can.BusABC
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        sub = ep.subscribe()
        for f in [
            can.Message(arbitration_id=0x555, data=b"\x00", is_extended_id=False),
            can.Message(arbitration_id=0x020, data=b"\x01", is_extended_id=False),
            can.Message(arbitration_id=0x020, data=b"\x01\x09\x00", is_extended_id=False),
            can.Message(arbitration_id=0x020, data=b"\x01\x01\x00", is_extended_id=True),
            can.Message(arbitration_id=0x020, is_remote_frame=True, dlc=3, is_extended_id=False),
            can.Message(arbitration_id=0, is_error_frame=True),
        ]:
            peer.send(f)
        peer.send(status(1).to_frame())
        assert await next_item(sub) == status(1)
        assert dict(ep.counters) == {
            "unknown_id": 1, "bad_length": 1, "bad_value": 1, "extended_id": 1,
            "remote_frame": 1, "error_frame": 1,
        }


async def test_random_frames_are_all_counted_and_valid_ones_still_delivered(
    channel: str, peer: can.BusABC
) -> None:
    rng = np.random.default_rng(20240611)
    known = [0x010, 0x020, 0x110, 0x111, 0x120, 0x121, 0x7A0, 0x7B0, 0x7C0]
    n = 400
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        sub = ep.subscribe(DeviceStatus)
        for _ in range(n):
            ident = int(rng.choice(known)) if rng.random() < 0.7 else int(rng.integers(0, 0x800))
            data = rng.integers(0, 256, size=int(rng.integers(0, 9)), dtype=np.uint8).tobytes()
            peer.send(can.Message(arbitration_id=ident, data=data, is_extended_id=False))
        peer.send(status(99).to_frame())
        while (item := await next_item(sub)) != status(99):
            assert isinstance(item, DeviceStatus)  # a random frame that happened to decode
        total = sum(ep.counters.values()) + sum(ep.received.values())
        assert total == n + 1
        assert ep.counters["bad_length"] > 0 and ep.counters["unknown_id"] > 0
        assert ep.error is None


async def test_slow_subscriber_loses_oldest_items_and_they_are_counted(
    channel: str, peer: can.BusABC
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        slow = ep.subscribe(DeviceStatus, maxsize=2)
        fast = ep.subscribe(DeviceStatus)
        for k in range(5):
            peer.send(status(k).to_frame())
        for k in range(5):
            assert await next_item(fast) == status(k)
        assert ep.counters["subscriber_overflow"] == 3
        assert [slow.get_nowait(), slow.get_nowait()] == [status(3), status(4)]


# --- transmit, heartbeat, assistance-off ---------------------------------------------------------


async def test_heartbeat_counts_up_and_carries_the_bridge_state(
    channel: str, peer: can.BusABC
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        task = ep.start_heartbeat(period_s=0.005)
        assert ep.start_heartbeat(period_s=0.005) is task  # idempotent
        seen = []
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 2.0
        while len(seen) < 6 and loop.time() < deadline:
            f = await asyncio.to_thread(peer.recv, 0.5)
            if f is not None:
                seen.append(BridgeHeartbeat.from_frame(f))
            if len(seen) == 3:
                ep.bridge_state = BridgeState.RUNNING
        assert [h.counter for h in seen] == list(range(seen[0].counter, seen[0].counter + 6))
        assert seen[0].state == BridgeState.IDLE
        assert seen[-1].state == BridgeState.RUNNING
        await ep.stop_heartbeat()
        assert task.done()


async def test_assistance_off_is_sent_and_pauses_the_heartbeat_state(
    channel: str, peer: can.BusABC
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        ep.bridge_state = BridgeState.RUNNING
        await ep.send_assistance_off(AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
        f = await asyncio.to_thread(peer.recv, 2.0)
        assert f is not None and f.arbitration_id == 0x010
        assert AssistanceOff.from_frame(f).reason == AssistanceOffReason.DEVICE_HEARTBEAT_LOST
        assert ep.bridge_state == BridgeState.PAUSED


async def test_send_refuses_unencodable_messages_and_closed_endpoints(channel: str) -> None:
    ep = CanEndpoint(CanBusConfig("virtual", channel))
    with pytest.raises(DriverError, match="not open"):
        await ep.send(status())
    async with ep:
        with pytest.raises(EncodeError):
            await ep.send(ForceFeedback(0, float("nan"), 0.0, None, 0))
        with pytest.raises(DriverConfigError):
            await ep.push_profile([1.0, 2.0], 1, timeout_s=0)
        with pytest.raises(EncodeError, match="point 1"):
            await ep.push_profile([1.0, float("nan")], 1)
        with pytest.raises(DriverConfigError):
            ep.start_heartbeat(period_s=0)


# --- failures surface ------------------------------------------------------------------------------


class FailingBus(can.BusABC):
    """recv (and optionally send) raise; ``fd`` selects the loop-reader or the thread path."""

    def __init__(self, channel: str = "fail", *, fd: bool, fail_send: bool = False,
                 **kwargs: object) -> None:
        self._r, self._w = os.pipe()
        self._fd = fd
        self._fail_send = fail_send
        self.channel_info = "failing"
        super().__init__(channel=channel)

    def fileno(self) -> int:
        if not self._fd:
            raise NotImplementedError
        return self._r

    def trigger(self) -> None:
        os.write(self._w, b"x")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._fd:
            raise can.CanOperationError("adapter unplugged")
        os.read(self._r, 1)
        raise can.CanOperationError("adapter unplugged")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._fail_send:
            raise can.CanOperationError("bus off", 0)

    def shutdown(self) -> None:
        os.close(self._r)
        os.close(self._w)
        super().shutdown()


# python-can's threaded reader reports the error to the listeners, then re-raises it in its
# thread (by design); only that second report is silenced here.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
@pytest.mark.parametrize("fd", [True, False], ids=["fd-reader", "thread-reader"])
async def test_receive_failure_surfaces_to_waiters_subscribers_and_pushes(fd: bool) -> None:
    bus = FailingBus(fd=fd)
    ep = CanEndpoint(CanBusConfig("virtual", "unused"), bus_factory=lambda **kw: bus)
    async with ep:
        sub = ep.subscribe()
        if fd:
            bus.trigger()
        err = await asyncio.wait_for(ep.wait_failed(), 2.0)
        assert "adapter unplugged" in str(err)
        with pytest.raises(TransportError, match="adapter unplugged"):
            await next_item(sub)
        with pytest.raises(TransportError):
            await next_item(sub)  # keeps failing
        with pytest.raises(TransportError):
            await ep.push_profile([1.0, 2.0], 1)
        with pytest.raises(TransportError):
            await next_item(ep.subscribe())


async def test_heartbeat_send_failure_ends_the_task_and_marks_the_endpoint_failed() -> None:
    bus = FailingBus(fd=True, fail_send=True)
    ep = CanEndpoint(CanBusConfig("virtual", "unused"), bus_factory=lambda **kw: bus,
                     send_timeout_s=0.01)
    async with ep:
        task = ep.start_heartbeat(period_s=0.005)
        err = await asyncio.wait_for(ep.wait_failed(), 2.0)
        assert isinstance(err, TransportError) and "bus off" in str(err)
        assert task.done()
        assert ep.counters["send_retry"] >= 1


async def test_ack_for_another_version_is_ignored_and_counted(
    channel: str, peer: can.BusABC
) -> None:
    async with CanEndpoint(CanBusConfig("virtual", channel)) as ep:
        async def device() -> None:
            while True:
                f = await asyncio.to_thread(peer.recv, 1.0)
                if f is not None and f.arbitration_id == 0x7B0:
                    peer.send(ProfileAck.ack(41).to_frame())  # stale
                    peer.send(ProfileAck.ack(42).to_frame())
                    return

        task = asyncio.create_task(device())
        result = await ep.push_profile([5.0] * 101, 42, pace_s=0)
        await task
        assert (result.version, result.attempts) == (42, 1)
        assert ep.counters["ack_stale"] == 1
