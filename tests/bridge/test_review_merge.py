"""hilbo review of a session resumed after a crash: both files merge, every evaluation once.

The logs are written the way the bridge writes them (SessionLog + HILOptimizer, as in
test_resume.py) with a cheap estimator and a synthetic wearer, so no devices are needed.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from bridge.log import SessionLog
from bridge.log.reader import read_log
from bridge.log.resume import rebuild_optimizer
from bridge.review.command import review_session
from bridge.review.session import load_session
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer
from hilbo_core.presets import hip_6d
from hilbo_core.types import BreathRecord

SPACE = hip_6d()
N_EXPLORE = 3


def estimator() -> GaussianProductEstimator:
    return GaussianProductEstimator(prior_mean=400.0, prior_var=100.0**2, meas_var=40.0**2)


def make() -> HILOptimizer:
    # A measured setting is recommended (recommend = "posterior"), so the force-feedback plot has
    # an evaluation to look for; the default's global recommendation may be a setting never
    # measured when nothing confirmed it.
    return HILOptimizer(SPACE, estimator_factory=estimator, n_explore=N_EXPLORE, max_breaths=5, window=1,
                        budget_breaths=14, seed=5, n_candidates=64, n_local=1, recommend="posterior")


def watts(k: int, b: int, params: dict[str, float]) -> float:
    u = SPACE.to_unit(SPACE.from_dict(params))
    cost = 300.0 + 400.0 * float(np.sum((u - 0.5) ** 2))
    return cost + float(np.random.default_rng([11, k, b]).normal(0.0, 40.0))


def drive(opt: HILOptimizer, log: SessionLog, sizes: list[tuple[str, int, int]]) -> None:
    """The session to its end as the bridge logs it; ``sizes`` gets (kind, index, file size)."""
    t_cart = 1000.0
    log.log_breath(BreathRecord(t_s=t_cart, vo2_ml_min=1200.0, vco2_ml_min=1000.0))  # warm-up breath
    while not opt.done:
        k = len(opt.evaluations)
        params = opt.ask()
        log.log_proposal(params, index=k, phase=opt.phase.value, incumbent=opt.incumbent)
        t0 = t_cart
        b = 0
        while True:
            t_cart += 3.0
            w = watts(k, b, params)
            log.log_breath(BreathRecord(t_s=t_cart, vo2_ml_min=w * 3.0, vco2_ml_min=w * 0.5))
            step = opt.observe_breath(t_cart - t0, w)
            log.log_step(step, index=k, t_setting_s=t_cart - t0, watts=w, t_s=t_cart, incumbent=opt.incumbent)
            b += 1
            if step.stop:
                sizes.append(("last_breath", k, log.path.stat().st_size))
                log.log_observation(step.evaluation, t_start=t0 - 1000.0, t_end=t_cart - 1000.0, t_s=t_cart)
                log.log_optimizer_state(opt, reason="evaluation", t_s=t_cart)
                sizes.append(("snapshot", k, log.path.stat().st_size))
                break


def session_log(path: Path, previous: Path | None = None) -> SessionLog:
    config = {"session": {"subject": "synthetic"},
              "protocol": {"n_explore": N_EXPLORE, "max_breaths": 5, "window": 1}}
    return SessionLog(path, session_id="sess", config_json=config, previous_log=previous,
                      flush_interval_s=None, param_names=SPACE.names)


@pytest.fixture(scope="module")
def full(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[tuple[str, int, int]], list[dict]]:
    path = tmp_path_factory.mktemp("review-merge") / "full.mcap"
    sizes: list[tuple[str, int, int]] = []
    opt = make()
    with session_log(path) as log:
        log.log_optimizer_state(opt, reason="start")
        drive(opt, log, sizes)
    evs = [e.to_json() for e in opt.evaluations]
    assert len(evs) > N_EXPLORE + 2
    return path, sizes, evs


def crash_and_resume(full_log: Path, cut_at: int, tmp_path: Path) -> tuple[Path, Path, HILOptimizer]:
    crashed = tmp_path / "crashed.mcap"
    crashed.write_bytes(full_log.read_bytes()[:cut_at])
    opt, _ = rebuild_optimizer(crashed, estimator_factory=estimator)
    resumed = tmp_path / "resumed.mcap"
    with session_log(resumed, previous=crashed) as log:
        log.log_optimizer_state(opt, reason="resume")
        drive(opt, log, [])
    return crashed, resumed, opt


def size_at(sizes: list[tuple[str, int, int]], kind: str, k: int) -> int:
    return next(s for kd, i, s in sizes if kd == kind and i == k)


def test_both_files_merge_in_order_with_every_evaluation_once(full, tmp_path: Path) -> None:
    path, sizes, evs = full
    crashed, resumed, final = crash_and_resume(path, size_at(sizes, "snapshot", N_EXPLORE), tmp_path)
    n_old = len(read_log(crashed).data("/observations"))
    assert 0 < n_old < len(evs)
    # Given in the wrong order: the previous_log link orders them.
    result = review_session([resumed, crashed], tmp_path / "out")
    s = result.session
    assert [f.path for f in s.files] == [str(crashed), str(resumed)]
    assert [e.index for e in s.evaluations] == list(range(len(final.evaluations)))
    assert [e.file for e in s.evaluations] == [0] * n_old + [1] * (len(evs) - n_old)
    for row, ev in zip(s.evaluations, final.evaluations, strict=True):
        assert row.params == ev.params and row.mean_w == ev.mean and row.breaths == ev.breaths
    # The second file is laid after the first on the session-time axis.
    assert s.files[1].offset_s == pytest.approx(s.files[0].offset_s + s.files[0].duration_s)
    t_end = [e.t_end_s for e in s.evaluations]
    assert t_end == sorted(t_end) and t_end[n_old] > s.files[1].offset_s
    assert any(e.kind == "resumed" for e in s.events) and any(e.kind == "log_cut_off" for e in s.events)
    with open(result.out_dir / "evaluations.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["evaluation"]) for r in rows] == list(range(1, len(evs) + 1))
    assert [int(r["index"]) for r in rows] == list(range(len(evs)))
    with open(result.out_dir / "breaths.csv", newline="") as f:
        breaths = list(csv.DictReader(f))
    assert len(breaths) == len(read_log(crashed).data("/breaths")) + len(read_log(resumed).data("/breaths"))
    assert [r["log"] for r in breaths].count("resumed.mcap") == len(read_log(resumed).data("/breaths"))


def test_an_evaluation_completed_only_by_the_replay_comes_from_the_snapshot(full, tmp_path: Path) -> None:
    path, sizes, _ = full
    k = N_EXPLORE + 1
    # Cut after evaluation k's last breath, before its /observations message: the resume's
    # replay completes it; only the resumed file's snapshot knows it as an evaluation.
    crashed, resumed, final = crash_and_resume(path, size_at(sizes, "last_breath", k), tmp_path)
    assert [o["index"] for o in read_log(crashed).data("/observations")] == list(range(k))
    s = load_session([crashed, resumed])
    assert [e.index for e in s.evaluations] == list(range(len(final.evaluations)))
    row = s.evaluations[k]
    assert row.source == "snapshot" and row.file == 0 and row.mean_w == final.evaluations[k].mean
    assert row.t_end_s is not None and row.t_end_s <= s.files[1].offset_s
    assert sum(t.completed for t in s.traces) == len(s.evaluations)


def test_a_log_without_force_feedback_skips_that_plot_and_says_so(full, tmp_path: Path) -> None:
    path, _, evs = full
    result = review_session([path], tmp_path / "one")
    assert "force_tracking" in result.skipped and not (result.out_dir / "force_tracking.png").exists()
    report = (result.out_dir / "report.md").read_text()
    assert "Force tracking of the recommended setting: not drawn" in report
    assert "no /profiles_sent message" in report
    assert len(result.session.evaluations) == len(evs)
    # Recommended = the optimizer's own best() at the end of the session.
    opt = HILOptimizer.from_json(read_log(path).data("/optimizer_state")[-1]["state"])
    params, mean, _ = opt.best()
    assert result.session.recommended is not None
    assert result.session.recommended.params == params and result.session.recommended.mean_w == mean


def test_only_the_new_file_notes_the_missing_old_one(full, tmp_path: Path) -> None:
    path, sizes, _ = full
    _, resumed, final = crash_and_resume(path, size_at(sizes, "snapshot", N_EXPLORE), tmp_path)
    s = load_session([resumed])
    assert any("which was not given" in n for n in s.notes)
    # Evaluations of the old file are known from the resume snapshot (without times).
    assert [e.index for e in s.evaluations] == list(range(len(final.evaluations)))
    assert {e.source for e in s.evaluations[: N_EXPLORE + 1]} == {"snapshot"}


def test_without_snapshots_the_schedule_is_computed_from_the_exploration_estimates(
        full, tmp_path: Path) -> None:
    path, _, evs = full
    logged = load_session([path])
    assert logged.thresholds is not None and "logged" in logged.thresholds.source
    # The same session without its /optimizer_state snapshots.
    bare = tmp_path / "bare.mcap"
    with session_log(bare) as log:
        for m in read_log(path).messages:
            if m.topic not in ("/config", "/optimizer_state"):
                log.log(m.topic, m.data, m.publish_time_ns if m.topic != "/proposals" else None)
    s = load_session([bare])
    assert s.thresholds is not None and "computed" in s.thresholds.source
    np.testing.assert_allclose(s.thresholds.thresholds, logged.thresholds.thresholds, rtol=1e-9)
    np.testing.assert_allclose(s.thresholds.traces, logged.thresholds.traces, rtol=1e-9, atol=1e-12)
    # No optimizer state to ask: the recommendation falls back to the lowest estimate.
    assert s.recommended is not None and "lowest estimated mean" in s.recommended.method
    assert s.recommended.mean_w == min(e["mean"] for e in evs)


def test_compare_takes_a_resumed_sessions_logs_joined_by_a_comma(
        full, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from bridge.cli.main import main

    path, sizes, evs = full
    crashed, resumed, final = crash_and_resume(path, size_at(sizes, "snapshot", N_EXPLORE), tmp_path)
    out = tmp_path / "cmp"
    assert main(["review", "--compare", f"{crashed},{resumed}", str(path), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning" not in err
    md = (out / "compare.md").read_text()
    assert f"| evaluations | {len(final.evaluations)} | {len(evs)} |" in md
    # The resumed log alone is a part of its session: said, not silently compared.
    assert main(["review", "--compare", str(resumed), str(path), "--out", str(tmp_path / "cmp2")]) == 0
    err = capsys.readouterr().err
    assert f"hilbo review: warning: A ({resumed}) resumed {crashed}" in err and f"{crashed},{resumed}" in err
