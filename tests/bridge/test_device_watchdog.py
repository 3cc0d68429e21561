"""The device watchdog acts within its configured time: AssistanceOff is commanded before the
last DeviceStatus + ``device_timeout_s``, not after it (simulated clock, the supervision
harness's device model)."""

from __future__ import annotations

import asyncio
import bisect
import itertools
from pathlib import Path
from typing import Any

import pytest
from supervision_harness import BREATH_S, run_session

from bridge.runtime import RuntimeSettings
from drivers.exosuit import AssistanceOffReason


@pytest.mark.parametrize(("timeout_s", "at_time_s"), [
    (0.35, 4 * BREATH_S + 0.01), (0.35, 7 * BREATH_S + 1.234), (1.0, 5 * BREATH_S + 0.5)])
def test_assistance_off_before_the_last_status_plus_the_timeout(
        tmp_path: Path, timeout_s: float, at_time_s: float) -> None:
    out = run_session(tmp_path, at_time_s=at_time_s, fault="heartbeat_loss", n_evaluations=4,
                      device_timeout_s=timeout_s)
    offs = out.device.times_of("assistance_off", AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
    assert offs, "the silent device was not noticed"
    statuses = out.device.status_times
    last = statuses[bisect.bisect_right(statuses, at_time_s) - 1]
    limit = RuntimeSettings(device_timeout_s=timeout_s).device_silence_limit_s
    # Off before the configured time has passed since the last status, and not before the
    # watchdog's own limit (a status or two late is not a lost device).
    assert last + limit <= offs[0] < last + timeout_s
    assert offs[0] - last == pytest.approx(limit, abs=3e-3)  # and 2 ms for statuses on their way


def test_the_margin_leaves_a_short_timeout_more_than_a_missed_status() -> None:
    assert RuntimeSettings(device_timeout_s=0.1).device_silence_limit_s == pytest.approx(0.075)
    assert RuntimeSettings(device_timeout_s=0.04).device_silence_limit_s == pytest.approx(0.03)
    assert RuntimeSettings(device_timeout_s=1.0).device_silence_limit_s == pytest.approx(0.975)


def test_no_status_at_all_pauses_at_the_limit_after_the_start(tmp_path: Path) -> None:
    out = run_session(tmp_path, at_time_s=0.0, fault="heartbeat_loss", n_evaluations=3)
    offs = out.device.times_of("assistance_off", AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
    assert offs and offs[0] < RuntimeSettings(device_timeout_s=0.35).device_timeout_s
    assert any("no device status since the session started" in e for e in out.events)


def test_a_heartbeat_lost_again_during_its_own_pause_sends_off_again_without_a_new_cause(
        tmp_path: Path) -> None:
    # Lost at 5 breaths, back 1 s later; the pause holds (the operator's r comes at +30 s), and
    # the device goes silent once more at +4 s: a second AssistanceOff, but one pause cause (the
    # operator's line does not grow with every loss).
    t0 = 5 * BREATH_S + 0.3

    def flap_again(session: Any) -> None:
        loop = asyncio.get_running_loop()
        loop.call_at(t0 + 4.0, setattr, session.endpoint, "silent", True)
        loop.call_at(t0 + 5.0, setattr, session.endpoint, "silent", False)
        # On a real PC each loss is noticed after a slightly different silence (78 ms, 85 ms,
        # ...); this loop's time is exact, so add a different millisecond to each reading.
        silent_for, calls = session.device.silent_for, itertools.count(1)
        session.device.silent_for = lambda *a: silent_for(*a) + 1e-3 * (next(calls) % 7)

    out = run_session(tmp_path, at_time_s=t0, fault="heartbeat_loss", n_evaluations=4,
                      resume_after_s=30.0, on_session=flap_again)
    offs = out.device.times_of("assistance_off", AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
    assert len([t for t in offs if t0 < t < t0 + 2.0]) >= 1
    assert len([t for t in offs if t0 + 4.0 < t < t0 + 6.0]) >= 1
    pauses = [e for e in out.events if e.startswith("device heartbeat lost")]
    assert len(pauses) == 1, out.events
    assert out.summary["n_evaluations"] >= 1  # the session resumed and went on
