"""bridge.bench.stopping: the Optuna TPE + pruner peers and both noise readings, at toy size."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from bridge.bench.cli import bench_main
from bridge.bench.stopping import PEER_METHODS, StoppingCampaign, peer_trial
from hilbo_core.errors import ConfigError
from hilbo_core.studies.benchmarks import StoppingProtocol, stopping_trial

pytest.importorskip("optuna")

TOY = StoppingProtocol(n_explore=3, max_breaths=4, window=1, budget=12, n_candidates=32, n_local=0)
TRIAL_FIELDS = {"function", "noise", "method", "seed", "y", "evaluations", "early_stops", "measurements",
                "f_x0", "f_final", "x0", "x_final", "wall_s", "protocol", "refit_growth"}


@pytest.mark.parametrize("method", sorted(PEER_METHODS))
def test_peer_shares_the_trials_exploration_and_spends_the_same_budget(method: str) -> None:
    bo = stopping_trial("branin", 1.0, "fixed", 3, TOY)
    peer = peer_trial("branin", 1.0, method, 3, TOY)
    # Same design, same measurement stream: the same x_0, so y is normalised alike.
    assert peer["x0"] == bo["x0"] and peer["f_x0"] == bo["f_x0"]
    assert peer["measurements"] == TOY.budget == bo["measurements"]
    assert len(peer["y"]) == TOY.budget + 1 and peer["y"][0] == 1.0
    assert all(v >= 0.0 for v in peer["y"])
    assert 1 <= peer["evaluations"] <= TOY.budget and 0 <= peer["pruned"] < peer["evaluations"] + 1
    assert peer["early_stops"] == peer["pruned"]
    # Deterministic in its arguments (TPE seeded with the trial seed).
    assert peer_trial("branin", 1.0, method, 3, TOY) == peer


def test_peer_bad_input_and_missing_optuna(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ConfigError, match="unknown peer method 'tpe'"):
        peer_trial("branin", 1.0, "tpe", 0, TOY)
    with pytest.raises(ConfigError, match="unknown method 'tpe'; choose one of"):
        StoppingCampaign(methods=("tpe",), protocol=TOY)
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna -> ImportError
    with pytest.raises(ConfigError, match=r"need Optuna: pip install hilbo\[peers\]"):
        StoppingCampaign(methods=("fixed", "tpe-halving"), protocol=TOY)
    with pytest.raises(ConfigError, match=r"pip install hilbo\[peers\]"):
        peer_trial("branin", 1.0, "tpe-wilcoxon", 0, TOY)


@pytest.mark.parametrize("noise_model", ["matched", "assumed"])
def test_cli_runs_every_method_under_both_noise_readings(tmp_path: Path, noise_model: str) -> None:
    out = tmp_path / noise_model
    methods = ["fixed", "adaptive", *sorted(PEER_METHODS)]
    argv = ["stopping", "--trials", "2", "--functions", "branin", "--noise", "1",
            "--methods", ",".join(methods), "--noise-model", noise_model, "--n-explore", "3",
            "--max-breaths", "4", "--budget", "12", "--n-candidates", "32", "--workers", "1",
            "--no-progress", "--out", str(out)]
    assert bench_main(argv) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["campaign"]["protocol"]["noise_model"] == noise_model
    assert f"--noise-model {noise_model}" in doc["command"]
    assert set(doc["methods"]) == set(methods) and "Optuna TPE" in doc["methods"]["tpe-wilcoxon"]
    assert [(s["method"], s["n_trials"]) for s in doc["settings"]] == [(m, 2) for m in methods]
    for s in doc["settings"]:
        assert s["t"][-1] == 12 and len(s["y_mean"]) == len(s["t"])
        assert s["y_final_mean"] >= 0.0 and s["evaluations_mean"] >= 1.0
    assert {c["method"] for c in doc["comparisons"]} == set(methods[1:])
    lines = [json.loads(x) for x in (out / "trials.jsonl").read_text().splitlines()]
    assert len(lines) == 2 * len(methods)
    for rec in lines:
        assert TRIAL_FIELDS <= set(rec)
        assert rec["protocol"]["noise_model"] == noise_model
    # Per seed, every method starts from the same x_0.
    for seed in (0, 1):
        assert len({json.dumps(r["x0"], sort_keys=True) for r in lines if r["seed"] == seed}) == 1


def test_cli_rejects_an_unknown_method_naming_the_peers(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["stopping", "--trials", "1", "--functions", "branin", "--methods", "fixed,tpe",
            "--workers", "1", "--no-progress", "--out", str(tmp_path / "x")]
    assert bench_main(argv) == 2
    err = capsys.readouterr().err
    assert "tpe" in err and "tpe-wilcoxon" in err and "Traceback" not in err


def test_keep_freed_memory_is_harmless_to_call_again() -> None:
    from bridge.bench.executors import keep_freed_memory

    first = keep_freed_memory()
    assert isinstance(first, bool) and keep_freed_memory() == first
    import platform

    if platform.libc_ver()[0] == "glibc":
        assert first  # both mallopt calls succeed
