"""A breath the cart passes but the estimator leaves out as implausible for the level (a 0.1x
breath in a steady walk) is counted and logged with the session's rejects, not dropped silently."""

from __future__ import annotations

from pathlib import Path

from supervision_harness import run_session

from bridge.log.reader import read_log


def _estimator_rejects(log: Path) -> list[dict]:
    return [r for r in read_log(log).data("/rejects") if r["source"] == "estimator"]


def test_an_implausible_breath_is_counted_in_the_logged_rejects(tmp_path: Path) -> None:
    out = run_session(tmp_path, n_evaluations=4, scaled_breaths={4: 0.1})
    rejects = _estimator_rejects(out.log)
    assert rejects and rejects[-1]["counts"] == {"implausible_for_level": 1}
    assert out.session.opt.flagged_breaths == 1


def test_a_steady_walk_logs_no_estimator_rejects(tmp_path: Path) -> None:
    out = run_session(tmp_path, n_evaluations=4)
    assert _estimator_rejects(out.log) == [] and out.session.opt.flagged_breaths == 0
