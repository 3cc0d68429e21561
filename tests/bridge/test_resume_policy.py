"""A pause can end: the resume policy of headless runs, and no whole-heap
garbage collection while a device is connected."""

from __future__ import annotations

import itertools
from pathlib import Path

from supervision_harness import run_session

from bridge.supervisor import SupervisorState


def _kinds(out) -> list[str]:
    return [e.split(":")[0] for e in out.session.status.events]


def test_the_pause_between_the_bouts_ends_by_the_policy_without_a_full_collection(tmp_path: Path) -> None:
    out = run_session(tmp_path, n_evaluations=4, pause_between_bouts=True, auto_resume_s=2.0)
    assert out.summary["n_evaluations"] >= 4
    assert out.session.collector.stats.full == 0
    assert out.session.supervisor.state is not SupervisorState.STOPPED
    times = [t for t, what, _ in out.device.transcript if what == "commit"]
    # The bout pause lasted at least the policy's healthy time before the next commit.
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) >= 2.0


def test_a_lost_heartbeat_resumes_by_itself_once_healthy(tmp_path: Path) -> None:
    out = run_session(tmp_path, at_time_s=10.0, fault="heartbeat_loss", n_evaluations=4,
                      resume_after_s=1e6, auto_resume_s=1.0)
    assert out.device.violations == []
    assert out.summary["n_evaluations"] >= 4
    assert out.session._auto_resumes == 1


def test_an_operator_pause_waits_for_the_operator(tmp_path: Path) -> None:
    out = run_session(tmp_path, at_time_s=10.0, fault="pause", n_evaluations=4,
                      resume_after_s=30.0, auto_resume_s=0.5)
    assert out.session._auto_resumes == 0
    t_pause = 10.0
    first_commit_after = min(t for t, w, _ in out.device.transcript if w == "commit" and t > t_pause)
    assert first_commit_after >= t_pause + 30.0


def test_when_the_automatic_resumes_are_used_up_the_session_stops(tmp_path: Path) -> None:
    out = run_session(tmp_path, n_evaluations=8, pause_between_bouts=True, auto_resume_s=0.5,
                      max_auto_resumes=1, at_time_s=15.0, fault="heartbeat_loss", resume_after_s=1e6)
    assert out.session._auto_resumes == 1
    assert out.session.supervisor.state is SupervisorState.STOPPED
    assert any("automatic resumes used" in e for e in out.session.status.events)


def test_a_cart_restart_costs_at_most_the_evaluation_in_progress(tmp_path: Path) -> None:
    out = run_session(tmp_path, n_evaluations=8, cart_restart_at_s=16.0)
    assert out.session._breaths.reanchors == 1
    # Only the breaths that confirmed the new clock were rejected; the rest reached the session.
    assert out.cart.validator.rejected == 2
    reanchor = [e for e in out.events if e.startswith("cart clock clock_reset")]
    assert len(reanchor) == 1
    after = out.events[out.events.index(reanchor[0]):]
    # The evaluation in progress is measured again, the session never pauses, and it ends
    # with its budget spent like a session without the restart.
    assert sum("abandoned by the cart's clock re-anchoring" in e for e in out.events) == 1
    assert not any(e.startswith("pause") or "paused" in e for e in out.events)
    assert any(e.startswith("eval ") for e in after)
    assert any(e.startswith("session time spent") for e in out.events)
