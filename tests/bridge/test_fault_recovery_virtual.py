"""The emergency stop on the virtual devices, end to end: pressed for half a second during the
exploration bout with the resume policy on (every simulation has it), assistance stays off until
a person presses r after the release, and with nobody at the keyboard the session stops.
(ISO 13850: releasing an emergency stop must not restart the machine.)"""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from bridge.log.reader import read_log
from bridge.runtime import BridgeSession, Command
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.slow

#: Pressed at 100 sim-s (inside the exploration bout, assisting) for 0.5 sim-s.
PRESS = "emergency-stop@100+0.5"


def small(**kw) -> VirtualSimConfig:
    opts = {"minutes": 6.0, "seed": 2, "n_explore": 3, "max_breaths": 10, "warmup_s": 20.0,
            "proposal_worker": "thread", "exosuit_faults": (PRESS,)}
    opts.update(kw)
    return VirtualSimConfig(**opts)


def test_released_emergency_stop_waits_for_the_operators_r(tmp_path) -> None:
    pressed: dict[str, float] = {}

    def operator(session: BridgeSession) -> None:
        session.settings = dataclasses.replace(session.settings, operator_present=True)
        st = session.status

        # The operator looks at the suit and presses r 40 sim-s after the pause, acting at the
        # session's breaths (not by polling in wall time, which a busy machine makes late).
        def on_breath(rec: BreathRecord) -> None:
            if "paused_at" not in pressed and "emergency_stop" in session.supervisor.pause_reason:
                pressed["paused_at"] = st.breath_time_s
            elif ("paused_at" in pressed and "r_at" not in pressed
                  and st.breath_time_s >= pressed["paused_at"] + 40.0):
                pressed["r_at"] = st.breath_time_s
                session.command(Command.RESUME)
        session.breath_listeners.append(on_breath)

    s = asyncio.run(run_virtual_sim(small(), tmp_path, on_session=operator))
    log = read_log(tmp_path / "session.mcap")
    events = log.data("/events")
    i_pause = next(i for i, e in enumerate(events)
                   if e["kind"] == "pause" and "emergency_stop" in e["message"])
    resumes = [e for e in events[i_pause:] if e["kind"] == "resume"]
    # Only the operator ended the emergency stop's pause: the policy never did.
    assert resumes and resumes[0]["message"] == "resumed by the operator"
    i_resume = events.index(resumes[0])
    between = events[i_pause:i_resume]
    # The one ClearFaults is the operator's resume's own: only its answers come after it.
    clears = [i for i, e in enumerate(between) if e["kind"] == "clear_faults"]
    assert len(clears) == 1
    assert {e["kind"] for e in between[clears[0] + 1:]} <= {"device_fault_cleared"}
    assert any(e["kind"] == "person_required" for e in between)
    # No profile was pushed and acked between the press and the operator's r (40 sim-s later).
    assert pressed["r_at"] - pressed["paused_at"] >= 40.0
    between_versions = {p["version"] for p in log.data("/profiles_sent")
                        if pressed["paused_at"] < p.get("t_s", 0.0) < pressed["r_at"]}
    assert not any(a["accepted"] and a["version"] in between_versions for a in log.data("/acks"))
    # The session went on after the operator's r: an evaluation ended after it.
    assert any(e["t_end"] > pressed["r_at"] for e in s["evaluations"])


def test_emergency_stop_without_an_operator_stops_the_simulation(tmp_path) -> None:
    s = asyncio.run(run_virtual_sim(small(), tmp_path))
    events = read_log(tmp_path / "session.mcap").data("/events")
    i_pause = next(i for i, e in enumerate(events)
                   if e["kind"] == "pause" and "emergency_stop" in e["message"])
    after = events[i_pause:]
    assert not any(e["kind"] in ("resume", "clear_faults") for e in after)
    assert any(e["kind"] == "person_required" and "only a person" in e["message"] for e in after)
    assert s["walking"]["session_s"] < 200.0
