"""bridge.bench.stopping: campaign planning, summary statistics, resumable runs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bridge.bench.cli import bench_main
from bridge.bench.executors import LocalExecutor
from bridge.bench.stopping import (
    StoppingCampaign,
    against_peers,
    load_trials,
    run_campaign,
    stopping_table,
    summarize_stopping,
)
from hilbo_core.errors import ConfigError
from hilbo_core.optimizer import OptimizerConfig
from hilbo_core.studies.benchmarks import StoppingProtocol

TOY = StoppingProtocol(n_explore=3, max_breaths=4, window=1, budget=8, n_candidates=32, n_local=0)


def fake(method: str, seed: int, y: list[float], evaluations: int = 2, early: int = 0,
         function: str = "branin", noise: float = 1.0) -> dict:
    return {"method": method, "function": function, "noise": noise, "seed": seed, "y": y,
            "evaluations": evaluations, "early_stops": early, "wall_s": 0.5}


def test_campaign_is_trial_major_with_shared_seeds_per_trial() -> None:
    c = StoppingCampaign(functions=("branin", "levy"), noises=(1.0,), methods=("fixed", "adaptive"),
                         trials=2, seed=10, protocol=TOY)
    keys = [t.key() for t in c.tasks()]
    assert len(keys) == 2 * 2 * 2 == len(set(keys))
    assert keys[:4] == [("branin", 1.0, "fixed", 10), ("branin", 1.0, "adaptive", 10),
                        ("levy", 1.0, "fixed", 10), ("levy", 1.0, "adaptive", 10)]
    assert {k[3] for k in keys} == {10, 11}


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"trials": 0}, "trials=0; expected an integer >= 1"),
    ({"functions": ("branin", "sphere")}, "unknown function 'sphere'; choose one of"),
    ({"methods": ("fixed", "oracle")}, "unknown method 'oracle'; choose one of"),
    ({"noises": (1.0, -2.0)}, "noise=-2.0"),
    ({"methods": ("fixed", "fixed")}, "listed twice"),
    ({"refit_growth": 0.5}, r"refit_growth=0.5; expected a finite factor >= 1.0"),
    ({"refit_growth": math.nan}, "refit_growth=nan"),
])
def test_campaign_rejects_bad_input_before_any_work(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        StoppingCampaign(**{"protocol": TOY, **kwargs})


def test_summary_means_and_standard_errors_by_hand() -> None:
    c = StoppingCampaign(functions=("branin",), noises=(1.0,), methods=("fixed", "adaptive"), trials=2,
                         protocol=StoppingProtocol(max_breaths=2, budget=2))
    results = [fake("fixed", 0, [1.0, 1.0, 0.5]), fake("fixed", 1, [1.0, 0.5, 0.25]),
               fake("adaptive", 0, [1.0, 0.5, 0.25], 2, 1), fake("adaptive", 1, [1.0, 0.25, 0.25], 2, 2)]
    s = summarize_stopping(results, c)
    fixed, adaptive = s["settings"]
    assert fixed["method"] == "fixed" and fixed["t"] == [0, 1, 2] and fixed["n_trials"] == 2
    np.testing.assert_allclose(fixed["y_mean"], [1.0, 0.75, 0.375])
    # SE of (1.0, 0.5) is std(ddof=1)/sqrt(2) = 0.353553/1.414214 = 0.25
    np.testing.assert_allclose(fixed["y_se"], [0.0, 0.25, 0.125])
    assert fixed["y_final_mean"] == 0.375 and fixed["y_final_se"] == 0.125
    assert adaptive["early_stops_mean"] == 1.5 and adaptive["evaluations_mean"] == 2.0
    (comp,) = s["comparisons"]
    # paired final differences: 0.25 − 0.5 = −0.25 and 0.25 − 0.25 = 0
    assert comp["y_final_diff_mean"] == -0.125 and comp["y_final_diff_se"] == 0.125
    assert comp["frac_final_lower"] == 0.5 and comp["frac_final_tied"] == 0.5
    table = stopping_table(s)
    assert "| branin | 1 | fixed | 2 | 0.375 ± 0.125 |" in table
    assert "adaptive − fixed" in table


def test_against_peers_counts_settings_below_the_better_peer_by_mean_y_final() -> None:
    def setting(method: str, function: str, y_final: float) -> dict:
        return {"method": method, "function": function, "noise": 1.0, "y_final_mean": y_final}

    settings = [setting("sound", "branin", 0.30), setting("adaptive", "branin", 0.50),
                setting("tpe-wilcoxon", "branin", 0.40), setting("tpe-halving", "branin", 0.45),
                setting("sound", "levy", 0.20), setting("adaptive", "levy", 0.10),
                setting("tpe-wilcoxon", "levy", 0.30), setting("tpe-halving", "levy", 0.20),
                setting("sound", "ackley", 0.10)]  # no peer ran on ackley: not a setting
    out = against_peers(settings)
    assert out["n_settings"] == 2 and out["count"] == {"sound": 1, "adaptive": 1}
    branin, levy = out["settings"]
    assert branin["best_peer"] == "tpe-wilcoxon" and branin["best_peer_y_final"] == 0.40
    assert branin["below"] == {"sound": True, "adaptive": False}
    # A tie with the better peer is not below it.
    assert levy["best_peer"] == "tpe-halving" and levy["below"] == {"sound": False, "adaptive": True}
    assert against_peers(settings[-1:]) == {"settings": [], "count": {}, "n_settings": 0}
    table = stopping_table({"settings": [], "against_peers": out})
    assert "| sound | 1 of 2 |" in table and "mean y_T below the better TPE + pruner" in table


def test_summary_grid_keeps_the_last_measurement() -> None:
    c = StoppingCampaign(functions=("branin",), noises=(1.0,), methods=("fixed",), trials=1,
                         protocol=StoppingProtocol(max_breaths=2, budget=5))
    (s,) = summarize_stopping([fake("fixed", 0, [1, 1, 0.5, 0.5, 0.2, 0.1])], c, grid_step=2)["settings"]
    assert s["t"] == [0, 2, 4, 5] and s["y_mean"] == [1, 0.5, 0.2, 0.1]
    assert s["y_final_se"] is None  # one trial: no standard error (null in JSON, not NaN)


def test_toy_campaign_runs_resumes_and_respects_budgets(tmp_path: Path) -> None:
    c = StoppingCampaign(functions=("branin",), noises=(1.0,), methods=("fixed", "adaptive"), trials=2,
                         protocol=TOY)
    ex = LocalExecutor(1, progress=False)
    results, wall = run_campaign(c, ex, tmp_path)
    assert wall > 0 and len(results) == 4
    lines = (tmp_path / "trials.jsonl").read_text().splitlines()
    assert len(lines) == 4
    # What the run summarises is what trials.jsonl holds, to the last digit (wall times included),
    # so --summarize-only reproduces its tables.
    assert sorted(map(json.dumps, results)) == sorted(lines)
    for r in results:
        assert r["measurements"] == TOY.budget and len(r["y"]) == TOY.budget + 1 and r["y"][0] == 1.0
        assert all(y >= 0 for y in r["y"])
    by = {(r["method"], r["seed"]): r for r in results}
    for seed in (0, 1):
        assert by[("fixed", seed)]["x0"] == by[("adaptive", seed)]["x0"]
        assert by[("fixed", seed)]["evaluations"] == TOY.budget // TOY.max_breaths
    # Resume with one more trial: only the two new trials run; the old ones are reused.
    more = StoppingCampaign(functions=("branin",), noises=(1.0,), methods=("fixed", "adaptive"),
                            trials=3, protocol=TOY)
    again, _ = run_campaign(more, ex, tmp_path, resume=True)
    assert len((tmp_path / "trials.jsonl").read_text().splitlines()) == 6
    np.testing.assert_allclose([r["y"] for r in again[:4]], [r["y"] for r in results], rtol=1e-9)
    assert len(load_trials(tmp_path / "trials.jsonl", TOY)) == 6
    assert load_trials(tmp_path / "trials.jsonl", StoppingProtocol()) == {}  # other protocol


def test_load_trials_reads_a_line_without_noise_estimate_as_the_seeds(tmp_path: Path) -> None:
    # Campaigns written before --noise-estimate existed used Kim et al. 2019's estimator.
    path = tmp_path / "trials.jsonl"
    old = {k: v for k, v in TOY.to_json().items() if k != "noise_estimate"}
    path.write_text(json.dumps(fake("fixed", 0, [1.0]) | {"protocol": old}) + "\n")
    seed = StoppingProtocol(**{**old, "noise_estimate": "seed"})  # type: ignore[arg-type]
    assert list(load_trials(path, seed)) == [("branin", 1.0, "fixed", 0)]
    assert load_trials(path, TOY) == {}  # TOY is pooled (the default)


def test_load_trials_skips_a_truncated_last_line(tmp_path: Path) -> None:
    path = tmp_path / "trials.jsonl"
    rec = fake("fixed", 0, [1.0]) | {"protocol": TOY.to_json()}
    path.write_text(json.dumps(rec) + "\n" + json.dumps(rec)[:20])
    loaded = load_trials(path, TOY)
    assert list(loaded) == [("branin", 1.0, "fixed", 0)]
    assert math.isclose(loaded[("branin", 1.0, "fixed", 0)]["y"][0], 1.0)


def test_refit_growth_reaches_every_method_and_is_recorded(tmp_path: Path, optimize_calls: list[int]) -> None:
    fits = optimize_calls
    proto = StoppingProtocol(n_explore=3, max_breaths=4, window=1, budget=40, n_candidates=32, n_local=0)
    ex = LocalExecutor(1, progress=False)
    kw = {"functions": ("branin",), "noises": (1.0,), "methods": ("fixed", "adaptive"), "trials": 1,
          "protocol": proto}
    every, _ = run_campaign(StoppingCampaign(**kw), ex, tmp_path / "g1")
    n_every = len(fits)
    fits.clear()
    rare, _ = run_campaign(StoppingCampaign(**kw, refit_growth=100.0), ex, tmp_path / "g100")
    # Growth 100 in a 3-point start: per trial one fit for x_0 (best() after exploration) and
    # one at the first proposal; every later GP only re-conditions, in both methods.
    assert fits == [3, 3, 3, 3]
    # Growth 1: x_0, one fit per proposal and one for the final recommendation.
    assert n_every == sum(2 + r["evaluations"] for r in every)
    for a, b in zip(every, rare, strict=True):
        assert a["x0"] == b["x0"] and a["refit_growth"] == 1.0 and b["refit_growth"] == 100.0
    # A trial is identified by its growth factor too: the other campaign's trials are not reused.
    assert load_trials(tmp_path / "g100" / "trials.jsonl", proto, 100.0).keys() == {
        ("branin", 1.0, "fixed", 0), ("branin", 1.0, "adaptive", 0)}
    assert load_trials(tmp_path / "g100" / "trials.jsonl", proto) == {}


def test_trials_recorded_before_refit_growth_count_as_growth_one(tmp_path: Path) -> None:
    path = tmp_path / "trials.jsonl"
    rec = fake("fixed", 0, [1.0]) | {"protocol": TOY.to_json()}  # no "refit_growth" key
    path.write_text(json.dumps(rec) + "\n")
    assert list(load_trials(path, TOY)) == [("branin", 1.0, "fixed", 0)]
    assert load_trials(path, TOY, 1.25) == {}


def test_cli_refit_growth_toy_run_and_bad_value(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["stopping", "--trials", "1", "--functions", "branin", "--noise", "1", "--n-explore", "3",
            "--max-breaths", "4", "--budget", "8", "--n-candidates", "32", "--workers", "1",
            "--no-progress", "--out", str(tmp_path / "ok")]
    assert bench_main(argv) == 0  # the benchmark's default growth factor, 1.25
    doc = json.loads((tmp_path / "ok" / "results.json").read_text())
    assert " --refit-growth 1.25 " in doc["command"]
    assert doc["campaign"]["refit_growth"] == 1.25
    assert {s["refit_growth"] for s in doc["settings"]} == {1.25} and len(doc["settings"]) == 2
    lines = [json.loads(x) for x in (tmp_path / "ok" / "trials.jsonl").read_text().splitlines()]
    assert [r["refit_growth"] for r in lines] == [1.25, 1.25]
    # The summary of another growth factor finds none of these trials: a failure at run time
    # (the command line was valid), so exit status 1.
    summarize = [*argv[:-1], str(tmp_path / "ok"), "--summarize-only", "--refit-growth", "1"]
    assert bench_main(summarize) == 1
    assert "no trial of this campaign" in capsys.readouterr().err
    bad = tmp_path / "bad"
    assert bench_main([*argv[:-2], "--refit-growth", "0.9", "--out", str(bad)]) == 2
    assert "refit_growth=0.9; expected a finite factor >= 1.0" in capsys.readouterr().err
    assert not bad.exists()


def test_cli_n_local_defaults_to_the_optimizers_three_and_is_recorded(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["stopping", "--trials", "1", "--functions", "branin", "--noise", "1", "--methods", "fixed",
            "--n-explore", "3", "--max-breaths", "4", "--budget", "8", "--n-candidates", "32",
            "--workers", "1", "--no-progress"]
    assert bench_main([*argv, "--out", str(tmp_path / "three")]) == 0
    doc = json.loads((tmp_path / "three" / "results.json").read_text())
    assert " --n-local 3 " in doc["command"] and doc["campaign"]["protocol"]["n_local"] == 3
    assert doc["campaign"]["protocol"]["n_local"] == OptimizerConfig().n_local
    # One refinement is selectable, and is a campaign of its own.
    assert bench_main([*argv, "--n-local", "1", "--out", str(tmp_path / "one")]) == 0
    doc = json.loads((tmp_path / "one" / "results.json").read_text())
    assert " --n-local 1 " in doc["command"] and doc["campaign"]["protocol"]["n_local"] == 1
    assert load_trials(tmp_path / "one" / "trials.jsonl", StoppingProtocol(
        n_explore=3, max_breaths=4, budget=8, n_candidates=32)) == {}
    capsys.readouterr()
    assert bench_main([*argv, "--n-local", "-1", "--out", str(tmp_path / "bad")]) == 2
    assert "n_local=-1; expected an integer >= 0" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_cli_noise_estimate_defaults_to_pooled_and_the_seeds_is_selectable(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["stopping", "--trials", "1", "--functions", "branin", "--noise", "0.1", "--methods",
            "adaptive", "--noise-model", "assumed", "--n-explore", "3", "--max-breaths", "6",
            "--budget", "24", "--n-candidates", "32", "--workers", "1", "--no-progress"]
    docs = {}
    for name, extra in (("pooled", []), ("seed", ["--noise-estimate", "seed"])):
        assert bench_main([*argv, *extra, "--out", str(tmp_path / name)]) == 0
        docs[name] = json.loads((tmp_path / name / "results.json").read_text())
        assert f" --noise-estimate {name} " in docs[name]["command"]
        assert docs[name]["campaign"]["protocol"]["noise_estimate"] == name
    # Same seed, same measurements, different estimators: different trials.
    trials = {n: (tmp_path / n / "trials.jsonl").read_text() for n in docs}
    assert json.loads(trials["pooled"])["y"] != json.loads(trials["seed"])["y"]
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        bench_main([*argv, "--noise-estimate", "fitted", "--out", str(tmp_path / "bad")])
    assert exc.value.code == 2
    assert "invalid choice: 'fitted'" in capsys.readouterr().err
