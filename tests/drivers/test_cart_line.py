"""hilbo-line codec: golden bytes, CRC reference values, round trips, each decode reason."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.cart.errors import EncodeError
from drivers.cart.line import (
    MAX_LINE_BYTES,
    HbrLineParser,
    ParsedBreath,
    crc16,
    encode_line,
    parse_line,
)
from drivers.cart.reasons import RejectReason
from drivers.errors import DecodeError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(30)

FULL = BreathRecord(t_s=12.345, vo2_ml_min=1234.5, vco2_ml_min=1000.0, ve_l_min=30.2, rer=0.81, hr_bpm=120.0)
GOLDEN_FULL = b"$HBR,7,12.345,1234.5,1000.0,30.2,0.81,120.0*4D32\r\n"
GOLDEN_MIN = b"$HBR,0,3.0,250.0,200.0,,,*1C76\r\n"


def bitwise_crc16_ccitt_false(data: bytes) -> int:
    """Independent reference: the textbook MSB-first loop (the C code in FORMAT.md)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def with_crc(body: bytes) -> bytes:
    """A line with a correct checksum around an arbitrary body (to test field errors)."""
    return b"$" + body + b"*" + f"{crc16(body):04X}".encode() + b"\r\n"


def test_crc16_check_value_of_the_catalogue() -> None:
    # CRC-16/CCITT-FALSE catalogue check value for the ASCII string "123456789".
    assert crc16(b"123456789") == 0x29B1
    assert bitwise_crc16_ccitt_false(b"123456789") == 0x29B1


@given(st.binary(max_size=300))
def test_crc16_matches_independent_implementation(data: bytes) -> None:
    assert crc16(data) == bitwise_crc16_ccitt_false(data)


def test_encode_golden_bytes() -> None:
    assert encode_line(FULL, 7) == GOLDEN_FULL
    assert encode_line(BreathRecord(3.0, 250.0, 200.0), 0) == GOLDEN_MIN
    body = GOLDEN_FULL[1 : GOLDEN_FULL.index(b"*")]
    assert bitwise_crc16_ccitt_false(body) == 0x4D32


def test_parse_golden_bytes() -> None:
    assert parse_line(GOLDEN_FULL) == ParsedBreath(FULL, 7)
    assert parse_line(GOLDEN_MIN) == ParsedBreath(BreathRecord(3.0, 250.0, 200.0), 0)


def test_parse_accepts_lowercase_hex_and_missing_terminator() -> None:
    lower = GOLDEN_FULL.replace(b"*4D32", b"*4d32").rstrip(b"\r\n")
    assert parse_line(lower).record == FULL


def test_parse_accepts_c_printf_style_numbers() -> None:
    line = with_crc(b"HBR,4294967295,1e2,+1500.,1.2E3,.5,0.90,72")
    parsed = parse_line(line)
    assert parsed.seq == 2**32 - 1
    assert parsed.record == BreathRecord(100.0, 1500.0, 1200.0, 0.5, 0.9, 72.0)


def test_nan_and_inf_are_encoded_and_decoded_for_the_validator() -> None:
    line = encode_line(BreathRecord(1.0, math.nan, math.inf, None, None, -math.inf), 3)
    assert b",nan,inf,,,-inf*" in line
    rec = parse_line(line).record
    assert math.isnan(rec.vo2_ml_min) and rec.vco2_ml_min == math.inf and rec.hr_bpm == -math.inf


@pytest.mark.parametrize("seq", [-1, 2**32, 1.0, True, "3"])
def test_encode_rejects_bad_seq(seq: object) -> None:
    with pytest.raises(EncodeError, match="seq"):
        encode_line(FULL, seq)  # type: ignore[arg-type]


floats = st.floats(allow_nan=False, allow_infinity=False)
records = st.builds(
    BreathRecord,
    t_s=floats,
    vo2_ml_min=floats,
    vco2_ml_min=floats,
    ve_l_min=st.none() | floats,
    rer=st.none() | floats,
    hr_bpm=st.none() | floats,
)
seqs = st.integers(min_value=0, max_value=2**32 - 1)


