"""The supervisor alone owns pause/stop/assist, the heartbeat's state and the gate's baseline."""

from __future__ import annotations

import asyncio

import pytest

from bridge.supervisor import PushRefused, PushStage, Supervisor, SupervisorState
from drivers.errors import TransportError
from drivers.exosuit import AssistanceOffReason, BridgeState, FaultRecovery


class Endpoint:
    def __init__(self, fail: bool = False) -> None:
        self.bridge_state = BridgeState.IDLE
        self.offs: list[AssistanceOffReason] = []
        self.fail = fail

    async def send_assistance_off(self, reason: AssistanceOffReason) -> None:
        if self.fail:
            raise TransportError("bus down")
        self.offs.append(reason)


class Gate:
    def __init__(self) -> None:
        self.baseline: object | None = None

    def acknowledge(self, admitted: object) -> None:
        self.baseline = admitted

    def assistance_off(self) -> None:
        self.baseline = None


def make(health: str | None = None, fail: bool = False) -> tuple[Supervisor, Endpoint, Gate, list]:
    ep, gate, events = Endpoint(fail), Gate(), []
    sup = Supervisor(ep, gate, on_event=lambda k, t: events.append((k, t)), health=lambda: health)
    return sup, ep, gate, events


async def test_a_push_runs_only_with_leave_and_its_ack_sets_assist_and_baseline() -> None:
    sup, ep, gate, _ = make()
    assert sup.state is SupervisorState.STARTING
    ticket = sup.begin_push("admitted", 1)
    assert ep.bridge_state == BridgeState.IDLE  # nothing on the heartbeat before the first segment
    assert sup.permit(ticket, "first_segment") and ep.bridge_state == BridgeState.RUNNING
    assert sup.permit(ticket, PushStage.COMMIT)
    assert sup.acknowledged(ticket)
    assert sup.assisting and gate.baseline == "admitted" and sup.state is SupervisorState.RUNNING


async def test_a_pause_during_a_push_refuses_its_commit_and_its_ack() -> None:
    sup, ep, gate, events = make()
    ticket = sup.begin_push("admitted", 1)
    assert sup.permit(ticket, "first_segment")
    await sup.pause(AssistanceOffReason.OPERATOR_STOP, "operator pause")
    assert ep.bridge_state == BridgeState.PAUSED and ep.offs == [AssistanceOffReason.OPERATOR_STOP]
    assert not sup.permit(ticket, "commit")
    assert not sup.acknowledged(ticket)
    assert not sup.assisting and gate.baseline is None
    assert sup.counters["commit_refused"] == 1 and sup.counters["ack_overtaken"] == 1
    assert sup.describe() == "paused: operator pause" and ("pause", "operator pause") in events
    with pytest.raises(PushRefused):
        sup.begin_push("next", 2)


async def test_the_pause_takes_effect_before_its_first_await() -> None:
    sup, ep, _, _ = make()
    ticket = sup.begin_push("admitted", 1)
    sup.permit(ticket, "first_segment")
    pausing = asyncio.ensure_future(sup.pause(AssistanceOffReason.OPERATOR_STOP, "p"))
    await asyncio.sleep(0)  # the pause started; its assistance-off may still be on its way
    assert not sup.permit(ticket, "commit") and ep.bridge_state == BridgeState.PAUSED
    await pausing


async def test_an_assistance_off_without_pause_voids_older_tickets_but_not_new_ones() -> None:
    sup, _, _, _ = make()
    old = sup.begin_push("a", 1)
    await sup.assistance_off(AssistanceOffReason.SESSION_END, "warm-up")
    assert not sup.paused and not sup.permit(old, "first_segment")
    new = sup.begin_push("b", 2)
    assert sup.permit(new, "first_segment") and sup.acknowledged(new)


async def test_resume_asks_health_and_stop_is_final() -> None:
    sup, _, _, events = make(health="device LOST")
    await sup.pause(AssistanceOffReason.DEVICE_HEARTBEAT_LOST, "lost")
    assert sup.resume("operator") == "device LOST" and sup.paused
    assert sup.counters["resume_refused"] == 1
    sup._health = lambda: None
    assert sup.resume("operator") is None and not sup.paused
    assert events[-1] == ("resume", "resumed by the operator")
    await sup.stop(AssistanceOffReason.OPERATOR_STOP, "operator stop")
    assert sup.resume("operator") == "the session is stopped"
    assert sup.state is SupervisorState.STOPPED


