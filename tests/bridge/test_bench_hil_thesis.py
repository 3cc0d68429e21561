"""The Antonova 2016 methods of ``hilbo bench hil`` at toy size: sessions, tuning K, comparisons, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from bridge.bench.cli import bench_main
from bridge.bench.hil import (
    ABLATION_METHODS,
    DEFAULT_HIL_METHODS,
    HIL_METHODS,
    THESIS_METHODS,
    HilProtocol,
    HilTask,
    hil_comparisons,
    hil_table,
    run_hil_task,
    run_training_session,
    tune_constant_k,
)
from bridge.bench.hil import _thesis_arm as _thesis_arm  # the method → session mapping
from bridge.bench.thesis_session import Arm, run_session
from hilbo_core.errors import ConfigError

# The Antonova 2016 methods run on the legacy wearer (bridge/bench/thesis_session.py builds it).
TOY = HilProtocol(minutes=5.5, warmup_s=30.0, n_explore=2, max_breaths=5, condition_s=30.0, popsize=4,
                  bout1_conditions=4, grid_min=0.5, wearer="legacy")
# The feature kernel costs ~1 s per proposal (profiles of every EI candidate): a shorter session.
TINY = HilProtocol(minutes=1.5, warmup_s=10.0, n_explore=2, max_breaths=3, condition_s=20.0, popsize=2,
                   bout1_conditions=2, grid_min=0.5, wearer="legacy")
RESULT_KEYS = {"method", "space", "seed", "trace", "baseline_cost_w", "optimum_cost_w", "final_regret_w",
               "final_regret_pct", "evaluations_per_hour", "n_evaluations", "n_evaluations_bout2",
               "early_stops", "assisted_s", "bout2_s", "session_s", "n_explore", "n_priors", "stopping_k",
               "wall_s"}


def _check_session(r: dict, proto: HilProtocol) -> None:
    assert RESULT_KEYS <= set(r)
    assert r["n_evaluations"] == len(r["trace"]) > r["n_explore"]
    assert r["n_evaluations_bout2"] == r["n_evaluations"] - r["n_explore"]
    times = [t for t, _ in r["trace"]]
    assert times == sorted(times) and all(math.isfinite(g) and g >= -1e-9 for _, g in r["trace"])
    assert r["session_s"] <= proto.minutes * 60.0 + 15.0  # the last breath may overrun a little
    assert r["final_regret_w"] == r["trace"][-1][1]
    json.dumps(r)


def test_method_lists() -> None:
    assert DEFAULT_HIL_METHODS == ("sound", "adaptive", "fixed", "cmaes", "random")
    # adaptive-ahead: adaptive with the hyperparameters fitted ahead, as the bridge runs it.
    # The default's ablations and the fast protocol's other candidates (docs/hour_answer.md).
    assert set(HIL_METHODS) == (set(DEFAULT_HIL_METHODS) | set(THESIS_METHODS) | {"adaptive-ahead"}
                                | set(ABLATION_METHODS))


def test_day_one_of_the_shared_session_code_is_the_adaptive_session() -> None:
    adaptive = run_hil_task(HilTask("adaptive", "hip_6d", 3, TOY))
    day1 = run_session(3, Arm("day1", n_explore=TOY.n_explore, window=TOY.window), minutes=TOY.minutes,
                       max_breaths=TOY.max_breaths, warmup_s=TOY.warmup_s)
    assert [t for t, _ in day1["regret_trace"]] == [t for t, _ in adaptive["trace"]]
    assert day1["regret_trace"][-1][1] == pytest.approx(adaptive["final_regret_w"])


@pytest.mark.slow  # six toy sessions (two per prior method): ~15-35 s on a busy 2-core machine
def test_prior_methods_run_day_two_with_day_one_as_the_prior() -> None:
    day2 = run_hil_task(HilTask("adaptive-day2", "hip_6d", 3, TOY))
    prior = run_hil_task(HilTask("adaptive-prior", "hip_6d", 3, TOY))
    e3 = run_hil_task(HilTask("adaptive-prior-e3", "hip_6d", 3, TOY))
    for r in (day2, prior, e3):
        _check_session(r, TOY)
    assert day2["n_priors"] == 0 and "day1_wall_s" not in day2
    assert prior["n_priors"] == prior["day1_n_evaluations"] == e3["n_priors"] > TOY.n_explore
    assert prior["n_explore"] == TOY.n_explore and e3["n_explore"] == 3
    assert prior["day1_final_regret_w"] == e3["day1_final_regret_w"]
    assert prior["wall_s"] >= prior["day1_wall_s"]
    # Same wearer, a new breath stream: day 2 is not a replay of day 1.
    assert day2["trace"] != run_hil_task(HilTask("adaptive", "hip_6d", 3, TOY))["trace"]


def test_tuned_k_method_uses_the_given_constant() -> None:
    low = run_hil_task(HilTask("adaptive-tuned-k", "hip_ankle_4d", 2, TOY, stopping_k=0.0))
    high = run_hil_task(HilTask("adaptive-tuned-k", "hip_ankle_4d", 2, TOY, stopping_k=3.0))
    for r in (low, high):
        _check_session(r, TOY)
    assert (low["stopping_k"], high["stopping_k"]) == (0.0, 3.0)
    # A lower threshold stops more settings early.
    assert low["early_stops"] / low["n_evaluations"] >= high["early_stops"] / high["n_evaluations"]


@pytest.mark.slow  # a feature-kernel session: ~10 s on a busy 2-core machine
def test_feature_kernel_method() -> None:
    r = run_hil_task(HilTask("adaptive-features", "hip_6d", 1, TINY))
    _check_session(r, TINY)
    assert r["n_priors"] == 0 and r["stopping_k"] is None
    # adaptive-features-only is the same session code with the profile features alone.
    assert _thesis_arm(HilTask("adaptive-features-only", "hip_6d", 1, TINY)).feature == "profile"
    assert _thesis_arm(HilTask("adaptive-features", "hip_6d", 1, TINY)).feature == "profile+raw"


def test_task_validation() -> None:
    with pytest.raises(ConfigError, match="adaptive-tuned-k needs stopping_k"):
        HilTask("adaptive-tuned-k", "hip_6d", 1, TOY)
    with pytest.raises(ConfigError, match="adaptive-tuned-k needs stopping_k"):
        HilTask("adaptive-tuned-k", "hip_6d", 1, TOY, stopping_k=-1.0)
    with pytest.raises(ConfigError, match=r"stopping_k=1\.0 is only for adaptive-tuned-k, not 'adaptive'"):
        HilTask("adaptive", "hip_6d", 1, TOY, stopping_k=1.0)
    with pytest.raises(ConfigError, match="feature='dog'"):
        Arm("x", feature="dog")
    # bridge/bench/thesis_session.py builds the legacy wearer: the realistic one is refused by name.
    with pytest.raises(ConfigError, match=r"adaptive-day2 run on the legacy wearer only .*'realistic'"):
        HilTask("adaptive-day2", "hip_6d", 1, dataclasses.replace(TOY, wearer="realistic"))


def test_thesis_methods_on_the_realistic_wearer_exit_2_before_any_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert bench_main(["hil", "--methods", "adaptive,adaptive-tuned-k", "--subjects", "2",
                       "--out", str(out)]) == 2
    assert "adaptive-tuned-k run on the legacy wearer only" in capsys.readouterr().err
    assert not out.exists()


def test_tune_constant_k_on_training_trajectories() -> None:
    trajs = [t for s in (101, 102) for t in run_training_session(HilTask("adaptive", "hip_6d", s, TOY))]
    assert len(trajs) >= 3 and all(len(t) == TOY.max_breaths for t in trajs)
    bo = tune_constant_k(trajs, TOY, pick="bo", n_real=5)
    grid = tune_constant_k(trajs, TOY, pick="grid", n_real=5)
    assert bo["k"] == bo["recommended"]["k"] and grid["k"] == grid["grid_best"]["k"]
    assert 0.0 <= bo["k"] <= 4.0 and bo["n_trajectories"] == len(trajs)
    assert grid["grid_best"]["cost"] <= grid["algorithm2"]["cost"] + 1.0
    json.dumps(bo)
    with pytest.raises(ConfigError, match="pick='best'"):
        tune_constant_k(trajs, TOY, pick="best")


def test_comparisons_include_method_minus_adaptive_and_prior_minus_day2() -> None:
    def rec(method: str, seed: int, trace: list[list[float]]) -> dict:
        return {"method": method, "space": "hip_6d", "seed": seed, "trace": trace,
                "final_regret_w": trace[-1][1]}

    results = [rec("random", 1, [[60.0, 30.0]]), rec("random", 2, [[60.0, 30.0]]),
               rec("adaptive", 1, [[600.0, 10.0], [1500.0, 8.0]]), rec("adaptive", 2, [[600.0, 20.0]]),
               rec("adaptive-day2", 1, [[600.0, 12.0]]), rec("adaptive-day2", 2, [[600.0, 14.0]]),
               rec("adaptive-prior", 1, [[300.0, 4.0], [1500.0, 2.0]]), rec("adaptive-prior", 2,
                                                                              [[300.0, 30.0]])]
    methods = ["random", "adaptive", "adaptive-day2", "adaptive-prior"]
    comps = hil_comparisons(results, ["hip_6d"], methods, at_minutes=(5.0, 20.0))
    pairs = [(c["method"], c["baseline"]) for c in comps]
    assert pairs == [("adaptive", "random"), ("adaptive-day2", "random"), ("adaptive-prior", "random"),
                     ("random", "adaptive"), ("adaptive-day2", "adaptive"), ("adaptive-prior", "adaptive"),
                     ("adaptive-prior", "adaptive-day2")]
    c = comps[pairs.index(("adaptive-prior", "adaptive"))]
    assert c["n_subjects"] == 2 and c["final_regret_diff_w_mean"] == pytest.approx(((2 - 8) + (30 - 20)) / 2)
    assert c["frac_lower"] == 0.5
    # @5 min adaptive has no recommendation yet (first at 10 min): not comparable.
    assert c["at_minutes"] == [5.0, 20.0] and c["regret_diff_w_mean_at"][0] is None
    assert c["regret_diff_w_mean_at"][1] == pytest.approx(((4 - 10) + (30 - 20)) / 2)
    assert c["regret_diff_w_se_at"][1] == pytest.approx(8.0)  # sd of (-6, 10) / √2
    assert c["frac_lower_at"][1] == 0.5
    table = hil_table([], comparisons=comps)
    assert "| hip_6d | adaptive-prior − adaptive-day2 | 2 |" in table
    assert "@20 min: mean ± SE (W) (% lower)" in table and "2.0 ± 8.0 (50 %)" in table


@pytest.mark.slow  # two training and eight toy sessions: ~10-25 s on a busy 2-core machine
def test_cli_runs_the_thesis_methods_tunes_k_and_resumes(tmp_path: Path) -> None:
    toy = ["--subjects", "1", "--seed", "3", "--spaces", "hip_6d", "--minutes", "5.5", "--warmup-s", "30",
           "--n-explore", "2", "--max-breaths", "5", "--condition-s", "30", "--popsize", "4",
           "--grid-min", "0.5", "--workers", "1", "--no-progress", "--wearer", "legacy",
           "--out", str(tmp_path)]
    methods = "adaptive,adaptive-day2,adaptive-prior,adaptive-prior-e3,adaptive-tuned-k"
    assert bench_main(["hil", "--methods", methods, "--tuned-k", "grid", "--tune-subjects", "2",
                       "--tune-seed", "101", *toy]) == 0
    doc = json.loads((tmp_path / "hil.json").read_text())
    assert [e["method"] for e in doc["results"]] == methods.split(",")
    for e in doc["results"]:
        assert e["n_sessions"] == 1 and e["minutes"][-1] == 5.5 and len(e["regret_w_median"]) == 12
    tuning = doc["tuning"]["hip_6d"]
    assert tuning["pick"] == "grid" and tuning["k"] == tuning["grid_best"]["k"]
    assert tuning["train_seeds"] == [101, 102] and tuning["n_trajectories"] >= 3
    pairs = {(c["method"], c["baseline"]) for c in doc["comparisons"]}
    assert {("adaptive-prior", "adaptive"), ("adaptive-prior-e3", "adaptive"),
            ("adaptive-tuned-k", "adaptive"), ("adaptive-prior", "adaptive-day2")} <= pairs
    by_method = {s["method"]: s for s in doc["sessions"]}
    assert by_method["adaptive-tuned-k"]["stopping_k"] == tuning["k"]
    assert by_method["adaptive-prior"]["n_priors"] > 0
    assert "--tuned-k grid --tune-subjects 2 --tune-seed 101 --error-weight 2" in doc["command"]
    assert "adaptive-prior − adaptive-day2" in (tmp_path / "hil_table.md").read_text()
    # --resume with another K reruns only the tuned-K session.
    assert bench_main(["hil", "--methods", methods, "--tuned-k", "0.5", *toy, "--resume"]) == 0
    lines = [json.loads(x) for x in (tmp_path / "sessions.jsonl").read_text().splitlines()]
    assert [x["method"] for x in lines[5:]] == ["adaptive-tuned-k"] and lines[5]["stopping_k"] == 0.5
    doc = json.loads((tmp_path / "hil.json").read_text())
    assert doc["tuning"]["hip_6d"] == {"k": 0.5, "pick": "given"}


@pytest.mark.parametrize(("extra", "message"), [
    (["--tuned-k", "big"], "--tuned-k 'big'; expected bo, grid or a constant K >= 0"),
    (["--tuned-k", "-1"], "--tuned-k '-1'"),
    (["--tune-seed", "1"], "training wearers [1, 2] are also test subjects"),
])
def test_bad_tuned_k_options_exit_2_before_any_work(extra: list[str], message: str, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    argv = ["hil", "--methods", "adaptive,adaptive-tuned-k", "--subjects", "2", "--seed", "1",
            "--tune-subjects", "2", "--wearer", "legacy", *extra, "--out", str(out)]
    assert bench_main(argv) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