@given(records, seqs)
def test_round_trip_is_exact(record: BreathRecord, seq: int) -> None:
    line = encode_line(record, seq)
    assert len(line.rstrip(b"\r\n")) <= MAX_LINE_BYTES
    assert parse_line(line) == ParsedBreath(record, seq)


@given(st.builds(BreathRecord, st.floats(), st.floats(), st.floats(), st.none() | st.floats()), seqs)
def test_round_trip_bytes_including_nan(record: BreathRecord, seq: int) -> None:
    line = encode_line(record, seq)
    assert encode_line(parse_line(line).record, seq) == line


@given(records, seqs, st.data())
def test_any_single_byte_corruption_is_rejected(record: BreathRecord, seq: int, data: st.DataObject) -> None:
    # A one-byte substitution is a burst of <= 8 bits: CRC-16 always catches it (or the
    # framing does, when the '$' or '*' itself is hit).
    line = encode_line(record, seq).rstrip(b"\r\n")
    pos = data.draw(st.integers(0, len(line) - 1), label="pos")
    new = data.draw(st.integers(0, 255).filter(lambda b: b != line[pos]), label="byte")
    corrupted = line[:pos] + bytes([new]) + line[pos + 1 :]
    with pytest.raises(DecodeError):
        parse_line(corrupted)


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        (b"x" * (MAX_LINE_BYTES + 1), RejectReason.TOO_LONG),
        (b"hello", RejectReason.GARBAGE),
        (b"$GPGGA,1,2*00", RejectReason.GARBAGE),
        (b"$HB", RejectReason.TRUNCATED),
        (b"$HBR,7,12.345,1234.5,100", RejectReason.TRUNCATED),
        (GOLDEN_FULL[:-4], RejectReason.TRUNCATED),  # "*4D" : checksum cut short
        (GOLDEN_FULL.replace(b"*4D32", b"*4D33"), RejectReason.BAD_CHECKSUM),
        (GOLDEN_FULL.replace(b"*4D32", b"*4D3G"), RejectReason.BAD_CHECKSUM),
        (GOLDEN_FULL.replace(b"*4D32", b"*4D321"), RejectReason.BAD_CHECKSUM),
        (GOLDEN_FULL.replace(b"1234.5", b"1243.5"), RejectReason.BAD_CHECKSUM),
        (with_crc(b"HBR,7,1.0,500.0,400.0,,"), RejectReason.FIELD_COUNT),
        (with_crc(b"HBR,7,1.0,500.0,400.0,,,,"), RejectReason.FIELD_COUNT),
        (with_crc(b"HBR,-1,1.0,500.0,400.0,,,"), RejectReason.BAD_SEQ),
        (with_crc(b"HBR,4294967296,1.0,500.0,400.0,,,"), RejectReason.BAD_SEQ),
        (with_crc(b"HBR,1.5,1.0,500.0,400.0,,,"), RejectReason.BAD_SEQ),
        (with_crc(b"HBR,7,,500.0,400.0,,,"), RejectReason.MISSING_FIELD),
        (with_crc(b"HBR,7,1.0,500.0,,,,"), RejectReason.MISSING_FIELD),
        (with_crc(b"HBR,7,1.0,5OO.0,400.0,,,"), RejectReason.BAD_NUMBER),
        (with_crc(b"HBR,7,1.0,500.0,400.0, 30,,"), RejectReason.BAD_NUMBER),
        (with_crc(b"HBR,7,1.0,1_000,400.0,,,"), RejectReason.BAD_NUMBER),
        (with_crc(b"HBR,7,1.0,500.0,400.0,,,0x48"), RejectReason.BAD_NUMBER),
        (with_crc("HBR,7,1.0,500.0,400.0,,,\u00b5".encode()), RejectReason.GARBAGE),
    ],
)
def test_each_fault_has_its_reason(line: bytes, reason: RejectReason) -> None:
    with pytest.raises(DecodeError) as info:
        parse_line(line)
    assert info.value.reason == reason


def test_parser_skips_comments_and_delegates_the_rest() -> None:
    parser = HbrLineParser()
    assert parser.parse(b"# recorded 2024-05-01 by hilbo virtual-cart") is None
    assert parser.parse(GOLDEN_FULL) == ParsedBreath(FULL, 7)
    with pytest.raises(DecodeError):
        parser.parse(b"not a line")
