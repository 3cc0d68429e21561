"""A session's walking time starts once its proposal worker answers (bridge/runtime.py).

The worker process's start (numpy, scipy: seconds on a busy host) is the bridge's start, not
walked session time: at ``hilbo sim --speed max`` it used to eat minutes of the session's budget.
"""

from __future__ import annotations

from pathlib import Path

from supervision_harness import BREATH_S, Outcome, run_session

from bridge.log.reader import read_log


def logged_events(out: Outcome) -> list[object]:
    """The session's /events records (typed)."""
    return read_log(out.log).records("/events")


def test_breaths_before_the_worker_answers_are_not_session_time(tmp_path: Path) -> None:
    prompt = run_session(tmp_path, n_evaluations=3)
    # The cart's breaths come at 3, 6, ... 30 s of loop time: ten of them before the worker.
    slow = run_session(tmp_path, n_evaluations=3, worker_start_s=10 * BREATH_S + 1.5)

    kinds = [e.kind for e in logged_events(slow)]
    assert "breaths_before_start" not in [e.kind for e in logged_events(prompt)]
    (before,) = [e for e in logged_events(slow) if e.kind == "breaths_before_start"]
    assert before.details == {"n_breaths": 10}, before
    assert kinds.index("breaths_before_start") < kinds.index("budget_spent")
    # The same session after the wait: the same walked time, breath for breath.
    assert slow.summary["walking"] == prompt.summary["walking"]
    assert slow.summary["n_evaluations"] == prompt.summary["n_evaluations"] == 3
    assert slow.summary["n_breaths"] == prompt.summary["n_breaths"] + 10
    assert any("starting the proposal worker" in e for e in slow.events)
    # Session times (records, status) stay seconds since the log's first breath, as `hilbo
    # review` reads them: the same evaluations, 10 breaths later.
    assert [(e["t_start"] - 10 * BREATH_S, e["t_end"] - 10 * BREATH_S)
            for e in slow.summary["evaluations"]] == \
        [(e["t_start"], e["t_end"]) for e in prompt.summary["evaluations"]]
