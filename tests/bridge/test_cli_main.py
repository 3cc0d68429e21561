"""bridge.cli.main.main: exit codes of the top-level command line."""

from __future__ import annotations

import argparse

import pytest

import bridge.cli.main as cli
import bridge.cli.session_end as session_end


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


def test_the_end_of_hilbo_run_says_why_what_to_set_and_the_minutes_walked() -> None:
    from bridge.outcome import recommendation

    evals = [{"params": {"t_on": 1.66e-11, "F_p": 152.37}, "breaths": 45},
             {"params": {"t_on": 20.0, "F_p": 100.0}, "breaths": 12}]
    rec = recommendation({"t_on": 1.66e-11, "F_p": 152.37}, 344.0799, 20.25, evaluations=evals,
                         method="posterior", units={"t_on": "%GC", "F_p": "N"})
    summary = {"n_evaluations": 2, "n_early_stops": 1, "end_reason": "budget", "recommendation": rec,
               "walking": {"session_s": 4009.26, "optimization_s": 2400.99}}
    assert session_end.ended_text(summary).splitlines() == [
        "session ended: the optimisation bout's budget ([protocol] budget_min) was spent; "
        "2 evaluations (1 early stops); 66.8 min walked, 40.0 of them in the optimisation bout",
        "recommended setting: t_on = 0.00 %GC, F_p = 152.4 N; estimated 344.1 W (95 % CI 335.3 to "
        "352.9 W; GP posterior over all 2 evaluations; this setting measured 1 time, 45 breaths)"]
    assert session_end.run_exit_status(summary) == 0
    # A session stopped before any evaluation or any breath: it says so, and exits 3.
    nothing = {"n_evaluations": 0, "n_early_stops": 0, "end_reason": "operator_stop",
               "recommendation": None, "walking": {}}
    assert session_end.ended_text(nothing) == (
        "session ended: stopped by the operator; 0 evaluations (0 early stops)\n"
        "no evaluation completed: nothing to recommend (exit status 3)")
    assert session_end.run_exit_status(nothing) == 3
    # Ctrl-C (or SIGTERM): 130, as the README says, whatever was measured.
    assert session_end.run_exit_status({**summary, "end_reason": "interrupted"}) == 130
    assert session_end.run_exit_status({**nothing, "end_reason": "interrupted"}) == 130
    assert session_end.ended_text({**nothing, "end_reason": "interrupted"}).endswith(
        "nothing to recommend (exit status 130)")


def test_the_last_lines_of_hilbo_run_give_the_confirmed_recommendation() -> None:
    summary = {"n_evaluations": 32, "n_early_stops": 15, "end_reason": "session", "recommendation": None,
               "confirmation": {"mean_w": 351.24, "sd_w": 5.5, "n_evaluations": 1},
               "walking": {"session_s": 3600.5, "optimization_s": 2950.0}}
    assert session_end.ended_text(summary).splitlines()[-1] == "recommended, confirmed at 351.2 ± 5.5 W (SD)"
    # A confirmation that began but did not complete adds nothing.
    summary["confirmation"] = {"mean_w": None, "sd_w": None, "n_evaluations": 0}
    assert "confirmed" not in session_end.ended_text(summary)


def test_a_resumed_run_counts_this_runs_evaluations_and_the_sessions() -> None:
    summary = {"n_evaluations": 0, "n_evaluations_session": 12, "n_early_stops": 0,
               "end_reason": "operator_stop", "recommendation": None}
    assert "0 evaluations (0 early stops) in this run, 12 in the session" in session_end.ended_text(summary)
    assert "nothing to recommend" not in session_end.ended_text(summary)
    assert session_end.run_exit_status(summary) == 0  # the session has evaluations to recommend from
    summary["n_evaluations_session"] = 0
    assert session_end.run_exit_status(summary) == session_end.EXIT_NOTHING_MEASURED


def test_hilbo_sim_ends_with_the_last_lines_of_hilbo_run(capsys: pytest.CaptureFixture[str]) -> None:
    from rich.console import Console

    from bridge.cli.main import _print_done
    from bridge.outcome import recommendation

    rec = recommendation({"F_p": 200.0}, 323.2, 25.0, evaluations=[{"params": {"F_p": 200.0}, "breaths": 45}],
                         method="global", units={"F_p": "N"})
    summary = {"n_evaluations": 24, "n_early_stops": 6, "end_reason": "session", "recommendation": rec,
               "confirmation": {"mean_w": 323.2, "sd_w": 11.6}, "walking": {"session_s": 3600.0},
               "wall_time_s": 15.8, "best_mean": 323.2, "true_cost_of_best": 347.8,
               "true_optimum": {"cost_w": 345.4}, "regret_w": 2.4}
    _print_done(Console(stderr=True, markup=False, soft_wrap=True), summary)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("session ended: ") and lines[1].startswith("recommended setting: F_p = 200")
    assert lines[2] == "recommended, confirmed at 323.2 ± 11.6 W (SD)"
    assert lines[3].startswith("done: 24 evaluations") and "regret 2.4 W" in lines[3]
    # The core engine's summary has no recommendation record: only the done line.
    del summary["recommendation"]
    _print_done(Console(stderr=True, markup=False, soft_wrap=True), summary)
    assert capsys.readouterr().err.startswith("done: ")


def test_hilbo_run_help_documents_its_exit_statuses(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "3 the session ended without a completed evaluation" in text
    assert "130 stopped by Ctrl-C or SIGTERM" in text


def test_hilbo_validate_help_says_what_its_exit_3_means() -> None:
    text = " ".join(session_end.VALIDATE_EXIT_STATUS.split())
    assert "3 the walk ended before any condition was measured" in text and "recommend" not in text
