"""bridge.cli.main.main: exit codes of the top-level command line."""

from __future__ import annotations

import argparse

import pytest

import bridge.cli.main as cli


def test_a_reader_that_leaves_early_is_exit_141_without_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def closed_pipe(args: argparse.Namespace) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cli, "_cmd_vcan_setup", closed_pipe)
    assert cli.main(["vcan-setup"]) == 141
    assert "Traceback" not in capsys.readouterr().err


def test_errors_of_the_packages_are_exit_1_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["vcan-setup", "no such iface!"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("hilbo vcan-setup: error:") and len(err.strip().splitlines()) == 1


def test_the_last_line_of_hilbo_run_gives_the_best_estimate_and_the_minutes_walked() -> None:
    summary = {"n_evaluations": 32, "n_early_stops": 15, "best_mean": 344.0799, "best_var": 20.25,
               "walking": {"session_s": 4009.26, "optimization_s": 2400.99}}
    assert cli._ended_text(summary) == ("session ended: 32 evaluations (15 early stops); best 344.1 ± 4.5 W; "
                                    "66.8 min walked, 40.0 of them in the optimisation bout")
    # A session stopped before any evaluation or any breath.
    assert cli._ended_text({"n_evaluations": 0, "n_early_stops": 0, "best_mean": None, "walking": {}}) \
        == "session ended: 0 evaluations (0 early stops)"


def test_the_last_line_of_hilbo_run_gives_the_confirmed_recommendation() -> None:
    summary = {"n_evaluations": 32, "n_early_stops": 15, "best_mean": 351.2, "best_var": 30.25,
               "confirmation": {"mean_w": 351.24, "sd_w": 5.5, "n_evaluations": 1},
               "walking": {"session_s": 3600.5, "optimization_s": 2950.0}}
    assert cli._ended_text(summary) == (
        "session ended: 32 evaluations (15 early stops); recommended, confirmed at 351.2 ± 5.5 W; "
        "60.0 min walked, 49.2 of them in the optimisation bout")
    # A confirmation that began but did not complete: the recommendation's estimate as before.
    summary["confirmation"] = {"mean_w": None, "sd_w": None, "n_evaluations": 0}
    assert "; best 351.2 ± 5.5 W;" in cli._ended_text(summary)
