"""``hilbo review`` says what the session did: the estimator it used by name, the threshold it
stopped on (floored by the sound rule), the recommendation apart from the best raw estimate,
evaluations counted from 1 in the CSVs as in the report, the pauses on the timeline, and the
minutes walked the session itself counted."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from supervision_harness import Outcome, run_session

import bridge.review.plots as plots
from bridge.review.command import review_session
from bridge.review.report import write_compare_report
from bridge.review.session import load_session

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def paused(tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    """A short session (2 exploration points, then optimisation) paused by the operator at 45 s
    for about 12 s."""
    return run_session(tmp_path_factory.mktemp("paused"), n_evaluations=8, at_time_s=45.0, fault="pause",
                       resume_after_s=12.0)


def figures(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Keep each figure the review draws, by file name."""
    drawn: dict[str, Any] = {}
    save = plots._save

    def keep(fig: Any, path: Path, mode: int) -> Path:
        drawn[path.name] = fig
        return save(fig, path, mode)

    monkeypatch.setattr(plots, "_save", keep)
    return drawn


def legend(fig: Any) -> list[str]:
    return [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]


def test_the_review_names_the_estimator_and_marks_the_pauses(paused: Outcome, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    drawn = figures(monkeypatch)
    result = review_session([paused.log], tmp_path / "r")
    s = result.session
    assert s.estimator_label.startswith("transition estimate")
    labels = legend(drawn["timeline.png"])
    assert not any("UKF" in t for t in labels)
    assert any(t.startswith("transition estimate") for t in labels)
    # The operator's pause, from its pause event to its resume, shaded on the timeline.
    assert len(s.pauses) >= 1
    (t0, t1) = s.pauses[0]
    assert t1 is not None and t1 - t0 >= 10.0
    assert "paused (assistance off)" in labels
    md = (result.out_dir / "report.md").read_text()
    assert "UKF" not in md.split("## Configuration")[0]
    assert "estimator: transition estimate" in md and "1 pause (" in md


def test_the_threshold_plot_draws_the_threshold_the_session_used(paused: Outcome, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    drawn = figures(monkeypatch)
    result = review_session([paused.log], tmp_path / "r")
    s = result.session
    assert s.threshold_floor == 1.0 and s.thresholds is not None
    ax = drawn["thresholds.png"].axes[0]
    used = next(ln for ln in ax.get_lines() if ln.get_label().startswith("threshold used"))
    raw = next(ln for ln in ax.get_lines() if ln.get_label().startswith("Algorithm 2's A (before"))
    np.testing.assert_allclose(used.get_ydata(), np.maximum(s.thresholds.thresholds, 1.0))
    np.testing.assert_allclose(raw.get_ydata(), s.thresholds.thresholds)
    report = (result.out_dir / "report.md").read_text()
    assert "max(A_i, 1)" in report
    # The default rule's sequential boundary: the floor is the late level, higher before 60 s.
    assert s.boundary_s == 60.0
    assert "before 60 s in a setting the floor was 1·sqrt(60 s / t)" in report


def test_best_so_far_and_the_recommendation_are_told_apart(paused: Outcome, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    drawn = figures(monkeypatch)
    result = review_session([paused.log], tmp_path / "r")
    s = result.session
    labels = legend(drawn["best_so_far.png"])
    assert "best so far (lowest raw estimate)" in labels
    lowest = min(e.mean_w for e in s.evaluations)
    assert s.recommended is not None
    differs = not np.isclose(lowest, s.recommended.mean_w, rtol=1e-9)
    assert any("differs from the best raw estimate" in t for t in labels) == differs
    assert ("differs from the recommendation" in (result.out_dir / "report.md").read_text()) == differs


def test_the_csvs_count_evaluations_from_1_as_the_report(paused: Outcome, tmp_path: Path) -> None:
    result = review_session([paused.log], tmp_path / "r")
    n = len(result.session.evaluations)
    with open(result.out_dir / "evaluations.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["evaluation"]) for r in rows] == list(range(1, n + 1))
    assert [int(r["index"]) for r in rows] == list(range(n))
    with open(result.out_dir / "breaths.csv", newline="") as f:
        breaths = [r for r in csv.DictReader(f) if r["evaluation"]]
    assert {int(b["evaluation"]) for b in breaths} <= set(range(1, n + 1))
    assert all(int(b["evaluation"]) == int(b["index"]) + 1 for b in breaths)
    assert min(int(b["breath_in_evaluation"]) for b in breaths) == 1
    md = (result.out_dir / "report.md").read_text()
    table = md.split("## Evaluations", 1)[1].split("\n## ", 1)[0]
    assert f"| {n} |" in table and "| 0 |" not in table.split("\n")[2][:6]


def test_minutes_walked_are_the_sessions_own(tmp_path: Path) -> None:
    # Breaths logged while the proposal worker started are not walked session time: the log's
    # last breath is 30 s later than what the session counted.
    out = run_session(tmp_path, n_evaluations=6, worker_start_s=31.5)
    s = load_session([out.log])
    own = out.summary["walking"]["session_s"] / 60.0
    assert s.breaths[-1].time_s / 60.0 > own + 0.4
    assert s.minutes_walked == pytest.approx(own)
    png = tmp_path / "compare.png"
    png.write_bytes(b"")  # the plot is not what this test reads
    md, _ = write_compare_report([s, s], tmp_path, png)
    table = md.read_text().split("## Key numbers", 1)[1]
    assert f"| minutes walked | {own:.1f} | {own:.1f} |" in table
