"""``hilbo bench``: 2 for a wrong command line only, 1 with one line for a failure at run time,
the same through ``hilbo bench`` and ``python -m bridge.bench``."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from bridge.bench.cli import bench_main
from bridge.cli.main import main


def one_line(err: str, *parts: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for part in parts:
        assert part in lines[0], (part, lines[0])


@pytest.mark.parametrize("entry", [bench_main, lambda argv: main(["bench", *argv])])
def test_summarizing_a_folder_without_trials_is_a_runtime_failure(
        entry, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = entry(["stopping", "--summarize-only", "--out", str(tmp_path)])
    assert code == 1
    one_line(capsys.readouterr().err, "--summarize-only: no trial of this campaign in",
             str(tmp_path / "trials.jsonl"))


def test_an_unreadable_replay_file_is_a_runtime_failure(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.txt"
    code = bench_main(["estimator", "--replay", str(missing), "--transitions", "60,120",
                       "--out", str(tmp_path / "out")])
    assert code == 1
    one_line(capsys.readouterr().err, f"--replay {missing}: cannot read breaths")


def test_missing_optuna_is_a_runtime_failure_not_a_usage_error(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna -> ImportError
    code = bench_main(["stopping", "--methods", "fixed,tpe-halving", "--out", str(tmp_path / "o")])
    assert code == 1
    one_line(capsys.readouterr().err, "need Optuna: pip install hilbo[peers]")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("entry", [bench_main, lambda argv: main(["bench", *argv])])
def test_a_bad_option_value_is_a_usage_error_through_both_entry_points(
        entry, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = entry(["stopping", "--methods", "fixed,psychic", "--out", str(tmp_path / "o")])
    assert code == 2
    one_line(capsys.readouterr().err, "unknown method 'psychic'; choose from")


def test_argparse_usage_errors_stay_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", "stopping", "--trials", "three"])
    assert exc.value.code == 2
    assert "expected an integer, got 'three'" in capsys.readouterr().err