async def test_a_failed_assistance_off_keeps_the_baseline_and_is_reported() -> None:
    sup, ep, gate, events = make(fail=True)
    t = sup.begin_push("a", 1)
    sup.permit(t, "first_segment")
    sup.acknowledged(t)
    await sup.pause(AssistanceOffReason.INTERNAL_ERROR, "x")
    # Heartbeat says paused anyway; the device's last table stays the rate-limit baseline.
    assert ep.bridge_state == BridgeState.PAUSED and gate.baseline == "a"
    assert events[-1][0] == "assistance_off_failed"


async def test_an_unknown_stage_is_an_error() -> None:
    sup, _, _, _ = make()
    with pytest.raises(ValueError, match="segment"):
        sup.permit(sup.begin_push("a", 1), "segment")


async def test_a_pause_during_a_pause_adds_its_reason_and_one_resume_ends_both() -> None:
    sup, _, _, events = make()
    await sup.pause(AssistanceOffReason.DEVICE_HEARTBEAT_LOST, "device heartbeat lost for 260 ms")
    await sup.pause(AssistanceOffReason.SESSION_END, "between bouts")
    await sup.pause(AssistanceOffReason.SESSION_END, "between bouts")  # the same reason: once
    assert sup.describe() == "paused: device heartbeat lost for 260 ms; between bouts"
    assert [k for k, _ in events].count("pause") == 2 and not sup.by_operator
    await sup.pause(AssistanceOffReason.OPERATOR_STOP, "operator pause")
    assert sup.by_operator and sup.needs_person
    # The operator's own pause ends only by a person.
    assert sup.resume("resume policy") is not None and sup.paused
    assert sup.resume("operator", by_person=True) is None and not sup.paused
    assert not sup.by_operator and not sup.needs_person
    assert sup.pause_reason == "device heartbeat lost for 260 ms; between bouts; operator pause"


async def test_has_reason_answers_for_the_current_pause_only() -> None:
    sup, _, _, _ = make()
    assert not sup.has_reason(AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
    await sup.pause(AssistanceOffReason.DEVICE_HEARTBEAT_LOST, "device heartbeat lost: no status for 80 ms")
    assert sup.has_reason(AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
    assert not sup.has_reason(AssistanceOffReason.OPERATOR_STOP)
    assert sup.resume("resume policy") is None and not sup.paused
    assert not sup.has_reason(AssistanceOffReason.DEVICE_HEARTBEAT_LOST)


@pytest.mark.parametrize("recovery", list(FaultRecovery))
async def test_each_recovery_class_decides_who_may_end_the_pause(recovery: FaultRecovery) -> None:
    sup, ep, _, events = make()
    await sup.pause(AssistanceOffReason.INTERNAL_ERROR, "device faults: x", recovery=recovery)
    assert sup.paused and ep.bridge_state != BridgeState.RUNNING
    if recovery is FaultRecovery.END:
        assert sup.stopped and sup.resume("operator", by_person=True) == "the session is stopped"
        return
    policy = sup.resume("resume policy (1 of 10)")
    if recovery is FaultRecovery.PERSON:
        assert policy is not None and "only a person" in policy and sup.paused
        assert sup.resume("operator", by_person=True) is None
    else:
        assert policy is None
    assert not sup.paused and events[-1][0] == "resume"


async def test_a_person_cause_outlives_its_fault_and_later_causes() -> None:
    """The emergency stop's pause keeps needing the person after the device dropped the bit and
    after a policy-class cause joined it: the health check alone would let the policy resume."""
    sup, _, _, _ = make()
    await sup.pause(AssistanceOffReason.INTERNAL_ERROR, "device faults: emergency_stop",
                    recovery=FaultRecovery.PERSON)
    await sup.pause(AssistanceOffReason.DEVICE_HEARTBEAT_LOST, "device heartbeat lost for 120 ms")
    assert sup.person_causes == ("device faults: emergency_stop",)
    assert sup.has_cause("device heartbeat lost for 120 ms")
    assert sup.resume("resume policy (1 of 10)") is not None and sup.paused
    assert sup.resume("operator", by_person=True) is None and not sup.needs_person
