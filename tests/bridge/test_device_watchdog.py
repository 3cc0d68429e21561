"""The device watchdog acts within its configured time: AssistanceOff is commanded before the
last DeviceStatus + ``device_timeout_s``, not after it (simulated clock, the supervision
harness's device model)."""

from __future__ import annotations

import bisect
from pathlib import Path

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
