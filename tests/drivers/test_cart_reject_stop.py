"""A stream whose breaths are all rejected stops at once with the reason; a missing column is one line.

Reproductions of two failures a new user met: a CSV replayed with the wrong ``vo2_unit`` or ``time_format``
used to end "0 evaluations" with all 400 breaths rejected (visible only in /rejects); a column map
naming a missing column used to end in a 51-line ExceptionGroup traceback.
"""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import pytest
from cart_csv import replay_config_toml, write_cosmed_like_csv

import bridge.cli.main as cli
from bridge.log.reader import read_log
from drivers.cart import BreathStream, CartConfig
from drivers.cart.errors import CartError
from drivers.errors import DriverError

pytestmark = pytest.mark.timeout(60)

N_ROWS = 400


def _write_csv(path: Path, n: int = N_ROWS) -> Path:
    return write_cosmed_like_csv(path, n)


def _cart(path: Path, **csv: object) -> dict[str, object]:
    mapping = {"time_column": "t", "vo2_column": "VO2", "vco2_column": "VCO2", "time_format": "hh:mm:ss",
               "skip_rows": 1, **csv}
    return {"transport": "replay", "format": "csv", "options": {"path": str(path), "speed": "max"},
            "csv": mapping}


async def _drain(config: CartConfig) -> tuple[int, BreathStream]:
    n = 0
    async with BreathStream.from_config(config) as stream:
        async for _ in stream:
            n += 1
    return n, stream


def test_right_map_reads_every_row(tmp_path: Path) -> None:
    n, stream = asyncio.run(_drain(CartConfig.from_dict(_cart(_write_csv(tmp_path / "a.csv")))))
    assert n == N_ROWS and stream.counters == {}


@pytest.mark.parametrize(("csv", "reason", "value"), [
    ({"vo2_unit": "l/min", "vco2_unit": "l/min"}, "vo2_range", "VO2 = 1e+06 ml/min"),
    ({"time_format": "s"}, "bad_time", "time '0:00:03' is a clock time, not s"),
])
def test_all_rejected_stops_after_the_first_k(tmp_path: Path, csv: dict[str, object], reason: str,
                                              value: str) -> None:
    config = CartConfig.from_dict({**_cart(_write_csv(tmp_path / "a.csv"), **csv), "max_leading_rejects": 15})
    stream_box: list[BreathStream] = []

    async def run() -> None:
        async with BreathStream.from_config(config) as stream:
            stream_box.append(stream)
            async for _ in stream:
                pass

    with pytest.raises(CartError) as info:
        asyncio.run(run())
    msg = str(info.value)
    assert f"the first 15 records were all rejected, none accepted: 15 x {reason}" in msg
    assert value in msg
    assert "Check " in msg
    assert stream_box[0].validator.rejected == 15  # stopped at once, not after 400


def test_default_limit_and_accepted_breath_disarms(tmp_path: Path) -> None:
    assert CartConfig.from_dict(_cart(tmp_path / "x.csv")).max_leading_rejects == 20
    path = _write_csv(tmp_path / "a.csv", n=60)
    text = path.read_text().splitlines()
    # One good row first, then 50 rows out of range: accepted once, so the stream does not stop.
    bad = [re.sub(r",\d+,", ",5,", row, count=1) for row in text[3:53]]
    path.write_text("\n".join(text[:3] + bad + text[53:]) + "\n")
    n, stream = asyncio.run(_drain(CartConfig.from_dict(_cart(path))))
    assert n == 60 - 50 and stream.counters == {"vo2_range": 50}


def test_max_leading_rejects_is_validated(tmp_path: Path) -> None:
    with pytest.raises(DriverError, match="max_leading_rejects = 0: expected an integer in"):
        CartConfig.from_dict({**_cart(tmp_path / "x.csv"), "max_leading_rejects": 0})


