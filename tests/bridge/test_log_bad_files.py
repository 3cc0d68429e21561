"""Bad session logs: damage inside mcap's parser, files that are not regular, a FIFO as the
``previous_log`` of a resumed session, and the mode of ``hilbo log recover``'s output."""

from __future__ import annotations

import logging
import os
import stat
import struct
from pathlib import Path

import numpy as np
import pytest
from file_inputs import NOT_REGULAR, load_fuzz_script, not_regular_file
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bridge.cli.main import main
from bridge.log import LogError, SessionLog
from bridge.log.errors import LogFormatError
from bridge.log.reader import read_log, recover
from bridge.log.resume import rebuild_optimizer
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(60)

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "logs" / "v3" / "session.mcap"
_RECORD = struct.Struct("<BQ")
_CHUNK = 0x06


def chunk_length_of_2_63(src: Path, dst: Path) -> Path:
    """A copy of ``src`` whose first chunk says its records are 2^63 bytes long (mcap's reader
    then asks for a read of 2^63 bytes: OverflowError)."""
    data = bytearray(src.read_bytes())
    p = 8
    while data[p] != _CHUNK:
        p += _RECORD.size + _RECORD.unpack_from(data, p)[1]
    # start, end, uncompressed size (3 x u64), uncompressed crc (u32), compression (u32 + text)
    q = p + _RECORD.size + 8 * 3 + 4
    q += 4 + int.from_bytes(data[q:q + 4], "little")
    data[q:q + 8] = (1 << 63).to_bytes(8, "little")
    dst.write_bytes(bytes(data))
    return dst


def one_line_error(err: str, *needles: str) -> None:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_overflow_inside_mcaps_reader_is_a_damaged_record(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    bad = chunk_length_of_2_63(GOLDEN, tmp_path / "overflow.mcap")
    contents = read_log(bad)
    # The chunk is skipped as damaged, the records after it are read.
    assert len(contents.damage) == 1 and "OverflowError" in contents.damage[0].reason
    assert 0 < len(contents.messages) < len(read_log(GOLDEN).messages)
    assert main(["log", "info", str(bad)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert main(["review", str(bad), "--out", str(tmp_path / "r")]) == 1  # damaged: reviewed, exit 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "is damaged inside the file" in err


@pytest.fixture(params=NOT_REGULAR)
def not_a_file(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    return not_regular_file(request.param, tmp_path, "log.mcap")


def test_a_log_that_is_not_a_regular_file_is_refused_at_once(
    not_a_file: tuple[Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    path, kind = not_a_file
    with pytest.raises(LogFormatError, match=kind):  # "a FIFO", "a directory", ...
        read_log(path)
    for argv in (["log", "info", str(path)], ["review", str(path)]):
        assert main(argv) == 1
        one_line_error(capsys.readouterr().err, str(path), kind)


def test_a_fifo_as_the_previous_log_of_a_resumed_session(tmp_path: Path) -> None:
    pipe = tmp_path / "old.mcap"
    os.mkfifo(pipe)
    new = tmp_path / "new.mcap"
    # A resumed session's file that crashed before its first snapshot: resuming it reads the
    # previous log first, here a FIFO that no one writes.
    with SessionLog(new, session_id="s1", config_json={}, previous_log=pipe, flush_interval_s=None) as log:
        log.log_breath(BreathRecord(t_s=1.0, vo2_ml_min=1000.0, vco2_ml_min=800.0))
    with pytest.raises(LogError, match="FIFO"):
        rebuild_optimizer(new)


def test_mutated_logs_are_read_or_refused_never_a_traceback(tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR)  # damaged logs warn by design
    mutate = load_fuzz_script().mutate
    data = GOLDEN.read_bytes()
    rng = np.random.default_rng(20261206)
    copy = tmp_path / "m.mcap"
    outcomes = {"read": 0, "refused": 0}
    for _ in range(200):
        copy.write_bytes(mutate(data, rng))
        try:
            read_log(copy)
        except LogError:
            outcomes["refused"] += 1
        else:
            outcomes["read"] += 1
    assert outcomes["read"] > 0 and sum(outcomes.values()) == 200


@pytest.mark.parametrize(("config", "mode"), [({}, 0o600), ({"session": {"file_mode": "0640"}}, 0o640)])
def test_recover_writes_the_sessions_file_mode(tmp_path: Path, config: dict[str, object], mode: int) -> None:
    src = tmp_path / "s.mcap"
    with SessionLog(src, session_id="s1", config_json=config, flush_interval_s=None) as log:
        log.log_breath(BreathRecord(t_s=1.0, vo2_ml_min=1000.0, vco2_ml_min=800.0))
    old_umask = os.umask(0)  # the mode must not depend on the umask
    try:
        recover(src, tmp_path / "r.mcap")
    finally:
        os.umask(old_umask)
    assert stat.S_IMODE((tmp_path / "r.mcap").stat().st_mode) == mode
    assert main(["log", "recover", "--force", str(src), str(tmp_path / "r.mcap")]) == 0
    assert stat.S_IMODE((tmp_path / "r.mcap").stat().st_mode) == mode


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=st.lists(st.tuples(st.integers(min_value=0), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.none() | st.integers(min_value=0))
def test_read_log_raises_only_log_errors(tmp_path: Path, edits: list[tuple[int, int]],
                                         cut: int | None) -> None:
    data = bytearray(GOLDEN.read_bytes())
    for at, value in edits:
        data[at % len(data)] = value
    copy = tmp_path / "h.mcap"
    copy.write_bytes(bytes(data if cut is None else data[: cut % len(data)]))
    try:
        contents = read_log(copy)
    except LogError as err:
        assert "h.mcap" in str(err)
    else:
        assert contents.size_bytes == copy.stat().st_size
