"""``hilbo bench watchdog``: the spy's arithmetic on hand-made frames, its config checks, and one
toy run at real time (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from bridge.bench.watchdog import BusSpy, WatchdogBenchConfig, latencies
from bridge.cli.main import main
from drivers.exosuit import (
    AssistanceOff,
    AssistanceOffReason,
    BridgeHeartbeat,
    BridgeState,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
)
from hilbo_core.errors import ConfigError


def _frame(message: DeviceStatus | AssistanceOff | BridgeHeartbeat, t_s: float) -> can.Message:
    frame = message.to_frame()
    frame.timestamp = t_s
    return frame


def _status(actuator: int, t_s: float) -> can.Message:
    return _frame(DeviceStatus(actuator=actuator, mode=DeviceMode.ASSIST, faults=DeviceFault(0),
                               gait_phase_pct=None, profile_version_active=1,
                               profile_version_pending=0, counter=0), t_s)


def _heartbeat(state: BridgeState, t_s: float) -> can.Message:
    return _frame(BridgeHeartbeat(counter=0, state=state), t_s)


def _silent_between(spy: BusSpy, start_s: float, end_s: float, *, skew_s: float = 0.0) -> None:
    """Statuses of both actuators every 20 ms outside (start_s, end_s); actuator 1 ``skew_s``
    earlier."""
    for k in range(100):
        t = 0.02 * k
        if not start_s < t < end_s:
            spy.on_message_received(_status(0, t))
            spy.on_message_received(_status(1, t - skew_s))


def test_latency_counts_from_the_stalest_actuators_last_status() -> None:
    spy = BusSpy()
    _silent_between(spy, 0.3, 1.0, skew_s=0.002)  # the last statuses at 0.3 and 0.298
    spy.on_message_received(_heartbeat(BridgeState.RUNNING, 0.29))
    spy.on_message_received(_frame(AssistanceOff(AssistanceOffReason.DEVICE_HEARTBEAT_LOST), 0.378))
    spy.on_message_received(_frame(AssistanceOff(AssistanceOffReason.SESSION_END), 1.5))
    found = latencies(spy, 2, min_drop_s=0.3)
    assert found["latencies_ms"] == [pytest.approx(80.0)]
    assert (found["missed"], found["already_off"], found["other_offs_silence_ms"]) == (0, 0, [])


def test_a_drop_while_paused_is_already_off_and_one_while_running_unanswered_is_missed() -> None:
    for state, key in ((BridgeState.PAUSED, "already_off"), (BridgeState.RUNNING, "missed")):
        spy = BusSpy()
        _silent_between(spy, 0.3, 1.0)
        spy.on_message_received(_heartbeat(state, 0.29))
        found = latencies(spy, 2, min_drop_s=0.3)
        assert found[key] == 1 and found["latencies_ms"] == []


def test_an_off_while_statuses_still_come_is_reported_with_its_silence() -> None:
    spy = BusSpy()
    _silent_between(spy, 5.0, 6.0)  # no drop at all
    spy.on_message_received(_frame(AssistanceOff(AssistanceOffReason.DEVICE_HEARTBEAT_LOST), 0.505))
    found = latencies(spy, 2, min_drop_s=0.3)
    assert found["latencies_ms"] == [] and found["other_offs_silence_ms"] == [pytest.approx(20.0)]


def test_an_off_just_after_a_short_silence_ended_reports_that_silence() -> None:
    spy = BusSpy()
    _silent_between(spy, 0.2, 0.32)  # 120 ms (a stalled loop that also sends the statuses)
    spy.on_message_received(_frame(AssistanceOff(AssistanceOffReason.DEVICE_HEARTBEAT_LOST), 0.325))
    found = latencies(spy, 2, min_drop_s=0.3)
    assert found["latencies_ms"] == [] and found["other_offs_silence_ms"] == [pytest.approx(120.0)]


@pytest.mark.parametrize("kw", [{"n": 0}, {"timeout_ms": 20.0}, {"drop_s": 0.1}, {"spacing_s": 1.0},
                                {"burners": -1}])
def test_bad_settings_are_refused(kw: dict) -> None:
    with pytest.raises(ConfigError):
        WatchdogBenchConfig(**kw)


@pytest.mark.slow
def test_a_toy_run_at_real_time_writes_its_result(tmp_path: Path) -> None:
    code = main(["bench", "watchdog", "--n", "2", "--burners", "0", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "watchdog.json").read_text())
    run = result["runs"][0]
    assert run["drops_injected"] == 2 and run["statuses_seen"] > 100
    assert code == (0 if run["within_timeout"] and run["false_alarms"] == 0 else 1)
    assert (tmp_path / "watchdog_table.md").exists()


@pytest.mark.parametrize("argv", [["--burners", "x"], ["--n", "0"], ["--timeout-ms", "5"]])
def test_a_bad_command_line_is_a_usage_error_before_any_run(argv: list[str], tmp_path: Path) -> None:
    try:  # argparse's own usage error (a bounded number type) exits; the command's returns 2
        status = main(["bench", "watchdog", *argv, "--out", str(tmp_path)])
    except SystemExit as err:
        status = err.code
    assert status == 2
    assert not (tmp_path / "watchdog.json").exists()
