"""Tests for bridge.bench.tutor (``hilbo bench tutor``) at a toy size."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from bridge.bench.tutor import (
    TutorBenchConfig,
    add_tutor_bench_parser,
    bkt_threshold_reference,
    run_tutor_bench,
    run_tutor_repetition,
)
from hilbo_core.errors import ConfigError
from hilbo_core.studies.tutor import FIG7_STUDENTS, best_count_policy

TOY = TutorBenchConfig(figures=("fig9",), students=4, repetitions=2, resamples=2, max_reuse=2,
                       t_max=5, seed=3)


def test_repetition_is_deterministic_and_bounded() -> None:
    a = run_tutor_repetition("fig9", 0, TOY)
    b = run_tutor_repetition("fig9", 0, TOY)
    assert a == b
    for method, costs in a["costs"].items():
        assert len(costs) == TOY.students, method
        assert all(0.0 <= c <= 1.0 for c in costs)
    rs = a["details"]["bo_resample"]
    assert rs["n_simulated"] <= TOY.resamples * TOY.students
    assert rs["max_trajectory_uses"] <= TOY.max_reuse
    assert a["details"]["bo"]["n_simulated"] == 0


def test_bench_writes_json_and_plot(tmp_path: Path) -> None:
    res = run_tutor_bench(TOY, tmp_path)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["figures"]["fig9"]["methods"].keys() == {"bo", "bo_resample", "fit_threshold"}
    fig = res["figures"]["fig9"]
    for m in fig["methods"].values():
        assert len(m["mean"]) == TOY.students and len(m["final_values"]) == TOY.repetitions
        # No recommended policy can beat the best policy of its class.
        assert min(m["final_values"]) >= fig["best_afm_cost"] - 1e-12
    assert (tmp_path / "tutor_fig9.png").stat().st_size > 1000


def test_reference_lines() -> None:
    thr, cost = bkt_threshold_reference(FIG7_STUDENTS, 10)
    _, best_afm = best_count_policy(FIG7_STUDENTS, 10)
    # Antonova 2016 §4.1: the best AFM threshold policy ties with the best BKT threshold policy.
    assert cost == pytest.approx(1.0 - best_afm, abs=1e-9)  # at t_max = 10 exactly
    assert 0.0 < thr < 1.0


def test_cli_parser_runs(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_tutor_bench_parser(parser.add_subparsers())
    args = parser.parse_args(["tutor", "--figures", "fig7", "--students", "3", "--reps", "1",
                              "--resamples", "1", "--max-reuse", "1", "--t-max", "4",
                              "--out", str(tmp_path)])
    assert args.func(args) == 0
    assert (tmp_path / "tutor_fig7.png").exists()


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="figures"):
        TutorBenchConfig(figures=("fig8",))
    with pytest.raises(ConfigError, match="students"):
        TutorBenchConfig(students=1)
