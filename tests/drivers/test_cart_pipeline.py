"""process_line / iter_breaths / read_breath_file: one reject path for every caller."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.cart.csvmap import CsvBreathParser, CsvMapping
from drivers.cart.line import HbrLineParser, encode_line
from drivers.cart.pipeline import iter_breaths, process_line, read_breath_file
from drivers.cart.reasons import RejectReason
from drivers.cart.validate import BreathValidator
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(30)

GOOD = [BreathRecord(2.0 * i + 1.0, 800.0 + i, 700.0 + i, 20.0, None, 100.0) for i in range(4)]


def test_process_line_counts_decode_and_validation_rejects() -> None:
    v = BreathValidator()
    p = HbrLineParser()
    assert process_line(encode_line(GOOD[0], 0), p, v) == GOOD[0]
    assert process_line(b"# comment", p, v) is None
    assert process_line(b"junk", p, v) is None
    assert process_line(encode_line(GOOD[0], 0), p, v) is None
    assert v.counters == {RejectReason.GARBAGE: 1, RejectReason.DUPLICATE: 1}


def test_iter_breaths_keeps_order() -> None:
    lines = [encode_line(r, i) for i, r in enumerate(GOOD)]
    lines.insert(2, b"$HBR,99*0000")
    v = BreathValidator()
    assert list(iter_breaths(lines, HbrLineParser(), v)) == GOOD
    assert v.counters == {RejectReason.BAD_CHECKSUM: 1}


def test_read_breath_file_counts_framing_rejects(tmp_path: Path) -> None:
    path = tmp_path / "rec.hbr"
    lines = [encode_line(r, i) for i, r in enumerate(GOOD)]
    lines.insert(2, b"z" * 100 + b"\n")  # longer than max_line_bytes below
    path.write_bytes(b"# hilbo recording\n" + b"".join(lines))
    v = BreathValidator()
    assert read_breath_file(path, HbrLineParser(), v, max_line_bytes=64) == GOOD
    assert v.counters == {RejectReason.TOO_LONG: 1}


def test_read_breath_file_keeps_a_last_line_without_newline(tmp_path: Path) -> None:
    path = tmp_path / "rec.hbr"
    path.write_bytes(encode_line(GOOD[0], 0) + encode_line(GOOD[1], 1).rstrip(b"\r\n"))
    assert read_breath_file(path, HbrLineParser()) == GOOD[:2]


def test_config_errors_propagate(tmp_path: Path) -> None:
    path = tmp_path / "wrong.csv"
    path.write_text("time,oxygen,co2\n1,500,400\n")
    with pytest.raises(DriverConfigError, match=r"no column .VO2. or .VCO2. in the header"):
        read_breath_file(path, CsvBreathParser(CsvMapping("time", "VO2", "VCO2", header_row=0)))
