"""hilbo review of a session's health data: its files get the session's mode (0600 unless the
config says otherwise), and a log of only non-finite breaths is an error, not "0 breaths"."""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from bridge.cli.main import main
from bridge.log import SessionLog
from bridge.review.command import review_session
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(120)

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "logs" / "v3" / "session.mcap"


@pytest.fixture
def open_umask() -> Iterator[None]:
    """umask 0: a file's mode is then only what its writer asked for."""
    old = os.umask(0)
    try:
        yield
    finally:
        os.umask(old)


def write_log(path: Path, vo2: list[float], config: dict[str, object] | None = None) -> Path:
    with SessionLog(path, session_id="s", config_json=config or {}, flush_interval_s=None) as log:
        for k, v in enumerate(vo2):
            log.log_breath(BreathRecord(t_s=3.0 * k, vo2_ml_min=v, vco2_ml_min=800.0, hr_bpm=90.0))
    return path


def modes(files: tuple[Path, ...]) -> dict[str, int]:
    return {f.name: stat.S_IMODE(f.stat().st_mode) for f in files}


@pytest.mark.usefixtures("open_umask")
def test_every_file_of_a_review_is_owner_only(tmp_path: Path) -> None:
    result = review_session([GOLDEN], tmp_path / "review")
    names = {f.name for f in result.files}
    assert {"breaths.csv", "evaluations.csv", "report.md", "report.html"} <= names
    assert any(n.endswith(".png") for n in names)
    assert set(modes(result.files).values()) == {0o600}, modes(result.files)


@pytest.mark.usefixtures("open_umask")
def test_a_review_rewrites_an_older_readable_file_owner_only(tmp_path: Path) -> None:
    out = tmp_path / "review"
    out.mkdir()
    (out / "breaths.csv").write_text("old")
    (out / "breaths.csv").chmod(0o644)
    result = review_session([write_log(tmp_path / "s.mcap", [1000.0] * 3)], out)
    assert modes(result.files)["breaths.csv"] == 0o600


@pytest.mark.usefixtures("open_umask")
def test_the_sessions_file_mode_applies_to_its_review(tmp_path: Path) -> None:
    log = write_log(tmp_path / "s.mcap", [1000.0] * 3, {"session": {"file_mode": "0640"}})
    result = review_session([log], tmp_path / "review")
    assert set(modes(result.files).values()) == {0o640}


def test_only_non_finite_breaths_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = write_log(tmp_path / "nan.mcap", [math.nan, math.inf, -math.inf])
    assert main(["review", str(log), "--out", str(tmp_path / "r")]) == 1
    out, err = capsys.readouterr()
    assert out == "" and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hilbo review: error: ")
    assert "nan.mcap" in lines[0] and "all 3 logged breaths" in lines[0] and "non-finite" in lines[0]


def test_some_non_finite_breaths_are_noted(tmp_path: Path) -> None:
    log = write_log(tmp_path / "some.mcap", [1000.0, math.nan, 1010.0])
    result = review_session([log], tmp_path / "r")
    assert len(result.session.breaths) == 2
    assert any("1 of 3 logged breaths" in n for n in result.session.notes)
