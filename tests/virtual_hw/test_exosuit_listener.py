"""AppliedProfileListener: rebuilding the exosuit's applied profile from what is on the bus."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Sequence

import numpy as np
import pytest

from drivers.exosuit.codec import (
    AssistanceOff,
    AssistanceOffReason,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    ProfileAck,
    ProfileCommit,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint
from drivers.exosuit.profile import ProfileTransfer, forces_to_raw
from hilbo_core.profiles import ForceProfile, hip_ankle_profiles
from virtual_hw.clock import ScaledClock, VirtualClock
from virtual_hw.exosuit import AppliedProfileListener, VirtualExosuit, applied_profile_feed

TABLE = np.round(150.0 * np.sin(np.linspace(0.0, np.pi, 101)) ** 2, 1)


def status(actuator: int, mode: DeviceMode, active: int, phase: float = 0.0) -> DeviceStatus:
    return DeviceStatus(actuator, mode, DeviceFault(0), phase, active, 0, 0)


def transfer_messages(transfer: ProfileTransfer, *, crc: int | None = None) -> list[object]:
    commit = transfer.commit()
    if crc is not None:
        commit = ProfileCommit(commit.version, commit.n_points, crc)
    return [*transfer.segments(), commit]


class Recorder:
    def __init__(self) -> None:
        self.calls: list[tuple[tuple[ForceProfile, ...], float]] = []

    def __call__(self, profiles: tuple[ForceProfile, ...], t_s: float) -> None:
        self.calls.append((profiles, t_s))


@pytest.fixture
async def listener_and_calls() -> tuple[AppliedProfileListener, Recorder, VirtualClock]:
    clock = VirtualClock(start_s=10.0)
    calls = Recorder()
    # handle() is fed by hand: the endpoint is never opened
    listener = AppliedProfileListener(CanEndpoint(CanBusConfig("virtual", "unused")), clock,
                                      on_applied=calls, stride_s=1.0)
    return listener, calls, clock


async def test_switch_is_reported_once_every_leg_assists_backdated_by_the_gait_phase(
    listener_and_calls: tuple[AppliedProfileListener, Recorder, VirtualClock],
) -> None:
    listener, calls, clock = listener_and_calls
    transfer = ProfileTransfer.from_forces(TABLE, 5)
    for message in [*transfer_messages(transfer), ProfileAck.ack(5)]:
        listener.handle(message)
    listener.handle(status(0, DeviceMode.TRANSPARENT, 0))
    listener.handle(status(1, DeviceMode.TRANSPARENT, 0))
    await clock.run_until(10.3)
    listener.handle(status(0, DeviceMode.ASSIST, 5, phase=10.0))  # one leg switched: not yet
    assert calls.calls == []
    await clock.run_until(10.5)
    listener.handle(status(1, DeviceMode.ASSIST, 5, phase=20.0))
    ((profiles, t_s),) = calls.calls
    assert t_s == pytest.approx(10.5 - 0.20 * 1.0)  # phase 20 % of a 1 s stride ago
    assert forces_to_raw(profiles[0].force_n) == transfer.forces_raw
    listener.handle(status(1, DeviceMode.ASSIST, 5, phase=22.0))  # no change, no report
    await clock.run_until(11.0)
    listener.handle(status(0, DeviceMode.ASSISTANCE_OFF, 5))  # one leg's frame says off: wait
    assert len(calls.calls) == 1
    await clock.run_until(11.01)
    listener.handle(status(1, DeviceMode.ASSISTANCE_OFF, 5))
    assert calls.calls[1:] == [((), pytest.approx(11.01))]
    assert listener.reports == [(5, pytest.approx(10.3)), (None, pytest.approx(11.01))]


async def test_backdating_never_goes_before_the_previous_status_frame(
    listener_and_calls: tuple[AppliedProfileListener, Recorder, VirtualClock],
) -> None:
    listener, calls, clock = listener_and_calls
    for message in [*transfer_messages(ProfileTransfer.from_forces(TABLE, 6)), ProfileAck.ack(6)]:
        listener.handle(message)
    listener.handle(status(0, DeviceMode.ASSIST, 6))
    listener.handle(status(1, DeviceMode.TRANSPARENT, 0))
    await clock.run_until(10.02)
    listener.handle(status(1, DeviceMode.ASSIST, 6, phase=80.0))  # 0.8 s ago would be too early
    assert calls.calls[0][1] == pytest.approx(10.0)


async def test_corrupted_or_unseen_tables_are_never_reported(
    listener_and_calls: tuple[AppliedProfileListener, Recorder, VirtualClock],
) -> None:
    listener, calls, _ = listener_and_calls
    bad = ProfileTransfer.from_forces(TABLE, 7)
    for message in [*transfer_messages(bad, crc=bad.crc32 ^ 1), ProfileAck.ack(7)]:
        listener.handle(message)
    for _ in range(3):  # the device says it applies 7 (or 8, never pushed while we listened)
        for version in (7, 8):
            listener.handle(status(0, DeviceMode.ASSIST, version))
            listener.handle(status(1, DeviceMode.ASSIST, version))
    assert calls.calls == []
    assert listener.counters == {"bad_crc": 1, "ack_without_table": 1, "unknown_version": 2}


async def test_profile_feed_drives_a_cart_from_a_hip_ankle_exosuit_on_the_bus() -> None:
    config = CanBusConfig("virtual", f"vexo-feed-{os.getpid()}")
    clock = ScaledClock(4.0)
    hip, ankle = hip_ankle_profiles(
        {"hip_t_peak": 25.0, "hip_t_offset": 45.0, "ankle_t1": 35.0, "ankle_t2": 55.0})
    table = np.r_[hip.force_n, ankle.force_n]

    class Cart:
        def __init__(self) -> None:
            self.clock = clock
            self.calls: list[tuple[tuple[ForceProfile, ...], float | None]] = []

        def on_profile_applied(self, profiles: Sequence[ForceProfile],
                               t_sim: float | None = None) -> float:
            self.calls.append((tuple(profiles), t_sim))
            return 0.0

    cart = Cart()

    async def calls(n: int) -> None:
        for _ in range(500):
            if len(cart.calls) >= n:
                return
            await asyncio.sleep(0.01)  # reports cross python-can's bus thread: bounded poll
        raise AssertionError(f"the cart got {len(cart.calls)} of {n} reports")

    joints = ("hip", "ankle")
    async with VirtualExosuit(config, clock, joints=joints, feedback_hz=0) as exo, \
            CanEndpoint(config) as bridge:
        feed = asyncio.create_task(applied_profile_feed(config, joints=joints)(cart))
        bridge.bridge_state = BridgeState.RUNNING
        bridge.start_heartbeat()
        # Wall: the feed opens its own bus in an executor thread and exposes no readiness event.
        await asyncio.sleep(0.2)  # the feed's endpoint is open and listening
        await bridge.push_profile(table, 3)
        await calls(1)
        await bridge.send(AssistanceOff(AssistanceOffReason.OPERATOR_STOP))
        await calls(2)
        feed.cancel()
        with pytest.raises(asyncio.CancelledError):
            await feed
    (hip_got, ankle_got), t_on = cart.calls[0]
    assert (hip_got.actuator, ankle_got.actuator) == ("hip", "ankle")
    raw = ProfileTransfer.from_forces(table, 3).forces_raw
    assert forces_to_raw(hip_got.force_n) + forces_to_raw(ankle_got.force_n) == raw
    assert cart.calls[1][0] == ()
    ((_, t_switched), (_, t_off)) = exo.applied_log
    assert t_on == pytest.approx(t_switched, abs=0.3)
    assert cart.calls[1][1] == pytest.approx(t_off, abs=0.3)
