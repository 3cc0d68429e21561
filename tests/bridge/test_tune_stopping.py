"""Tests for bridge.bench.tune_stopping: offline tuning of the stopping rule with BO-RESAMPLE."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from bridge.bench.tune_stopping import (
    BreathTrace,
    TuneStoppingConfig,
    add_tune_stopping_parser,
    breath_traces,
    evaluate_schedule,
    trajectories_from_log,
    tune_stopping,
)
from bridge.log import SessionLog
from hilbo_core import HILOptimizer, presets
from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.metabolic import GaussianProductEstimator


def _trace(*means: float) -> BreathTrace:
    return BreathTrace(np.array(means, dtype=float), np.ones(len(means)))


def test_evaluate_schedule_hand_made() -> None:
    a, b, c = _trace(10, 10, 10, 10), _trace(20, 20, 20, 20), _trace(30, 30, 30, 30)
    out = evaluate_schedule([a, b, c], np.zeros(4), error_weight=2.0)
    # K = 0: a never stops; b stops at breath 1 against a; c stops at breath 1 against a and b.
    # Breaths: (a,b)=4 (a,c)=4 (b,a)=1 (b,c)=4 (c,a)=1 (c,b)=1 → 15 of 24; all stops correct.
    assert out["breath_fraction"] == pytest.approx(15 / 24)
    assert out["early_stop_rate"] == pytest.approx(3 / 6)
    assert out["wrong_stop_rate"] == 0.0
    assert out["cost"] == pytest.approx(15 / 24)
    never = evaluate_schedule([a, b, c], np.full(4, 20.0), 2.0)
    assert never["breath_fraction"] == 1.0 and never["early_stop_rate"] == 0.0


def test_evaluate_schedule_counts_wrong_stops() -> None:
    # d starts high (transient) and ends best: stopping it early is wrong against b.
    b, d = _trace(20, 20, 20, 20), _trace(50, 50, 5, 5)
    out = evaluate_schedule([b, d], np.zeros(4), error_weight=3.0)
    # (b, d): 20 − 5 > 0 → stop at 1, correct (b is worse). (d, b): stop at 1, wrong.
    assert out["wrong_stop_rate"] == pytest.approx(0.5)
    assert out["cost"] == pytest.approx(0.25 + 3.0 * 0.5)
    # Per-trace schedules: row j is used for trace j.
    per = evaluate_schedule([b, d], np.array([np.zeros(4), np.full(4, 100.0)]), 3.0)
    assert per["wrong_stop_rate"] == 0.0


def _step_response(level_w: float, n: int, rng: np.random.Generator, start_w: float = 400.0) -> np.ndarray:
    t = np.cumsum(rng.uniform(2.5, 3.5, n))
    m = level_w + (start_w - level_w) * np.exp(-t / 40.0)
    return np.column_stack([t, m * (1 + 0.05 * rng.standard_normal(n))])


def test_breath_traces_skip_short_and_name_bad_ones() -> None:
    rng = np.random.default_rng(0)
    trajs = [_step_response(350, 12, rng), _step_response(380, 5, rng), _step_response(360, 15, rng)]
    traces, skipped = breath_traces(trajs, 10, lambda: GaussianProductEstimator(400.0, 1e4, 400.0))
    assert skipped == 1 and len(traces) == 2
    assert all(len(t.means) == 10 for t in traces)
    bad = _step_response(350, 12, rng)
    bad[4, 1] = np.nan
    with pytest.raises(MeasurementError, match="trajectory 1"):
        breath_traces([trajs[0], bad], 10)


@pytest.mark.parametrize("family", ["k", "window"])
def test_tune_stopping_end_to_end(family: str) -> None:
    rng = np.random.default_rng(1)
    trajs = [_step_response(lv, 10, rng) for lv in rng.uniform(320, 400, 9)]
    cfg = TuneStoppingConfig(family=family, n_max=10, n_real=6, n_resamples=2, max_reuse=2,
                             n_grid=5, max_window=3)
    res = tune_stopping(trajs, cfg)
    assert res["n_trajectories"] == 9
    key = "k" if family == "k" else "window"
    value = res["recommended"][key]
    assert (0.0 <= value <= 4.0) if family == "k" else value in range(4)
    bo = res["bo_resample"]
    assert bo["n_real"] == 6 and bo["n_simulated"] <= 2 * 6 and bo["max_trajectory_uses"] <= 2
    assert res["grid_best"]["cost"] <= min(g["cost"] for g in res["grid"]) + 1e-12
    assert res["never_stop"]["breath_fraction"] == 1.0
    assert 0.0 <= res["algorithm2"]["wrong_stop_rate"] <= 1.0
    json.dumps(res)  # JSON-able


def test_tune_stopping_needs_enough_trajectories() -> None:
    rng = np.random.default_rng(2)
    with pytest.raises(ConfigError, match="at least 3"):
        tune_stopping([_step_response(350, 10, rng)] * 2, TuneStoppingConfig(n_max=10))
    with pytest.raises(ConfigError, match="error_weight"):
        TuneStoppingConfig(error_weight=-1.0)


def _write_log(path: Path, session_id: str = "t", validation: bool = False) -> None:
    """A tiny session (N = 4) written the way the bridge writes it (``validation``: with a
    validation walk's plan event)."""
    opt = HILOptimizer(presets.hip_6d(), n_explore=3, max_breaths=4, window=1, budget_breaths=8,
                       seed=1, n_candidates=32, n_local=0,
                       estimator_factory=lambda: GaussianProductEstimator(400.0, 1e4, 1600.0))
    rng = np.random.default_rng(3)
    with SessionLog(path, session_id=session_id, config_json={}, flush_interval_s=None) as log:
        if validation:
            log.log_event("validation_plan", "validation walk", conditions=[], source_log=None)
        k = 0
        while not opt.done:
            opt.ask()
            b = 0
            while True:
                t, w = 3.0 * (b + 1), float(rng.uniform(350, 450))
                step = opt.observe_breath(t, w)
                log.log_step(step, index=k, t_setting_s=t, watts=w)
                b += 1
                if step.stop:
                    log.log_observation(step.evaluation)
                    break
            k += 1


def test_trajectories_from_log_and_cli(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    _write_log(path)
    trajs, evs = trajectories_from_log(path)
    assert len(trajs) == len(evs) >= 4
    for tr, ev in zip(trajs, evs, strict=True):
        assert tr.shape == (ev.breaths, 2)
        assert np.all(np.diff(tr[:, 0]) > 0)
    parser = argparse.ArgumentParser()
    add_tune_stopping_parser(parser.add_subparsers())
    out = tmp_path / "tuned.json"
    args = parser.parse_args(["tune-stopping", str(path), "--real", "3", "--resamples", "1",
                              "--max-reuse", "1", "--out", str(out)])
    assert args.func(args) == 0
    res = json.loads(out.read_text())
    assert res["config"]["n_max"] == 4  # taken from the log's full-length evaluations
    assert res["n_trajectories"] >= 3


def test_each_evaluation_is_counted_once_and_validation_walks_are_left_out(tmp_path: Path) -> None:
    from bridge.bench.tune_stopping import collect_trajectories

    a, copy, other, walk = (tmp_path / f"{n}.mcap" for n in ("a", "a.recovered", "b", "walk"))
    _write_log(a)
    copy.write_bytes(a.read_bytes())  # what `hilbo log recover` leaves beside a cut log
    _write_log(other, session_id="other")
    _write_log(walk, session_id="walk", validation=True)
    one, _ = trajectories_from_log(a)
    trajs, evs, sources, notes = collect_trajectories([a, copy, other, walk])
    assert len(trajs) == len(evs) == len(sources) == 2 * len(one)
    assert not any(src.startswith(("a.recovered.mcap", "walk.mcap")) for src in sources)
    assert any("a.recovered.mcap" in n and "counted once" in n for n in notes)
    assert any(n == "walk.mcap: a validation walk, left out" for n in notes)


def test_cli_tunes_the_sound_rules_floors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "s.mcap"
    _write_log(path)
    parser = argparse.ArgumentParser()
    add_tune_stopping_parser(parser.add_subparsers())
    out = tmp_path / "sound.json"
    args = parser.parse_args(["tune-stopping", str(path), "--family", "sound", "--real", "3",
                              "--resamples", "1", "--max-reuse", "1", "--out", str(out)])
    assert args.func(args) == 0
    res = json.loads(out.read_text())
    assert res["config"]["n_max"] == 4 and res["n_trajectories"] >= 3
    assert set(res["recommended"]) == {"min_decision_s", "a_floor"}
    assert 20.0 <= res["recommended"]["min_decision_s"] <= 120.0
    # 4 breaths of 3 s never reach a 30 s time floor: every grid point uses all N breaths.
    assert {g["mean_breaths"] for g in res["grid"]} == {4.0}
    assert "the grid's best: no decision before" in capsys.readouterr().err


def test_cli_sound_needs_full_length_evaluations(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    _write_log(path)  # N = 4: no evaluation has 60 breaths
    parser = argparse.ArgumentParser()
    add_tune_stopping_parser(parser.add_subparsers())
    args = parser.parse_args(["tune-stopping", str(path), "--family", "sound", "--n-max", "60"])
    with pytest.raises(ConfigError, match=r"need >= 3 trajectories of >= 60 breaths, got 0 \(\d+ shorter\)$"):
        args.func(args)
