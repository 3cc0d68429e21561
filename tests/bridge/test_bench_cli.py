"""bridge.bench.cli: the ``bench`` subcommands end to end at toy size, and bad input."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from bridge.bench.cli import add_bench_parser, bench_main


def test_add_bench_parser_registers_three_benchmarks() -> None:
    parser = argparse.ArgumentParser(prog="hilbo")
    bench_sub = add_bench_parser(parser.add_subparsers(dest="command"))
    # Other benchmarks can join `hilbo bench` through the returned subparsers.
    extra = bench_sub.add_parser("extra")
    extra.set_defaults(func=lambda a: 0)
    assert parser.parse_args(["bench", "extra"]).bench_command == "extra"
    for name in ("stopping", "hil", "perf"):
        args = parser.parse_args(["bench", name])
        assert callable(args.func) and args.bench_command == name
    args = parser.parse_args(["bench", "stopping", "--trials", "3", "--scheduler", "tcp://h:8786"])
    assert args.trials == 3 and args.scheduler == "tcp://h:8786" and args.workers is None


@pytest.mark.parametrize(("argv", "message"), [
    (["stopping", "--functions", "branin,rosenbrock"], "unknown function 'rosenbrock'; choose from"),
    (["stopping", "--methods", "fixed,psychic"], "unknown method 'psychic'; choose from"),
    (["stopping", "--trials", "0"], "trials=0; expected an integer >= 1"),
    (["stopping", "--budget", "30"], "budget=30 measurements is smaller than one full evaluation"),
    (["stopping", "--noise", "1,zero"], "noise level 'zero' is not a number"),
    (["hil", "--methods", "cmaes,bayes"], "unknown method 'bayes'; choose from"),
    (["hil", "--spaces", "knee_2d"], "unknown space 'knee_2d'; choose from"),
    (["hil", "--subjects", "0"], "--subjects 0"),
    (["hil", "--minutes", "15"], "minutes=15 is too short"),
    (["perf", "--sizes", "10,2"], "sizes="),
])
def test_bad_input_exits_2_naming_the_value_before_any_work(
        argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert bench_main([*argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()  # nothing was started


def test_stopping_toy_run_writes_json_table_and_one_png_per_function(tmp_path: Path) -> None:
    argv = ["stopping", "--trials", "1", "--functions", "branin,hartmann6", "--noise", "1",
            "--n-explore", "3", "--max-breaths", "4", "--budget", "8", "--n-candidates", "32",
            "--workers", "1", "--no-progress", "--grid-step", "2", "--out", str(tmp_path)]
    assert bench_main(argv) == 0
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["command"].startswith("hilbo bench stopping --trials 1 --functions branin,hartmann6")
    assert len(doc["settings"]) == 2 * 1 * 2
    for s in doc["settings"]:
        for key in ("method", "function", "noise", "t", "y_mean", "y_se", "y_final_mean", "y_final_se",
                    "evaluations_mean", "early_stops_mean"):
            assert key in s
        assert s["t"] == [0, 2, 4, 6, 8] and s["y_mean"][0] == 1.0
    assert {s["method"] for s in doc["settings"]} == {"fixed", "adaptive"}
    assert (tmp_path / "stopping_branin.png").stat().st_size > 1000
    assert (tmp_path / "stopping_hartmann6.png").stat().st_size > 1000
    assert "| function |" in (tmp_path / "table.md").read_text()
    # Summaries can be rebuilt from trials.jsonl without running anything.
    (tmp_path / "results.json").unlink()
    assert bench_main([*argv, "--summarize-only"]) == 0
    assert json.loads((tmp_path / "results.json").read_text())["settings"] == doc["settings"]
    # ... also from other directories (campaigns run in parts), into a fresh one.
    merged = tmp_path / "merged"
    assert bench_main([*argv[:-1], str(merged), "--summarize-only", "--merge", str(tmp_path)]) == 0
    again = json.loads((merged / "results.json").read_text())
    assert again["settings"] == doc["settings"] and again["command"].endswith(f"--merge {tmp_path}")
    assert bench_main([*argv, "--merge", str(tmp_path)]) == 2  # --merge needs --summarize-only
    # A --merge directory without trials is a usage error, not silently nothing.
    assert bench_main([*argv, "--summarize-only", "--merge", str(tmp_path / "nowhere")]) == 2


def test_hil_toy_run_writes_the_summary_and_resumes(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["hil", "--subjects", "1", "--spaces", "hip_ankle_4d", "--methods", "random,cmaes",
            "--minutes", "25", "--workers", "1", "--no-progress", "--out", str(tmp_path)]
    assert bench_main(argv) == 0
    doc = json.loads((tmp_path / "hil.json").read_text())
    assert [(e["method"], e["space"]) for e in doc["results"]] == [("random", "hip_ankle_4d"),
                                                                  ("cmaes", "hip_ankle_4d")]
    for e in doc["results"]:
        for key in ("minutes", "regret_w_median", "regret_w_p75", "evaluations_per_hour"):
            assert key in e
        assert e["minutes"][-1] == 25.0 and len(e["regret_w_median"]) == 26
    assert (tmp_path / "hil.png").stat().st_size > 1000
    # --summarize-only rebuilds the same summary, to the last digit, from sessions.jsonl.
    assert bench_main([*argv, "--summarize-only"]) == 0
    assert json.loads((tmp_path / "hil.json").read_text())["results"] == doc["results"]
    # Summarising more subjects than are on disk says so.
    assert bench_main([*argv[:2], "2", *argv[3:], "--summarize-only"]) == 0
    assert "warning: --summarize-only: 2 of the 4 sessions" in capsys.readouterr().err
    # One more subject with --resume runs only the two new sessions.
    assert bench_main([*argv[:2], "2", *argv[3:], "--resume"]) == 0
    assert len((tmp_path / "sessions.jsonl").read_text().splitlines()) == 4


def test_perf_toy_run_writes_the_required_keys(tmp_path: Path) -> None:
    argv = ["perf", "--breaths", "20", "--sizes", "5,8", "--reps", "1", "--sessions", "0",
            "--out", str(tmp_path)]
    assert bench_main(argv) == 0
    doc = json.loads((tmp_path / "perf.json").read_text())
    assert set(doc["breath_latency_ms"]) >= {"median", "p99"}
    assert set(doc["proposal_latency_ms"]) == {"5", "8"}
    assert set(doc["proposal_latency_ms"]["8"]) >= {"median", "p95"}
    assert "session_60min_wall_s" in doc and doc["command"].startswith("hilbo bench perf")


def test_bench_hil_help_lists_the_methods_that_run_by_default(capsys: pytest.CaptureFixture[str]) -> None:
    from bridge.bench.hil import DEFAULT_HIL_METHODS

    parser = argparse.ArgumentParser(prog="hilbo")
    add_bench_parser(parser.add_subparsers(dest="command"))
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "hil", "--help"])
    text = "".join(capsys.readouterr().out.split())  # argparse wraps anywhere
    assert f"from{','.join(DEFAULT_HIL_METHODS)}(thedefault)" in text
    assert f"thedefaultmethods({','.join(DEFAULT_HIL_METHODS)})" in text
    assert len(DEFAULT_HIL_METHODS) == 5 and "sound" in DEFAULT_HIL_METHODS
