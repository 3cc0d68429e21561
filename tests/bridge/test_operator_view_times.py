"""The operator view's times follow every breath (bridge/runtime.py): the expected end is right
before the first optimisation evaluation ends, the optimisation minutes run on through a pause,
and a resumed session's view starts from what its log holds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from supervision_harness import harness_protocol_config, run_session

from bridge.log.resume import rebuild_optimizer
from bridge.runtime import BridgeSession
from hilbo_core.protocol import SessionProtocol

pytestmark = pytest.mark.timeout(120)


def sampler(rows: list[dict[str, Any]]) -> Any:
    """An ``on_session`` that samples the operator view's status at every breath."""
    def hook(session: BridgeSession) -> None:
        def sample(rec: Any) -> None:
            st = session.status
            rows.append({"t": rec.t_s, "evaluation": st.evaluation, "expected_end_s": st.expected_end_s,
                         "opt_s": st.budget_used_s, "paused": session.supervisor.paused,
                         "n_done": len(session.records), "best": st.best_mean_w,
                         "phase": session.protocol.phase.value})
        session.breath_listeners.append(sample)
    return hook


def test_the_expected_end_is_right_before_the_first_optimisation_evaluation_ends(tmp_path: Path) -> None:
    rows: list[dict[str, Any]] = []
    # The pause between the bouts (30 s here) is not in any estimate made before it.
    out = run_session(tmp_path, n_evaluations=5, pause_between_bouts=True, auto_resume_s=30.0,
                      on_session=sampler(rows))
    assert out.summary["n_evaluations"] >= 4
    first_opt = next(i for i, r in enumerate(rows) if r["n_done"] == 3)  # eval 3: the first optimisation one
    before, after = rows[first_opt - 1], rows[first_opt]
    assert before["phase"] == "optimization" and before["expected_end_s"] is not None
    assert before["expected_end_s"] == pytest.approx(after["expected_end_s"])
    # And from the first breath on, never "unknown".
    assert all(r["expected_end_s"] is not None for r in rows)


def test_the_optimisation_minutes_run_on_through_a_pause(tmp_path: Path) -> None:
    rows: list[dict[str, Any]] = []
    out = run_session(tmp_path, n_evaluations=8, at_time_s=45.0, fault="pause", resume_after_s=12.0,
                      on_session=sampler(rows))
    assert out.summary["n_evaluations"] >= 4
    paused = [r["opt_s"] for r in rows if r["paused"] and r["phase"] == "optimization"]
    assert len(paused) >= 3, rows
    assert paused == sorted(paused) and paused[-1] > paused[0]


def test_a_resumed_sessions_view_starts_from_the_resumed_state(tmp_path: Path) -> None:
    first = run_session(tmp_path, n_evaluations=4)
    opt, _ = rebuild_optimizer(first.log)
    n = len(opt.evaluations)
    assert n == first.summary["n_evaluations"] >= 3
    used = opt.budget_used  # as bridge/run.py resumes it
    protocol = SessionProtocol.resumed(harness_protocol_config(8), n_explored=2,
                                       optimization_used_s=float(used["seconds"]),
                                       optimization_used_breaths=int(used["breaths"]))
    rows: list[dict[str, Any]] = []
    run_session(tmp_path, n_evaluations=8, optimizer=opt, protocol=protocol, on_session=sampler(rows))
    start = rows[0]
    assert start["evaluation"] == n
    assert start["best"] is not None
    assert start["opt_s"] > 0
