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
