"""Who may resume after each fault class (drivers/PROTOCOL.md, "Who resumes after a fault").

One test per class, on the deterministic session harness (loop time): a device fault of class
``PERSON`` (the emergency stop first) keeps assistance off until a person presses ``r`` after its
cause is gone, whatever the resume policy says, and the bridge never asks the device to clear it
by itself; a fault of class ``POLICY`` may be cleared and resumed from by the policy; a fault of
class ``END`` ends the session. Releasing an emergency stop must not restart the machine
(ISO 13850 and IEC 60204-1 on resetting an emergency stop).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from supervision_harness import Outcome, run_session

from bridge.log.reader import read_log
from bridge.supervisor import SupervisorState
from drivers.exosuit import FAULT_INFO, DeviceFault, FaultRecovery

T_FAULT = 10.0
FAULT_S = 0.5
#: The operator presses r this long after the fault's cause is gone (loop time).
OPERATOR_AFTER_S = 30.0

PERSON = [i.name for i in FAULT_INFO.values() if i.recovery is FaultRecovery.PERSON]
POLICY = [i.name for i in FAULT_INFO.values() if i.recovery is FaultRecovery.POLICY]


def _bit(name: str) -> DeviceFault:
    return next(b for b, i in FAULT_INFO.items() if i.name == name)


def _commits_after(out: Outcome, t: float) -> list[float]:
    return [tt for tt, w, _ in out.device.transcript if w == "commit" and tt > t]


def _clears_of(out: Outcome, bit: DeviceFault) -> list[float]:
    return [t for t, w, d in out.device.transcript if w == "clear_faults" and d & bit]


def _resume_sources(out: Outcome) -> list[str]:
    return [e["message"] for e in read_log(out.log).data("/events") if e["kind"] == "resume"]


def test_the_table_covers_every_bit_and_the_emergency_stop_needs_a_person() -> None:
    assert {int(b) for b in FAULT_INFO} == {1 << k for k in range(8)}
    assert FAULT_INFO[DeviceFault.EMERGENCY_STOP].recovery is FaultRecovery.PERSON
    assert set(PERSON) == {"overcurrent", "force_sensor", "encoder", "force_limit", "emergency_stop"}
    assert set(POLICY) == {"overtemperature", "heartbeat_lost", "bus_error"}


@pytest.mark.parametrize("name", PERSON)
def test_a_person_fault_keeps_assistance_off_until_the_operator_resumes(
        tmp_path: Path, name: str) -> None:
    """Pressed, released, resume policy on (1 s): nothing is committed and nothing clears the
    fault until the operator's r, 30 s after the release."""
    out = run_session(tmp_path, at_time_s=T_FAULT, fault=f"device:{name}", fault_s=FAULT_S,
                      resume_after_s=OPERATOR_AFTER_S, n_evaluations=4, auto_resume_s=1.0,
                      operator_present=True)
    t_r = T_FAULT + FAULT_S + OPERATOR_AFTER_S
    bit = _bit(name)
    assert out.device.violations == []
    assert min(_commits_after(out, T_FAULT)) >= t_r
    assert min(_clears_of(out, bit)) >= t_r
    assert out.session._auto_resumes == 0
    assert "resumed by the operator" in _resume_sources(out)
    assert out.summary["n_evaluations"] >= 4
    kinds = [e["kind"] for e in read_log(out.log).data("/events")]
    assert "person_required" in kinds


def test_an_emergency_stop_still_held_refuses_the_operator_and_needs_a_new_r(tmp_path: Path) -> None:
    """r while the button is held is refused (the device keeps the fault); the release alone
    resumes nothing; the next r after the release does."""
    out = run_session(tmp_path, at_time_s=T_FAULT, fault="device:emergency_stop", fault_s=20.0,
                      resume_after_s=1e6, operator_r_s=(T_FAULT + 5.0, T_FAULT + 40.0),
                      n_evaluations=4, auto_resume_s=0.5, operator_present=True)
    assert min(_commits_after(out, T_FAULT)) >= T_FAULT + 40.0
    events = read_log(out.log).data("/events")
    refused = [e for e in events if e["kind"] == "resume_refused"]
    assert refused and "emergency_stop" in refused[0]["message"]
    assert _resume_sources(out) == ["resumed by the operator"]


def test_an_emergency_stop_during_a_warm_up_needs_the_person_too(tmp_path: Path) -> None:
    """Pressed before anything assists (the start): the push that follows must not clear it."""
    out = run_session(tmp_path, at_time_s=0.05, fault="device:emergency_stop", fault_s=FAULT_S,
                      resume_after_s=OPERATOR_AFTER_S, n_evaluations=3, auto_resume_s=0.5,
                      operator_present=True)
    t_r = 0.05 + FAULT_S + OPERATOR_AFTER_S
    assert min(_commits_after(out, 0.0)) >= t_r
    assert min(_clears_of(out, DeviceFault.EMERGENCY_STOP)) >= t_r


def test_a_person_fault_with_nobody_at_the_keyboard_stops_the_session(tmp_path: Path) -> None:
    out = run_session(tmp_path, at_time_s=T_FAULT, fault="device:emergency_stop", fault_s=FAULT_S,
                      resume_after_s=1e6, n_evaluations=6, auto_resume_s=0.5,
                      operator_present=False)
    assert out.session.supervisor.state is SupervisorState.STOPPED
    assert _commits_after(out, T_FAULT) == []
    assert _clears_of(out, DeviceFault.EMERGENCY_STOP) == []
    end = [e["message"] for e in read_log(out.log).data("/events") if e["kind"] == "person_required"]
    assert end and "only a person at the PC may resume" in end[0]
    # Nobody stopped it: the summary says why it ended.
    assert out.summary["end_reason"] == "person_required"


@pytest.mark.parametrize("name", ["overtemperature", "heartbeat_lost", "bus_error"])
def test_a_policy_fault_is_cleared_and_resumed_by_the_policy(tmp_path: Path, name: str) -> None:
    out = run_session(tmp_path, at_time_s=T_FAULT, fault=f"device:{name}", fault_s=FAULT_S,
                      resume_after_s=1e6, n_evaluations=4, auto_resume_s=1.0)
    assert out.device.violations == []
    assert out.session._auto_resumes == 1
    first = min(_commits_after(out, T_FAULT))
    # The policy waits its healthy time (1 s) from the pause; the cause was gone after 0.5 s.
    assert T_FAULT + max(FAULT_S, 1.0) <= first < T_FAULT + 30.0
    assert any(s.startswith("resumed by the resume policy") for s in _resume_sources(out))
    assert out.summary["n_evaluations"] >= 4


def test_a_failed_bus_ends_the_session(tmp_path: Path) -> None:
    out = run_session(tmp_path, at_time_s=T_FAULT, fault="bus_error", n_evaluations=6,
                      auto_resume_s=0.5, operator_present=True)
    assert out.session.supervisor.state is SupervisorState.STOPPED
    assert _commits_after(out, T_FAULT) == []
