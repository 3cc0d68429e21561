"""hilbo review: bad input gives one line naming the file and what was expected, exit status 2."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.writer import Writer

from bridge.cli.main import main
from bridge.errors import BridgeError, ReviewError
from bridge.log import SessionLog
from bridge.review.session import load_session


def other_programs_mcap(path: Path) -> Path:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="someone else")
        sid = w.register_schema("Foo", "jsonschema", b'{"type":"object"}')
        cid = w.register_channel("/camera/info", "json", sid)
        w.add_message(cid, log_time=1, data=b'{"x":1}', publish_time=1)
        w.finish()
    return path


def empty_session_log(path: Path, session_id: str = "s1") -> Path:
    SessionLog(path, session_id=session_id, config_json={}, flush_interval_s=None).close()
    return path


def run_review(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["review", *args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(err: str, *needles: str) -> None:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("hilbo review: error: ")
    for n in needles:
        assert n in lines[0], (n, lines[0])


def test_random_bytes_are_not_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "noise.mcap"
    bad.write_bytes(bytes(range(256)) * 8)
    code, out, err = run_review([str(bad)], capsys)
    assert code == 1 and out == ""
    assert_one_line_error(err, "noise.mcap", "not an MCAP file", "expected")


def test_an_empty_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    code, out, err = run_review([str(empty)], capsys)
    assert code == 1 and out == ""
    assert_one_line_error(err, "empty.mcap", "empty", "expected a hilbo session log")


def test_another_programs_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    foreign = other_programs_mcap(tmp_path / "camera.mcap")
    code, out, err = run_review([str(foreign)], capsys)
    assert code == 1 and out == ""
    assert_one_line_error(err, "camera.mcap", "not a hilbo session log", "/camera/info", "expected")


def test_a_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_review([str(tmp_path / "nope.mcap"), "--out", str(tmp_path / "r")], capsys)
    assert code == 1 and out == ""
    assert_one_line_error(err, "nope.mcap", "no such file", "expected a hilbo session log")
    assert not (tmp_path / "r").exists()  # nothing written for bad input


def test_a_session_log_with_nothing_in_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = empty_session_log(tmp_path / "started.mcap")
    code, out, err = run_review([str(log)], capsys)
    assert code == 1 and out == ""
    assert_one_line_error(err, "started.mcap", "without breaths or evaluations", "expected")


def test_compare_needs_exactly_two_logs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = empty_session_log(tmp_path / "one.mcap")
    code, _, err = run_review(["--compare", str(log)], capsys)
    assert code == 2
    assert_one_line_error(err, "--compare takes exactly two sessions", "got 1")


def test_logs_of_different_sessions_are_refused(tmp_path: Path) -> None:
    a = empty_session_log(tmp_path / "a.mcap", "session-a")
    b = empty_session_log(tmp_path / "b.mcap", "session-b")
    with pytest.raises(ReviewError, match=r"different sessions .*session-a.*session-b.*--compare"):
        load_session([a, b])


def test_the_review_error_is_a_bridge_error() -> None:
    assert issubclass(ReviewError, BridgeError) and issubclass(ReviewError, ValueError)


def test_help_names_the_outputs_and_the_default_directory(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["review", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for word in ("--compare", "--out", "report.html", "evaluations.csv", "session-review"):
        assert word in text