def _config_toml(tmp_path: Path, cart_path: Path, csv_extra: str = "") -> Path:
    return replay_config_toml(tmp_path, cart_path, csv_extra)


def test_config_check_shows_first_breaths_and_rejects(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    good = _config_toml(tmp_path, _write_csv(tmp_path / "a.csv"))
    assert cli.main(["config", "check", str(good), "--samples", "0"]) == 0
    out = capsys.readouterr().out
    assert f"cart file {tmp_path / 'a.csv'}: 400 breaths read, 0 rejected" in out
    assert "t = 3 s, VO2 = 1000 ml/min, VCO2 = 850 ml/min" in out
    bad = _config_toml(tmp_path, tmp_path / "a.csv", 'vo2_unit = "l/min"\nvco2_unit = "l/min"')
    assert cli.main(["config", "check", str(bad), "--samples", "0"]) == 1
    cap = capsys.readouterr()
    assert "0 breaths read, 400 rejected (vo2_range 400)" in cap.out
    assert "reject vo2_range: t = 3 s, VO2 = 1e+06 ml/min" in cap.out
    assert "every record of" in cap.err


def test_missing_column_is_one_line_naming_it_and_the_columns(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _config_toml(tmp_path, _write_csv(tmp_path / "a.csv"), 'hr_column = "HR"')
    assert cli.main(["config", "check", str(cfg), "--samples", "0"]) == 1
    err = capsys.readouterr().err
    assert ("csv.hr_column = 'HR': no column 'HR' in the header; the file's columns are: 't', 'VO2', "
            "'VCO2', 'R'") in err
    assert "Traceback" not in err


@pytest.mark.parametrize(("extra", "expected"), [
    ('hr_column = "HR"', "no column 'HR' in the header; the file's columns are: 't', 'VO2', 'VCO2', 'R'"),
    ('vo2_unit = "l/min"\nvco2_unit = "l/min"', "every record of"),
])
def test_hilbo_run_refuses_a_cart_file_that_does_not_fit_before_it_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: str, expected: str) -> None:
    """The replayed file is read as `hilbo config check` reads it, before any log is made."""
    cfg = _config_toml(tmp_path, _write_csv(tmp_path / "a.csv"), extra)
    rc = cli.main(["run", str(cfg), "--no-view"])
    err = capsys.readouterr().err
    assert rc == 1
    assert expected in err and err.startswith("hilbo run: ")
    assert "Traceback" not in err and "ExceptionGroup" not in err
    assert not list((tmp_path / "out").glob("*.mcap"))


def test_a_session_that_fails_after_it_started_writes_its_summary(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """A whole `hilbo run` (python-can virtual bus, no exosuit) whose cart fails once running:
    one line, exit 1, and the log and the summary (with the error) are written."""
    from bridge.runtime import BridgeSession

    async def unplugged(self: BridgeSession) -> None:
        raise CartError("the cart's link failed (unplugged in this test)")

    monkeypatch.setattr(BridgeSession, "_cart_task", unplugged)
    cfg = _config_toml(tmp_path, _write_csv(tmp_path / "a.csv"), "")
    rc = cli.main(["run", str(cfg), "--no-view"])
    err = capsys.readouterr().err
    assert rc == 1
    assert "hilbo run: error: the cart's link failed (unplugged in this test)" in err
    assert "Traceback" not in err and "ExceptionGroup" not in err
    # The log was named as the session began (what a crash would leave to resume).
    found = re.search(r"^hilbo run: log (\S+\.mcap)$", err, flags=re.M)
    assert found, err
    log_path = Path(found.group(1))
    summary = json.loads(log_path.with_suffix(".summary.json").read_text())
    assert "unplugged in this test" in summary["error"] and summary["end_reason"] == "error"
    assert summary["n_evaluations"] == 0 and summary["log"] == str(log_path)
    kinds = [e["kind"] for e in read_log(log_path).data("/events")]
    assert kinds[-2:] == ["session_end", "session_error"]
