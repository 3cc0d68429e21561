"""A console that goes away does not end a session (bridge/operator_view.py ``console_guard``).

``hilbo run CONFIG 2>&1 | tee run.log`` with tee killed, or ``| head -3``: the next line printed
used to end the session (Rich's console answers a broken pipe with SystemExit) with no event
naming it and no summary. Now the session goes on, its printing stops, the log gets one
``console_lost`` warning and the summary is written.
"""

from __future__ import annotations

import errno
import io
import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest
from cart_csv import replay_config_toml, write_cosmed_like_csv
from rich.console import Console

import bridge.cli.main as cli
from bridge.log import EventLevel
from bridge.log.reader import read_log
from bridge.operator_view import console_guard

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]


class ClosingConsole(io.StringIO):
    """A console whose reader leaves right after it has read ``last``: every later write
    raises BrokenPipeError, as a pipe's does once its reader has gone."""

    def __init__(self, last: str) -> None:
        super().__init__()
        self.last = last
        self.closed_pipe = False
        self.writes_after = 0

    def write(self, text: str) -> int:
        if self.closed_pipe:
            self.writes_after += 1
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")
        if self.last in text:
            self.closed_pipe = True
        return super().write(text)

    def flush(self) -> None:
        if self.closed_pipe and self.writes_after:
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    def isatty(self) -> bool:
        return False


def _config(tmp_path: Path, n_breaths: int = 40) -> Path:
    """The example config replaying a short CSV at full speed, on python-can's virtual bus."""
    return replay_config_toml(tmp_path, write_cosmed_like_csv(tmp_path / "a.csv", n_breaths))


def test_a_console_closed_mid_session_leaves_the_session_its_log_and_its_summary(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # stdout and stderr are one pipe (2>&1 | tee), whose reader leaves once the log is named.
    console = ClosingConsole("hilbo run: log ")
    monkeypatch.setattr(sys, "stdout", console)
    monkeypatch.setattr(sys, "stderr", console)
    rc = cli.main(["run", str(_config(tmp_path)), "--no-view", "--auto-resume", "0"])

    # The session ran to its end (the cart's file ended), not to the first line after the loss.
    assert rc in {0, 3}, console.getvalue()
    # One failed write for each of stdout and stderr (one pipe here); nothing tried after them.
    assert console.writes_after == 2
    (log,) = (tmp_path / "out").glob("*.mcap")
    summary = json.loads(log.with_suffix(".summary.json").read_text())
    assert summary["end_reason"] == "cart_ended"
    events = read_log(log, topics=["/events"]).records("/events")
    (lost,) = [e for e in events if e.kind == "console_lost"]
    assert lost.level == EventLevel.WARNING
    assert "console was lost" in lost.message and lost.details == {"stream": "stderr"}
    assert [e.kind for e in events][-1] == "session_end"
    # The streams are the test's again once the command has returned.
    assert sys.stdout is console and sys.stderr is console


def test_only_a_broken_pipe_is_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    class Failing(io.StringIO):
        def write(self, text: str) -> int:
            raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(sys, "stderr", Failing())
    with pytest.raises(OSError, match="Input/output error"), console_guard() as guard:
        print("x", file=sys.stderr)
    assert guard.lost is None


@pytest.mark.parametrize("stderr_too", [True, False], ids=["2>&1 | head", "| head"])
def test_a_closed_pipe_at_exit_prints_no_exception_ignored(tmp_path: Path, stderr_too: bool) -> None:
    """A real pipe whose reader has gone: Rich, print and logging write to it inside the guard;
    the guard is left and the interpreter exits quietly, with status 0 (a failed flush at exit
    is "Exception ignored ... BrokenPipeError" and status 120)."""
    script = """
import logging, sys
from rich.console import Console
from bridge.operator_view import console_guard
logging.basicConfig(format="%(message)s")
with console_guard() as guard:
    for i in range(2000):
        print("line", i)
        Console(stderr=False).print("rich line", i)
        logging.getLogger("t").warning("warning %d", i)
print("after the guard")
sys.stderr.write(f"DONE {guard.lost}\\n")
"""
    err = tmp_path / "stderr.txt"
    with err.open("wb") as err_file:
        proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT if stderr_too else err_file)
        assert proc.stdout is not None
        proc.stdout.close()  # the reader leaves at once
        assert proc.wait(timeout=60) == 0
    text = err.read_text()
    assert "Exception ignored" not in text and "Traceback" not in text
    if not stderr_too:
        assert text.endswith("DONE stdout\n")


def test_the_guard_drops_writes_after_a_broken_pipe_and_says_which_stream() -> None:
    console = ClosingConsole("first")
    saved = sys.stdout
    sys.stdout = console
    try:
        handler = logging.StreamHandler(console)
        logging.getLogger().addHandler(handler)
        try:
            with console_guard() as guard:
                sys.stdout.write("first\n")
                Console(stderr=False).print("second")  # raises inside: dropped
                logging.getLogger("t").warning("third")
                print("fourth")
            assert handler.stream is console  # restored
        finally:
            logging.getLogger().removeHandler(handler)
    finally:
        sys.stdout = saved
    assert guard.lost == "stdout"
    assert console.getvalue() == "first\n"
    assert console.writes_after == 1
