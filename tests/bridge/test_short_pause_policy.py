"""A fault the resume policy ends is a short pause: the same setting again at once, no warm-up.

The policy resumes once the device has been healthy for ``auto_resume_s`` (10 s in the lab's
headless runs; 16 s pauses on average on a busy PC, docs/results.md), so such a pause
lasts the detection and that wait. The default ``short_pause_s`` (30 s, hilbo_core/protocol.py)
must hold it, or every glitch of a busy PC costs the bout's 3-minute warm-up; a threshold of
15 s (the earlier default) did not. Here the policy waits 20 s, between the two. Deterministic
session harness, loop time, a breath every 3 s.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from supervision_harness import harness_protocol_config, run_session

from bridge.log.reader import read_log
from hilbo_core.protocol import SessionProtocol

WARMUP_S = 60.0
T_FAULT = 75.0  # in the first exploration setting, after the 60-s warm-up
POLICY_S = 20.0  # the resume policy's healthy time


@pytest.mark.parametrize(("short_pause_s", "warm_up"), [(None, False), (15.0, True)],
                         ids=["default-no-warm-up", "15s-warm-up"])
def test_a_glitch_the_policy_resumes_is_not_a_long_pause(tmp_path: Path, short_pause_s: float | None,
                                                         warm_up: bool) -> None:
    cfg = harness_protocol_config(4, warmup_s=WARMUP_S)
    if short_pause_s is not None:
        cfg = dataclasses.replace(cfg, short_pause_s=short_pause_s)
    out = run_session(tmp_path, at_time_s=T_FAULT, fault="device:heartbeat_lost", fault_s=0.5,
                      resume_after_s=1e6, n_evaluations=4, warmup_s=WARMUP_S, auto_resume_s=POLICY_S,
                      protocol=SessionProtocol(cfg))
    events = read_log(out.log).data("/events")
    assert any(e["kind"] == "resume" and e["message"].startswith("resumed by the resume policy")
               for e in events)
    (recovery,) = [e for e in events if e["kind"] == "recovery"]
    # The pause on the breath clock (3-s breaths): the detection and the policy's wait.
    assert POLICY_S - 3.0 <= recovery["details"]["pause_s"] <= 30.0
    assert recovery["details"]["warm_up"] is warm_up
    assert out.summary["n_evaluations"] >= 4
