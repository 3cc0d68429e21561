"""``hilbo log info`` and ``hilbo log recover`` (bridge.cli.log)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from bridge.cli.log import add_log_parser, default_recovered_path
from bridge.log import SessionLog, Topic
from bridge.log.reader import read_log
from hilbo_core.types import BreathRecord


def run(argv: list[str]) -> int:
    """Parse and run like bridge.cli.main.main does once ``add_log_parser`` is registered there."""
    parser = argparse.ArgumentParser(prog="hilbo")
    add_log_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))


@pytest.fixture
def crashed(tmp_path: Path) -> Path:
    """A log of 4 breaths whose writer died mid-way through a fifth chunk."""
    path = tmp_path / "session.mcap"
    with SessionLog(path, session_id="cli-1", config_json={}, previous_log="old.mcap",
                    flush_interval_s=None) as log:
        for i in range(4):
            log.log_breath(BreathRecord(t_s=float(i), vo2_ml_min=1000.0, vco2_ml_min=800.0))
        size = path.stat().st_size
        log.log_event("x", "y")
    path.write_bytes(path.read_bytes()[: size + 30])
    return path


def test_info_on_a_crashed_log(crashed: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["log", "info", str(crashed)]) == 0
    out = capsys.readouterr().out
    assert "TRUNCATED (30 bytes unreadable" in out
    assert "session:    cli-1 (resumes old.mcap)" in out
    assert any(line.split()[:1] == ["/breaths"] and line.split()[-1] == "4" for line in out.splitlines())
    # The walked (breath-clock) time beside the log's wall time: breaths at 0-3 s.
    assert "walked:     0.1 min of breaths (breath clock 0.0 – 0.1 min)" in out


def test_info_json(crashed: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["log", "info", "--json", str(crashed)]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["session_id"] == "cli-1" and s["previous_log"] == "old.mcap" and not s["complete"]
    assert s["channels"][Topic.BREATHS]["messages"] == 4 and s["messages"] == 5
    assert s["unreadable_bytes"] == 30 and s["duration_s"] >= 0
    assert s["breath_time_s"] == [0.0, 3.0]


def test_recover_to_the_default_path(crashed: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["log", "recover", str(crashed)]) == 0
    out_path = crashed.with_name("session.recovered.mcap")
    assert default_recovered_path(crashed) == out_path
    assert f"wrote 5 messages to {out_path}" in capsys.readouterr().out
    fixed = read_log(out_path)
    assert fixed.complete and len(fixed.topic(Topic.BREATHS)) == 4
    # A second run does not clobber the first output unless forced.
    assert run(["log", "recover", str(crashed)]) == 1
    assert "exists" in capsys.readouterr().err
    assert run(["log", "recover", "--force", str(crashed), str(out_path)]) == 0


@pytest.mark.parametrize(("content", "match"), [
    (b"", "is empty"),
    (b"hello, this is text\n", "not an MCAP file"),
    (None, "no such file"),
])
@pytest.mark.parametrize("action", ["info", "recover"])
def test_bad_input_exits_1_with_one_line_and_no_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None, match: str,
        action: str) -> None:
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    assert run(["log", action, str(path)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith(f"hilbo log {action}: error: ") and match in captured.err
    assert "Traceback" not in captured.err and captured.err.count("\n") == 1


def test_default_recovered_path_names() -> None:
    assert default_recovered_path("a/b.mcap") == Path("a/b.recovered.mcap")
    assert default_recovered_path("log") == Path("log.recovered.mcap")
