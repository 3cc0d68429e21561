"""``hilbo log recover`` on a log that needs no recovery (bridge.cli.log).

It used to write a ``.recovered`` copy of a log closed normally without a word: a second file
of the session beside the first, which ``hilbo review`` given both counted twice.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from test_log_cli import run

from bridge.log import SessionLog
from hilbo_core.types import BreathRecord


@pytest.mark.parametrize("out", [None, "copy.mcap"])
def test_a_log_closed_normally_is_said_to_need_nothing_and_no_copy_is_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], out: str | None) -> None:
    path = tmp_path / "session.mcap"
    with SessionLog(path, session_id="s1", config_json={}, flush_interval_s=None) as log:
        log.log_breath(BreathRecord(t_s=1.0, vo2_ml_min=1000.0, vco2_ml_min=800.0))
    argv = ["log", "recover", str(path)] + ([str(tmp_path / out)] if out else [])
    assert run(argv) == 0
    captured = capsys.readouterr()
    assert captured.out == (f"{path} was closed normally and is intact: nothing to recover, no copy "
                            "written (it opens as it is in hilbo review, Foxglove and any MCAP reader)\n")
    assert captured.err == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session.mcap"]
